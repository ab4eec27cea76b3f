"""Render views of a saved .blend with EEVEE (and optionally Cycles) in a separate process.

EEVEE needs an OpenGL context; a background Blender or bpy as a module gets one (software EGL) in a fresh
process, and keeping it out of the calling process leaves that session clean. Runs as either
    python blender_addon/eevee_worker.py FILE.blend SCENE OUT_DIR [--engines E1,E2] [--cameras C1,C2] [--samples N]
    blender -b FILE.blend --python blender_addon/eevee_worker.py -- FILE.blend SCENE OUT_DIR [...]
Writes OUT_DIR/{ENGINE}_{k}.exr for camera k (the scene camera when none is named) and prints one line
"SECONDS ENGINE k seconds" per render; the first EEVEE render includes compiling the scene's shaders.
"""
import argparse
import sys
import time

import bpy

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
p = argparse.ArgumentParser()
p.add_argument("blend")
p.add_argument("scene")
p.add_argument("out")
p.add_argument("--engines", default="BLENDER_EEVEE")
p.add_argument("--cameras", default="")
p.add_argument("--samples", type=int, default=16)
ns = p.parse_args(argv)
if bpy.data.filepath != ns.blend:
    bpy.ops.wm.open_mainfile(filepath=ns.blend)
scene = bpy.data.scenes[ns.scene]
if bpy.context.window is not None:
    bpy.context.window.scene = scene
scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
cameras = [bpy.data.objects[name] for name in ns.cameras.split(",") if name] or [scene.camera]
for engine in ns.engines.split(","):
    scene.render.engine = engine
    if engine == "CYCLES":
        scene.cycles.samples, scene.cycles.use_denoising = ns.samples * 4, False
    else:
        scene.eevee.taa_render_samples = ns.samples
    for k, camera in enumerate(cameras):
        scene.camera = camera
        scene.render.filepath = f"{ns.out}/{engine}_{k}.exr"
        start = time.perf_counter()
        bpy.ops.render.render(write_still=True, scene=scene.name)
        print(f"SECONDS {engine} {k} {time.perf_counter() - start:.3f}", flush=True)
