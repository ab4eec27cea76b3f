"""Run in a separate process by test_apply: render a saved .blend with EEVEE and Cycles to EXR files.

EEVEE needs an OpenGL context (software EGL here); keeping it out of the pytest process keeps the suite's
own bpy session clean. Usage: python tests/eevee_render.py FILE.blend SCENE OUT_DIR"""
import sys
import time

import bpy

path, scene_name, out = sys.argv[1:4]
bpy.ops.wm.open_mainfile(filepath=path)
scene = bpy.data.scenes[scene_name]
bpy.context.window.scene = scene
scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
for engine, samples in (("BLENDER_EEVEE", 16), ("CYCLES", 64)):
    scene.render.engine = engine
    if engine == "CYCLES":
        scene.cycles.samples, scene.cycles.use_denoising = samples, False
    else:
        scene.eevee.taa_render_samples = samples
    scene.render.filepath = f"{out}/{engine}.exr"
    start = time.perf_counter()
    bpy.ops.render.render(write_still=True, scene=scene.name)
    print(f"SECONDS {engine} {time.perf_counter() - start:.2f}", flush=True)
