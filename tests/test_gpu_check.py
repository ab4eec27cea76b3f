"""`make gpu-check` on a machine without CUDA: the export of a real rendered bake, then every measurement on the CPU,
CUDA named as not measured with its reason (the GPU rows need a lent machine; docs/design-additions.md §37)."""
import json

import numpy as np
import pytest

from sg_lightfield.blender_addon.capture import capture
from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
from sg_lightfield.blender_addon.render import render_stage
from sg_lightfield.blender_addon.scene_analysis import build_plan
from sg_lightfield.bake_directory.bake_plan import BakeSettings, write_json_atomic
from sg_lightfield.headless import gpu_check


@pytest.mark.slow
def test_gpu_check_exports_a_rendered_bake_and_measures_every_row_it_can(tmp_path, capsys):
    scene = build_demo_scene("spheres")
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=1.5, lightfield_resolution=8, samples=2,
                                                      irradiance_detail=1))
    write_json_atomic(tmp_path / "bake" / "plan.json", plan.to_dict())  # as every front end writes it
    capture(scene, plan, tmp_path / "bake")
    render_stage(scene, plan, tmp_path / "bake")
    data_file = tmp_path / "lightfields.npz"
    assert gpu_check.main(["--export", str(tmp_path / "bake"), "--out", str(data_file)]) == 0
    data = gpu_check.load_data(data_file)
    assert data["images"].shape[1:] == (8, 8, 3) and len(data["images"]) == len(data["normals"]) > 0
    assert data["lobe_counts"].max() >= 1 and np.all(np.isfinite(data["images"].astype(np.float32)))

    report_file = tmp_path / "gpu_check.json"
    assert gpu_check.main(["--data", str(data_file), "--seconds", "1", "--production-texels", "64",
                           "--refit-texels", "16", "--refit-steps", "2",
                           "--report", str(report_file)]) == 0
    report = json.loads(report_file.read_text())
    cpu = report["training"][0]
    assert cpu["device"] == "cpu" and cpu["epochs"] >= 1 and np.isfinite(cpu["final_loss"])
    assert report["production"][0]["texels"] == 64 and report["production"][0]["texels_per_s"] > 0
    assert report["refits"][0]["lobe_refit_s"] >= 0 and report["refits"][0]["amplitude_refit_s"] >= 0
    import torch

    if not torch.cuda.is_available():
        assert report["devices"]["cuda"].startswith("not measured: torch sees no CUDA device")
        assert len(report["training"]) == 1
    printed = capsys.readouterr().out
    assert "training   cpu" in printed and "NaN" not in printed and "nan" not in printed


def test_seconds_to_loss_reads_the_first_epoch_at_or_below_it():
    curve = [[1.0, 0.5], [2.0, 0.3], [3.0, 0.2]]
    assert gpu_check.seconds_to_loss(curve, 0.3) == 2.0
    assert gpu_check.seconds_to_loss(curve, 0.1) is None


def test_gpu_check_refuses_a_file_that_is_not_its_export(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, images=np.zeros((1, 8, 8, 3)))
    with pytest.raises(SystemExit, match="not a gpu-check export \\(missing normals"):
        gpu_check.load_data(other)


def test_the_gpu_payload_keeps_what_bpy_loads_and_cycles_renders_with_on_nvidia():
    """headless/gpu_payload.py's trimmed bpy, on the real package: every library bpy links, the OSL query module
    and the image module it imports, Cycles' OptiX kernels and the PTX; not AMD kernels, other add-ons or USD's
    Python."""
    import subprocess
    from pathlib import Path

    from sg_lightfield.headless import gpu_payload

    root = gpu_payload._site_packages() / "bpy"  # the wheel's folder (an imported bpy names its scripts' module)
    linked = [line.split("=>")[1].split("(")[0].strip() for line in subprocess.run(
        ["ldd", str(root / "__init__.so")], capture_output=True, text=True, check=True).stdout.splitlines()
        if "=>" in line and str(root) in line]
    assert len(linked) > 20
    for library in linked:
        assert gpu_payload.kept_in_bpy(str(Path(library).resolve().relative_to(root.resolve()))), library
    kept = {str(path.relative_to(root)) for path in root.rglob("*")
            if gpu_payload.kept_in_bpy(str(path.relative_to(root)))}
    cycles = "5.0/scripts/addons_core/cycles/lib/"
    site = "5.0/python/lib/python3.11/site-packages/"
    for name in (cycles + "kernel_optix_osl_camera.ptx.zst", cycles + "kernel_optix.ptx.zst",
                 cycles + "kernel_compute_75.ptx.zst", site + "oslquery", site + "OpenImageIO",
                 "5.0/datafiles/studiolights/world/courtyard.exr", "5.0/datafiles/colormanagement/config.ocio"):
        assert name in kept, name
    assert not [k for k in kept if "kernel_gfx" in k or "kernel_sm_" in k or "/pxr/" in k or "__pycache__" in k]
    assert {k.split("/")[3] for k in kept if k.startswith("5.0/scripts/addons_core/") and k.count("/") > 3} == \
        {"cycles"}


@pytest.mark.slow
def test_the_egl_stand_in_renders_eevee_on_the_first_egl_device(tmp_path):
    """headless/egl_device_display.c, built as the payload builds it: with it first on the library path, bpy's EEVEE
    gets its context from the first EGL device (here Mesa's software one) and renders; the lead for lent GPU machines
    whose default display hangs (docs/design-additions.md §49)."""
    import os
    import subprocess
    import sys

    from sg_lightfield.headless import gpu_payload

    library = gpu_payload.build_egl_device_display(tmp_path / "egl_device")
    assert library.is_file() and (library.parent / "libEGL_real.so.1").is_file()
    script = ("import bpy, numpy\n"
              "scene = bpy.context.scene\n"
              "scene.render.engine = 'BLENDER_EEVEE'\n"
              "scene.render.resolution_x, scene.render.resolution_y = 24, 16\n"
              "scene.eevee.taa_render_samples = 1\n"
              f"scene.render.filepath = {str(tmp_path / 'cube.png')!r}\n"
              "bpy.ops.render.render(write_still=True)\n"
              "import gpu\n"
              "print('RENDERER', gpu.platform.renderer_get())\n")
    env = {**os.environ, "LD_LIBRARY_PATH": str(library.parent) + os.pathsep + os.environ.get("LD_LIBRARY_PATH", ""),
           "SGLF_EGL_DEVICE_LOG": "1", "PYTHONPATH": ""}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "egl_device_display: the default display is device 0 of" in out.stderr and "(a display)" in out.stderr
    assert "RENDERER" in out.stdout and (tmp_path / "cube.png").stat().st_size > 0
