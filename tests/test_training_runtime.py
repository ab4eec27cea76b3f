"""The training runtime: Install Training Runtime makes a Python with torch in the extension's user directory
(online from the package index this machine reaches, or offline from a folder of wheels), a bake trains through it,
Remove deletes it; a cancelled install leaves nothing that counts as a runtime."""
import json
import subprocess
import time

import bpy
import pytest

from sg_lightfield.bake_directory.bake_plan import BakeSettings
from sg_lightfield.blender_addon import training_runtime as tr
from sg_lightfield.blender_addon.apply import remove_bake
from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
from sg_lightfield.blender_addon.pipeline import BakeJob
from sg_lightfield.blender_addon.training_runtime import TORCH_HELP


@pytest.mark.parametrize("system, nvidia, options, accelerator", [
    ("linux", False, ["--extra-index-url", tr.TORCH_CPU_INDEX], "cpu"),  # PyPI's Linux torch pulls CUDA libraries
    ("linux", True, [], "cuda"),  # PyPI's Linux torch is the CUDA build
    ("win32", True, ["--extra-index-url", tr.TORCH_CUDA_INDEX], "cuda"),  # PyPI's Windows torch is CPU only
    ("win32", False, [], "cpu"),
    ("darwin", False, [], "cpu or Apple GPU"),
])
def test_the_automatic_install_picks_cuda_wheels_only_where_an_nvidia_driver_is(tmp_path, system, nvidia, options,
                                                                                 accelerator):
    plan = tr.plan_install(tmp_path, system=system, nvidia=nvidia, base_python="python")
    assert (plan.pip_options, plan.accelerator, plan.needs_network) == (options, accelerator, True)
    assert plan.target == tmp_path / tr.RUNTIME_FOLDER and plan.staging.name == tr.RUNTIME_FOLDER + ".partial"
    assert "torch==2.13.0" in plan.description() and str(plan.target) in plan.description()


def test_bad_install_choices_are_refused_with_one_clear_sentence(tmp_path):
    with pytest.raises(tr.RuntimeInstallError, match="does not exist"):
        tr.plan_install(tmp_path, source="wheels", wheel_dir=str(tmp_path / "missing"))
    (tmp_path / "wheels").mkdir()
    (tmp_path / "wheels" / "numpy-1.26.4-cp311-cp311-any.whl").write_bytes(b"")
    with pytest.raises(tr.RuntimeInstallError, match=r"no torch wheel \(torch-\*\.whl\)"):
        tr.plan_install(tmp_path, source="wheels", wheel_dir=str(tmp_path / "wheels"))
    with pytest.raises(tr.RuntimeInstallError, match="unknown runtime source"):
        tr.plan_install(tmp_path, source="conda")
    with pytest.raises(tr.RuntimeInstallError, match="Allow Online Access"):
        tr.RuntimeInstall(tr.plan_install(tmp_path, source="pip"), online_allowed=False)
    (tmp_path / "wheels" / "torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"")
    offline = tr.plan_install(tmp_path, source="wheels", wheel_dir=str(tmp_path / "wheels"))
    assert offline.pip_options == ["--no-index", "--find-links", str(tmp_path / "wheels")]
    assert not offline.needs_network and offline.accelerator == "cpu"
    tr.RuntimeInstall(offline, online_allowed=False)  # offline needs no online access


def test_a_cancelled_install_leaves_nothing_that_counts_as_a_runtime(tmp_path):
    install = tr.RuntimeInstall(tr.plan_install(tmp_path, source="pip")).start()
    deadline = time.monotonic() + 120
    while install.progress.fraction < 0.08 and time.monotonic() < deadline:  # the venv is made, pip is running
        time.sleep(0.1)
    install.cancel()
    progress = install.wait(120)
    assert progress.done and progress.error == "cancelled"
    assert tr.installed_runtime(tmp_path) is None
    assert not (tmp_path / tr.RUNTIME_FOLDER).exists() and not (tmp_path / (tr.RUNTIME_FOLDER + ".partial")).exists()


@pytest.mark.slow
def test_install_from_the_reachable_index_then_a_bake_trains_through_the_runtime_and_remove_deletes_it(
        tmp_path, monkeypatch):
    monkeypatch.delenv(tr.ENV_VAR, raising=False)
    system = bpy.context.preferences.system
    online = system.use_online_access
    system.use_online_access = True  # what the user allows in Preferences > System > Network
    try:
        install = tr.RuntimeInstall(tr.plan_install(tmp_path / "user", source="pip"),
                                    online_allowed=bpy.app.online_access).start()
        fractions = []
        while install.running:
            fractions.append(install.progress.fraction)
            time.sleep(0.2)
        progress = install.wait()
    finally:
        system.use_online_access = online
    assert progress.error == "" and progress.fraction == 1.0, progress.log[-5:]
    assert fractions == sorted(fractions) and progress.message.startswith("installed: torch 2.13.0")
    python = tr.installed_runtime(tmp_path / "user")
    record = json.loads((tmp_path / "user" / tr.RUNTIME_FOLDER / tr.MARKER).read_text())
    assert python is not None and record["torch"].startswith("2.13.0") and record["source"] == "pip"
    out = subprocess.run([str(python), "-c", "import torch, numpy, OpenEXR; print(torch.__version__)"],
                         capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.startswith("2.13.0")

    scene = build_demo_scene("demo:spheres")
    settings = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=2,
                                        sg_count=2, training_budget_s=2.0)
    job = BakeJob(scene, settings, tmp_path / "bake", stages=("capture", "render", "train"), training="worker",
                  runtime_dir=tmp_path / "user")
    job.run()
    assert job.training_python == "the installed training runtime"
    assert job.results["train"]["event"] == "stage" and (tmp_path / "bake" / "sg_lightfield.exr").is_file()
    remove_bake(scene)

    assert tr.remove_runtime(tmp_path / "user") and tr.installed_runtime(tmp_path / "user") is None
    assert not (tmp_path / "user" / tr.RUNTIME_FOLDER).exists()


def test_the_training_python_is_chosen_in_order_and_a_broken_override_is_skipped(tmp_path, monkeypatch):
    """Preference, then SGLF_TORCH_PYTHON, then the installed runtime, then this Python; each only when it imports
    what training needs (PROBE). An unfinished install (no marker) is not a runtime."""
    import sys

    venv = tmp_path / "user" / tr.RUNTIME_FOLDER
    (venv / "bin").mkdir(parents=True)
    wrapper = venv / "bin" / "python"  # stands in for the runtime's Python: this test's Python, which has torch
    wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    wrapper.chmod(0o755)
    monkeypatch.setenv(tr.ENV_VAR, str(tmp_path / "no-such-python"))
    assert tr.installed_runtime(tmp_path / "user") is None  # no marker: an unfinished install
    assert tr.find_torch_python("", tmp_path / "user") == (sys.executable, "this Python")
    (venv / tr.MARKER).write_text("{}")
    assert tr.find_torch_python("", tmp_path / "user") == (str(venv / "bin" / "python"),
                                                           "the installed training runtime")
    monkeypatch.setenv(tr.ENV_VAR, sys.executable)
    assert tr.find_torch_python("", tmp_path / "user")[1] == tr.ENV_VAR
    assert tr.find_torch_python(str(tmp_path / "missing"), tmp_path / "user")[1] == tr.ENV_VAR
    assert tr.find_torch_python(sys.executable, tmp_path / "user")[1] == "the Python with torch preference"
    assert "Install Training Runtime" in TORCH_HELP and tr.ENV_VAR in TORCH_HELP and "Python with torch" in TORCH_HELP
    tried = []
    no_torch = tmp_path / "plain-python"  # a Python that runs but has no torch
    no_torch.write_text('#!/bin/sh\nexec /usr/bin/env -i /bin/false "$@"\n')
    no_torch.chmod(0o755)
    monkeypatch.setenv(tr.ENV_VAR, str(tmp_path / "gone"))
    tr.find_torch_python(str(no_torch), tmp_path / "user", tried)
    assert tried[:2] == [f"the Python with torch preference: {no_torch}", f"{tr.ENV_VAR}: {tmp_path / 'gone'} (no such file)"]
    message = tr.missing_torch_message(TORCH_HELP, tried)
    assert message.startswith(TORCH_HELP) and str(no_torch) in message
