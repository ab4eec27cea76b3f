"""Render views of a saved .blend with EEVEE (and optionally Cycles) in a separate process.

EEVEE needs an OpenGL context; a background Blender or bpy as a module gets one (software EGL) in a fresh
process, and keeping it out of the calling process leaves that session clean. Runs as either
    python blender_addon/eevee_worker.py FILE.blend SCENE OUT_DIR [--engines E1,E2] [--cameras C1,C2] [--samples N]
                                         [--best-lighting] [--without-bake]
    blender -b FILE.blend --python blender_addon/eevee_worker.py -- FILE.blend SCENE OUT_DIR [...]
Writes OUT_DIR/{ENGINE}_{k}.exr for camera k (the scene camera when none is named) and prints one line
"SECONDS ENGINE k seconds" per render; the first EEVEE render includes compiling the scene's shaders.

--best-lighting sets EEVEE up as well as Blender allows (DESIGN section 10): screen-space ray tracing and fast GI
on at full resolution and quality (the rays' temporal denoising off), ray-traced refraction for transmissive
materials (glass), and a volume probe over the scene (capturing emission) and a sphere probe at its centre baked
with Blender's own light-probe bake; with the bake, it lights what the bake leaves to the renderer (glass,
cut-outs, the coat over a baked base).
--without-bake also gives the baked slots their original materials back (the scene's bake record): EEVEE alone,
the comparison a user makes. Only the worker's copy of the scene changes.
--world-probe-too renders every EEVEE view a second time with the sphere probe removed (reflections from the world's
probe, where screen tracing misses), into {ENGINE}_{k}_world_probe.exr, printing "SECONDS_WORLD_PROBE ENGINE k
seconds": which of the two is better depends on the scene (docs §53), and the caller keeps the better one.
"""
import argparse
import json
import sys
import time

import bpy
from mathutils import Vector

BAKE_RECORD_KEY = "sglf_bake"  # blender_addon/apply.py: {object: {slot index: original material}}
PROBE_MARGIN = 1.1  # the volume probe covers the scene's bounding box and 10 % more
SPHERE_PROBE = "SGLF sphere probe"


def restore_originals(scene):
    """The original materials back in the slots the bake switched (apply.baked_slots' reading of the record: this
    script runs without the add-on on its path)."""
    for object_name, slots in json.loads(scene.get(BAKE_RECORD_KEY, "{}")).items():
        obj = scene.objects.get(object_name) or bpy.data.objects.get(object_name)  # instanced objects too
        for index, original in slots.items():
            if obj is not None and int(index) < len(obj.material_slots) and original in bpy.data.materials:
                obj.material_slots[int(index)].material = bpy.data.materials[original]


def transmits(material) -> bool:
    """Whether a material's nodes (node groups included) hold a glass or refraction BSDF or a Principled BSDF with
    transmission."""
    def visit(tree, seen):
        for node in tree.nodes:
            if node.type in ("BSDF_GLASS", "BSDF_REFRACTION"):
                return True
            if node.type == "BSDF_PRINCIPLED":
                weight = node.inputs.get("Transmission Weight")
                if weight is not None and (weight.is_linked or weight.default_value > 0):
                    return True
            group = getattr(node, "node_tree", None)
            if node.type == "GROUP" and group is not None and group.name not in seen:
                seen.add(group.name)
                if visit(group, seen):
                    return True
        return False
    return material is not None and material.node_tree is not None and visit(material.node_tree, set())


def best_lighting(scene):
    """Ray tracing on (refraction too, for transmissive materials), a volume and a sphere probe baked (see the
    docstring)."""
    eevee = scene.eevee
    eevee.use_raytracing, eevee.ray_tracing_method = True, "SCREEN"
    eevee.use_fast_gi = True
    options = eevee.ray_tracing_options  # full resolution and quality (defaults: half resolution, quality 0.25)
    options.resolution_scale, options.screen_trace_quality = "1", 1.0
    # Temporal denoising of the traced rays off: in a final render it cost EEVEE alone 0.0845 against 0.0793 FLIP
    # on demo:materials' camera view (metals 0.336 against 0.274), at 16 and at 64 samples (docs §45)
    options.denoise_temporal = False
    eevee.fast_gi_resolution, eevee.fast_gi_quality = "1", 1.0
    for material in bpy.data.materials:  # instanced collections' objects' too
        if transmits(material):
            material.use_raytrace_refraction = True
    corners = [obj.matrix_world @ Vector(c) for obj in scene.objects if obj.type == "MESH" and not obj.hide_render
               for c in obj.bound_box]
    if not corners:  # nothing for probes to capture
        return
    lo = Vector([min(c[i] for c in corners) for i in range(3)])
    hi = Vector([max(c[i] for c in corners) for i in range(3)])
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * PROBE_MARGIN
    volume_data = bpy.data.lightprobes.new("SGLF volume probe", "VOLUME")
    volume_data.resolution_x = volume_data.resolution_y = volume_data.resolution_z = 8
    if hasattr(volume_data, "capture_emission"):
        volume_data.capture_emission = True
    volume = bpy.data.objects.new("SGLF volume probe", volume_data)
    volume.location, volume.scale = centre, [max(h, 1e-3) for h in half]
    sphere_data = bpy.data.lightprobes.new(SPHERE_PROBE, "SPHERE")
    sphere_data.influence_distance = max(half) * 2
    sphere = bpy.data.objects.new(SPHERE_PROBE, sphere_data)
    sphere.location = centre
    for probe in (volume, sphere):
        scene.collection.objects.link(probe)
    view_layer = scene.view_layers[0]
    start = time.perf_counter()
    with bpy.context.temp_override(scene=scene, view_layer=view_layer, active_object=volume, object=volume,
                                   selected_objects=[volume, sphere]):
        bpy.ops.object.lightprobe_cache_bake(subset="ALL")
    print(f"PROBE BAKE SECONDS {time.perf_counter() - start:.3f}", flush=True)


def eevee_engine(engine: str = "BLENDER_EEVEE") -> str:
    """Blender 4.2-4.5 call EEVEE "BLENDER_EEVEE_NEXT"; files keep the name asked for."""
    return "BLENDER_EEVEE_NEXT" if engine == "BLENDER_EEVEE" and bpy.app.version < (5, 0, 0) else engine


def main(argv):
    p = argparse.ArgumentParser()
    p.add_argument("blend")
    p.add_argument("scene")
    p.add_argument("out")
    p.add_argument("--engines", default="BLENDER_EEVEE")
    p.add_argument("--cameras", default="")
    p.add_argument("--samples", type=int, default=16)
    p.add_argument("--best-lighting", action="store_true")
    p.add_argument("--without-bake", action="store_true")
    p.add_argument("--world-probe-too", action="store_true")
    ns = p.parse_args(argv)
    if bpy.data.filepath != ns.blend:
        bpy.ops.wm.open_mainfile(filepath=ns.blend)
    scene = bpy.data.scenes[ns.scene]
    if bpy.context.window is not None:
        bpy.context.window.scene = scene
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    if ns.without_bake:
        restore_originals(scene)
    if ns.best_lighting or ns.without_bake:
        best_lighting(scene)
    cameras = [bpy.data.objects[name] for name in ns.cameras.split(",") if name] or [scene.camera]
    for engine in ns.engines.split(","):
        scene.render.engine = eevee_engine(engine)
        if engine == "CYCLES":
            scene.cycles.samples, scene.cycles.use_denoising = ns.samples * 4, False
        else:
            scene.eevee.taa_render_samples = ns.samples
        render_views(scene, cameras, f"{ns.out}/{engine}", "SECONDS", engine)
    if ns.world_probe_too and SPHERE_PROBE in bpy.data.objects:
        bpy.data.objects.remove(bpy.data.objects[SPHERE_PROBE])
        for engine in ns.engines.split(","):
            if engine != "CYCLES":
                scene.render.engine = eevee_engine(engine)
                render_views(scene, cameras, f"{ns.out}/{engine}", "SECONDS_WORLD_PROBE", engine, "_world_probe")


def render_views(scene, cameras, prefix, tag, engine, suffix=""):
    for k, camera in enumerate(cameras):
        scene.camera = camera
        scene.render.filepath = f"{prefix}_{k}{suffix}.exr"
        start = time.perf_counter()
        bpy.ops.render.render(write_still=True, scene=scene.name)
        print(f"{tag} {engine} {k} {time.perf_counter() - start:.3f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
