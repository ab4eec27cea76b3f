"""Render farms: the bake as an Open Job Description template run locally with openjd-cli, and a Flamenco 3 job
type whose compiled task graph is checked under node. Each task is a separate process over one shared bake
directory, as on a farm."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sg_lightfield.bake_directory.exr_io import read_exr
from sg_lightfield.headless.bake import parse_args, script_args

REPO = Path(__file__).resolve().parent.parent
TEMPLATE = REPO / "farm" / "openjd" / "sg_lightfield_bake.yaml"
FLAMENCO = REPO / "farm" / "flamenco" / "sg_lightfield_bake.js"
OPENJD = Path(sys.executable).parent / "openjd"
# small enough for the suite, with enough tiles that each of 3 render tasks gets some; the evaluation by Cycles only
# (a farm node without OpenGL; EEVEE's evaluation has tests of its own)
SETTINGS = {"samples": 4, "texel-density": 2, "lightfield-resolution": 8, "training-budget": 3,
            "lobe-refit-steps": 10, "reference-samples": 16, "no-eevee-evaluation": True}
TILE_MEGAPIXELS = "0.002"  # the spheres' texels alone in six or more tiles (the lightmap-only floor has no light field)


def openjd(out: Path, settings: Path, *extra, check=True, **popen):
    command = [str(OPENJD), "run", str(TEMPLATE), "-p", "BlendFile=demo:spheres", "-p", f"OutputDir={out}",
               "-p", f"Python={sys.executable}", "-p", f"Repository={REPO}", "-p", "TileCount=3",
               "-p", f"TileMegapixels={TILE_MEGAPIXELS}", "-p", f"SettingsFile={settings}", *extra]
    if popen:
        return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, **popen)
    result = subprocess.run(command, capture_output=True, text=True, timeout=1800)
    if check:
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    return result


def kill_processes_of(out: Path, marker: str) -> int:
    """SIGKILL every process whose command line names `out` and `marker` (Linux /proc); how many were killed."""
    killed = 0
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if str(out).encode() in words and marker.encode() in words and b"openjd" not in words[0]:
            try:
                os.kill(int(cmdline.parent.name), signal.SIGKILL)
                killed += 1
            except ProcessLookupError:
                pass
    return killed


def tiles(out: Path) -> dict:
    return {p.relative_to(out).as_posix(): p for kind in ("lightfield", "env_visibility")
            for p in sorted((out / kind).glob("*.exr"))}


def test_the_openjd_template_is_valid_and_its_steps_call_the_bake_stages():
    check = subprocess.run([str(OPENJD), "check", str(TEMPLATE)], capture_output=True, text=True)
    assert check.returncode == 0 and "passes validation" in check.stdout, check.stdout + check.stderr
    summary = subprocess.run([str(OPENJD), "summary", str(TEMPLATE), "-p", "BlendFile=demo:spheres",
                              "-p", "OutputDir=/tmp/bake", "-p", f"Repository={REPO}", "-p", "TileCount=4",
                              "--output", "json"], capture_output=True, text=True)
    assert summary.returncode == 0, summary.stderr
    steps = {step["name"]: step for step in json.loads(summary.stdout)["steps"]}
    assert list(steps) == ["Capture", "Render", "Train", "ApplyEvaluate"]
    assert steps["Render"]["total_tasks"] == 4 and steps["Train"]["total_tasks"] == 1
    assert [d["step_name"] for d in steps["Render"]["dependencies"]] == ["Capture"]
    assert [d["step_name"] for d in steps["Train"]["dependencies"]] == ["Render"]
    assert [d["step_name"] for d in steps["ApplyEvaluate"]["dependencies"]] == ["Train"]


def flamenco_graph(**settings) -> dict:
    base = {"bake_dir": "/shared/bake", "preset": "draft", "device": "cpu", "tile_count": 4, "tile_megapixels": 4.0,
            "settings_file": "", "repository": "/opt/sglf", "torch_python": "/opt/sglf/.venv/bin/python",
            "blender_cmd": "{blender}", "blendfile": "/shared/shot.blend"}
    out = subprocess.run(["node", str(REPO / "tests" / "flamenco_harness.js"), str(FLAMENCO),
                          json.dumps({**base, **settings})], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.mark.skipif(shutil.which("node") is None, reason="needs node (Flamenco's job compiler is JavaScript)")
def test_the_flamenco_job_type_compiles_capture_renders_train_apply_with_their_dependencies():
    graph = flamenco_graph()
    tasks = {task["name"]: task for task in graph["tasks"]}
    assert list(tasks) == ["capture", "render-1", "render-2", "render-3", "render-4", "train", "apply-evaluate"]
    assert all(tasks[f"render-{i}"]["dependencies"] == ["capture"] for i in range(1, 5))
    assert tasks["train"]["dependencies"] == [f"render-{i}" for i in range(1, 5)]
    assert tasks["apply-evaluate"]["dependencies"] == ["train"]
    for name, task in tasks.items():
        (command,) = task["commands"]
        if name == "train":  # torch is not in Blender: an exec task in the Python that has it
            assert command["name"] == "exec" and task["type"] == "misc"
            assert command["parameters"]["args"][0] == "/opt/sglf/training/train_stage.py"
            from sg_lightfield.training.train_stage import main as train_main

            with pytest.raises(SystemExit) as exit_info:  # the worker's arguments parse (--help stops after that)
                train_main([*command["parameters"]["args"][1:], "--help"])
            assert exit_info.value.code == 0
            continue
        assert command["name"] == "blender-render" and task["type"] == "blender"
        assert command["parameters"]["blendfile"] == "/shared/shot.blend"
        ns = parse_args(script_args(["blender", *command["parameters"]["args"]]))  # bake.py's own parser
        assert str(ns.out) == "/shared/bake" and ns.preset == "draft" and ns.device == "cpu"
        expected = {"capture": ["capture"], "apply-evaluate": ["capture", "apply", "evaluate"]}.get(name, ["render"])
        assert ns.stages == expected and ns.tile == (f"{name.split('-')[1]}/4" if name.startswith("render") else None)
    settings = [s["key"] for s in graph["job_type"]["settings"]]
    assert {"bake_dir", "preset", "device", "tile_count", "torch_python", "blendfile"} <= set(settings)
    assert flamenco_graph(tile_count=0) == {"error": "tile_count must be a whole number from 1 to 1024, not 0"}
    assert "bake_dir is empty" in flamenco_graph(bake_dir="")["error"]
    with_settings = flamenco_graph(settings_file="/shared/q.json")["tasks"][0]["commands"][0]["parameters"]["args"]
    assert with_settings[with_settings.index("--settings") + 1] == "/shared/q.json"


@pytest.mark.slow
def test_the_openjd_job_runs_locally_its_tiles_equal_a_one_process_bake_and_a_killed_tile_reruns_alone(tmp_path):
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps(SETTINGS))
    farm, single = tmp_path / "farm", tmp_path / "single"

    # Capture and the three render tasks, each its own process, as on a farm
    openjd(farm, settings, "--step", "Render", "--run-dependencies")
    rendered = tiles(farm)
    assert len(rendered) >= 6  # two or more tiles for each render task

    # One share again, killed while it renders: atomic writes leave no file that counts as a finished tile
    index = json.loads((farm / "lightfield" / "index.json").read_text())
    share = [f"lightfield/{tile['file']}" for tile in index["tiles"] if tile["index"] % 3 == 1]  # share 2 of 3
    assert share
    for name in share:
        rendered[name].unlink()
    task = openjd(farm, settings, "--step", "Render", "--task-param", "Tile=2", "--no-run-dependencies",
                  start_new_session=True)
    deadline = time.monotonic() + 300
    while not list(farm.glob(".sglf-render-*")) and time.monotonic() < deadline and task.poll() is None:
        time.sleep(0.05)
    killed = kill_processes_of(farm, "--tile")  # the task's bake.py (openjd runs it in a session of its own)
    os.killpg(task.pid, signal.SIGKILL)
    task.wait()
    assert killed, "the render task was not running"
    assert not all((farm / name).is_file() for name in share)
    refused = openjd(farm, settings, "--step", "Train", "--no-run-dependencies", check=False)
    assert refused.returncode != 0 and "are not rendered" in refused.stdout + refused.stderr

    # The killed task re-run alone; then the whole job completes, skipping every finished task's work
    openjd(farm, settings, "--step", "Render", "--task-param", "Tile=2", "--no-run-dependencies")
    openjd(farm, settings)
    report = json.loads((farm / "report.json").read_text())
    assert {"atlas", "texels", "render", "train", "apply", "errors", "timings_s"} <= set(report)
    assert set(report["timings_s"]) == {"capture", "render", "train", "apply", "evaluate"}
    assert 0 < report["errors"]["flip"] < 0.5 and (farm / "baked.blend").is_file()
    assert (farm / "report.html").is_file()

    # The same tiles from one process: bit for bit
    one = subprocess.run([sys.executable, str(REPO / "headless" / "bake.py"), "--scene", "demo:spheres",
                          "--out", str(single), "--settings", str(settings), "--tile-megapixels", TILE_MEGAPIXELS,
                          "--stages", "capture,render"], capture_output=True, text=True, timeout=900)
    assert one.returncode == 0, one.stderr[-2000:]
    assert sorted(tiles(single)) == sorted(tiles(farm))
    for name, path in tiles(single).items():
        a, b = read_exr(path)[0], read_exr(farm / name)[0]
        assert a.shape == b.shape and np.array_equal(a, b), name


def test_a_settings_file_gives_every_task_the_same_quality_options_and_the_command_line_wins(tmp_path, capsys):
    settings = tmp_path / "q.json"
    settings.write_text(json.dumps({**SETTINGS, "uniform-sg-count": False, "preset": "preview"}))
    ns = parse_args(["--blend", "demo:spheres", "--out", str(tmp_path), "--settings", str(settings),
                     "--samples", "8"])
    assert (ns.samples, ns.texel_density, ns.lightfield_resolution, ns.training_budget_s) == (8, 2.0, 8, 3.0)
    assert ns.uniform_sg_count is False and ns.preset == "preview" and ns.reference_samples == 16
    assert ns.no_eevee_evaluation is True  # a true flag in the file is the option given
    assert parse_args(["--scene", "demo:spheres", "--out", str(tmp_path), "--settings="]).samples is None  # empty
    for bad, message in (({"out": "/elsewhere"}, "'out' is not a quality option"),
                         ({"samples": [1, 2]}, "'samples' must be a number, a word or true/false"),
                         ({"samples": "many"}, "argument --samples: invalid int value: 'many'")):
        settings.write_text(json.dumps(bad))
        with pytest.raises(SystemExit) as exit_info:
            parse_args(["--scene", "demo:spheres", "--out", str(tmp_path), "--settings", str(settings)])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    settings.write_text("{not json")
    with pytest.raises(SystemExit):
        parse_args(["--scene", "demo:spheres", "--out", str(tmp_path), "--settings", str(settings)])
    assert "not JSON" in capsys.readouterr().err
