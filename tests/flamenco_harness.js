// Runs a Flamenco 3 job-type script under node the way Flamenco's Manager does: the script gets the globals
// `author` (Task, Command), `path` and `print`, and compileJob(job) adds tasks to the job. Prints the compiled
// task graph as JSON: {"job_type": JOB_TYPE, "tasks": [{name, type, commands, dependencies}]}, or
// {"error": message} when compileJob throws (Flamenco then refuses the job with that message).
//
//   node tests/flamenco_harness.js farm/flamenco/sg_lightfield_bake.js '{"bake_dir": ...}'
"use strict";
const fs = require("fs");
const vm = require("vm");
const nodePath = require("path");

const [scriptPath, settingsJson] = process.argv.slice(2);

function Task(name, type) {
    const task = { name, type, commands: [], dependencies: [] };
    task.addCommand = (command) => { task.commands.push(command); };
    task.addDependency = (other) => {
        if (!other || typeof other.name !== "string") throw new Error(`${name}: a dependency must be a task`);
        task.dependencies.push(other.name);
    };
    return task;
}

const context = {
    author: { Task, Command: (name, parameters) => ({ name, parameters }) },
    // Flamenco's path module is path/posix with stem() added
    path: Object.assign({}, nodePath.posix, { stem: (p) => nodePath.posix.parse(p).name }),
    print: () => {},
};
vm.createContext(context);
vm.runInContext(fs.readFileSync(scriptPath, "utf8") + "\nthis.JOB_TYPE = JOB_TYPE;", context, { filename: scriptPath });

const tasks = [];
const job = { settings: JSON.parse(settingsJson), created: new Date(0), addTask: (task) => tasks.push(task) };
try {
    context.compileJob(job);
} catch (error) {
    console.log(JSON.stringify({ error: String(error) }));
    process.exit(0);
}
const seen = new Set();
for (const task of tasks) {
    for (const dependency of task.dependencies) {
        if (!seen.has(dependency)) throw new Error(`${task.name} depends on ${dependency}, which was not added before it`);
    }
    seen.add(task.name);
}
console.log(JSON.stringify({
    job_type: context.JOB_TYPE,
    tasks: tasks.map(({ name, type, commands, dependencies }) => ({ name, type, commands, dependencies })),
}));
