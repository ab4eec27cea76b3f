"""Run the pipeline on this Python's bpy (another Blender release as a module) and print one JSON line per step.

    <python with bpy X> tests/blender_version_check.py OUT_DIR [EXTENSION_ZIP]
Training runs in SGLF_TORCH_PYTHON (the project's own Python with torch), as it does inside Blender. Used by
tests/test_blender_versions.py; each step reports "ok" or its error, so one failure does not hide the rest."""
import json
import os
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import sg_launch  # noqa: E402

sg_launch.load_package()
import bpy  # noqa: E402

OUT = Path(sys.argv[1])


def step(name, action):
    start = time.perf_counter()
    try:
        detail = action()
        print(json.dumps({"step": name, "ok": True, "detail": detail,
                          "seconds": round(time.perf_counter() - start, 1)}), flush=True)
        return True
    except Exception as error:  # noqa: BLE001 - every failure is reported, the next step still runs
        print(json.dumps({"step": name, "ok": False, "error": f"{type(error).__name__}: {error}",
                          "trace": traceback.format_exc()[-1500:]}), flush=True)
        return False


def install_extension(zip_path):
    def run():
        import addon_utils

        result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                          enable_on_install=True)
        module = "bl_ext.user_default.sg_lightfield"
        enabled = hasattr(bpy.types.Scene, "sg_lightfield")
        addon_utils.disable(module, default_set=True)
        if result != {"FINISHED"} or not enabled:
            raise RuntimeError(f"install returned {result}, enabled: {enabled}")
        return "installed, enabled and disabled"
    return run


def register_twice():
    from sg_lightfield import blender_addon

    for _ in range(2):
        blender_addon.register()
        assert bpy.ops.sg_lightfield.bake.poll() and hasattr(bpy.types.Scene, "sg_lightfield")
        blender_addon.unregister()
    # Unregistered for the renders below, as headless/bake.py runs: bpy 4.5 as a module waits forever at exit after
    # a Cycles render while an add-on's Scene property is registered (5.0 does not).
    return bpy.app.version_string


def bake_spheres():
    from sg_lightfield.bake_directory.bake_plan import BakeSettings
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.evaluate import evaluate_stage
    from sg_lightfield.blender_addon.pipeline import BakeJob

    scene = build_demo_scene("demo:spheres")
    settings = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=4, sg_count=4,
                                        training_budget_s=3.0, lobe_refit_steps=10)
    job = BakeJob(scene, settings, OUT / "spheres", stages=("capture", "render", "train", "apply"), training="worker")
    job.run()
    errors = evaluate_stage(scene, job.plan, OUT / "spheres", views=1, resolution=(64, 36), reference_samples=16)
    eevee, alone = errors.get("eevee") or {}, errors.get("eevee_without_bake") or {}
    return {"training_python": job.training_python, "flip": errors["flip"], "eevee_flip": eevee.get("flip"),
            "eevee_error": eevee.get("error"), "eevee_alone_flip": alone.get("flip"),
            "eevee_alone_error": alone.get("error")}


def capture_scene(name):
    def run():
        from sg_lightfield.bake_directory.bake_plan import BakeSettings
        from sg_lightfield.blender_addon.apply import remove_bake
        from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
        from sg_lightfield.blender_addon.pipeline import BakeJob

        scene = build_demo_scene(f"demo:{name}")
        job = BakeJob(scene, BakeSettings.from_preset("draft", texel_density=2.0), OUT / name, stages=("capture",))
        job.run()
        result = job.results["capture"]
        remove_bake(scene)
        return {"texels": int(result.texels)}
    return run


if __name__ == "__main__":
    if not os.environ.get("SGLF_TORCH_PYTHON"):
        sys.exit("set SGLF_TORCH_PYTHON to a Python with torch")
    ok = True
    if len(sys.argv) > 2:
        ok &= step("install the extension zip", install_extension(sys.argv[2]))
    ok &= step("register", register_twice)
    ok &= step("bake spheres (capture, render, train in a worker, apply, evaluate with EEVEE)", bake_spheres)
    ok &= step("capture demo:materials (textured materials, Cycles probe bakes)", capture_scene("materials"))
    ok &= step("capture demo:geometry (modifier stacks, text, curves, instances)", capture_scene("geometry"))
    sys.exit(0 if ok else 1)
