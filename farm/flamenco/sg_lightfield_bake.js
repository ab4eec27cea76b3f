// SG Lightfield bake as a Flamenco 3 job type. Copy this file into the Manager's `scripts/` folder (beside
// flamenco-manager.yaml) and restart the Manager; Blender's Flamenco add-on then offers "SG Lightfield Bake".
//
// Task graph: capture -> render-1 .. render-N (any Workers, each renders one share of the light-field tiles)
//             -> train (one Worker; a Python with torch) -> apply-evaluate (writes baked.blend and report.html).
// Every task is idempotent over the shared bake directory: a re-queued task reuses what is finished and complete,
// and train refuses to start while a render share is missing. docs/farms.md has the set-up step by step.

const JOB_TYPE = {
    label: "SG Lightfield Bake",
    description: "Bake glossy light fields into EEVEE materials as spherical Gaussians",
    settings: [
        // The scene's own panel settings, read in Blender when the job is submitted.
        { key: "bake_dir", type: "string", subtype: "dir_path", required: true, visible: "submission",
          eval: "bpy.path.abspath(C.scene.sg_lightfield.output_dir)",
          description: "Bake directory on storage every Worker sees" },
        { key: "preset", type: "string", required: true, visible: "submission",
          choices: ["draft", "preview", "production"],
          eval: "C.scene.sg_lightfield.preset.lower() if C.scene.sg_lightfield.preset != 'CUSTOM' else 'draft'",
          description: "Quality preset" },
        { key: "device", type: "string", required: true, visible: "submission", choices: ["cpu", "cuda"],
          eval: "C.scene.sg_lightfield.device.lower()",
          description: "cuda: render with OptiX and train on CUDA" },
        { key: "tile_count", type: "int32", default: 8, required: true, visible: "submission",
          description: "Render tasks; each renders an equal share of the light-field tiles" },
        { key: "tile_megapixels", type: "float", default: 4.0, visible: "submission",
          description: "Pixels per light-field tile (memory per render)" },
        { key: "settings_file", type: "string", subtype: "file_path", default: "", visible: "submission",
          description: "Optional JSON file of quality options (headless/bake.py --settings)" },
        // Where things are on the Workers (two-way variables of the Manager, e.g. {sglf} and {sglf_python}).
        { key: "repository", type: "string", default: "{sglf}", visible: "submission",
          description: "The SG Lightfield checkout (or installed extension folder) on the Workers" },
        { key: "torch_python", type: "string", default: "{sglf_python}", visible: "submission",
          description: "A Python 3.11 with torch 2.13, numpy, OpenEXR, scipy and Pillow on the Worker that trains" },
        { key: "blender_cmd", type: "string", default: "{blender}", visible: "hidden" },
        { key: "blendfile", type: "string", required: true, eval: "bpy.data.filepath", visible: "web",
          description: "The .blend to bake (read, never modified)" },
    ]
};

function bakeArgs(settings, stages, extra) {
    const args = ["--python", path.join(settings.repository, "headless", "bake.py"), "--",
                  "--out", settings.bake_dir, "--preset", settings.preset, "--device", settings.device,
                  "--tile-megapixels", String(settings.tile_megapixels || 4.0), "--stages", stages];
    if (settings.settings_file) {
        args.push("--settings", settings.settings_file);
    }
    return args.concat(extra || []);
}

function blenderTask(settings, name, stages, extra) {
    const task = author.Task(name, "blender");
    task.addCommand(author.Command("blender-render", {
        exe: settings.blender_cmd,
        exeArgs: "{blenderArgs}",
        argsBefore: [],
        blendfile: settings.blendfile,
        args: bakeArgs(settings, stages, extra),
    }));
    return task;
}

function compileJob(job) {
    const settings = job.settings;
    const tiles = settings.tile_count;
    if (!Number.isInteger(tiles) || tiles < 1 || tiles > 1024) {
        throw `tile_count must be a whole number from 1 to 1024, not ${tiles}`;
    }
    if (!settings.bake_dir) {
        throw "bake_dir is empty: set the Bake Directory in the SG Lightfield panel";
    }

    // Lightmap UVs and texel maps; apply-evaluate recomputes the same UVs in its own Blender.
    const capture = blenderTask(settings, "capture", "capture");
    job.addTask(capture);

    const renders = [];
    for (let i = 1; i <= tiles; i++) {
        const render = blenderTask(settings, `render-${i}`, "render", ["--tile", `${i}/${tiles}`]);
        render.addDependency(capture);
        job.addTask(render);
        renders.push(render);
    }

    // Training needs torch, which Blender's Python lacks: it runs in a Python that has it.
    const train = author.Task("train", "misc");
    train.addCommand(author.Command("exec", {
        exe: settings.torch_python,
        args: [path.join(settings.repository, "training", "train_stage.py"), "--out", settings.bake_dir,
               "--device", settings.device],
    }));
    for (const render of renders) {
        train.addDependency(render);
    }
    job.addTask(train);

    const applyEvaluate = blenderTask(settings, "apply-evaluate", "capture,apply,evaluate");
    applyEvaluate.addDependency(train);
    job.addTask(applyEvaluate);
}
