"""Evaluate stage: the baked scene against a Cycles path-traced reference, from a few fixed views.

Reference: the scene with its original materials, path traced by Cycles at `reference_samples` spp in two
independent halves (different seeds). Their difference measures the reference's own noise: the full
reference's noise RMSE is RMSE(half A, half B) / 2, reported next to the bake's error so a reader can see the
reference is good enough (noise well below the error). Test: the same views with the baked materials, which
Cycles evaluates through the same node group EEVEE uses (emission only), at test_samples (surfaces the bake leaves
alone are still path traced there), fewer than the reference's: a reference sample is cheap beside one through the
SG node groups.
Metrics on tone-mapped images (bake_directory/image_metrics.py): RMSE, PSNR, FLIP; pictures reference | bake | FLIP.
EEVEE, the engine the bake is for, renders the same views in a separate process (blender_addon/eevee_worker.py;
it needs an OpenGL context), with ray tracing and baked light probes lighting what the bake leaves to the renderer:
its error against the reference, its difference from Cycles' evaluation of the same nodes, its first-render time
(shader compilation and the probe bake included) and pictures reference | EEVEE | FLIP. EEVEE without the bake, set
up the same way, is what a user compares with (errors.eevee_without_bake; pictures reference | EEVEE alone | EEVEE
with the bake). Each side renders with a sphere probe at the scene's centre and with the world's probe alone, and
keeps the better (probe_setup, flip_by_probe_setup): which helps depends on the scene (docs §53).
Nothing of the scene changes: temporary cameras and material swaps are undone before returning.
The bake's own evaluation uses reference_samples_for(settings) and test_samples_for(settings).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

from ..bake_directory.bake_plan import BakeInputError
from ..bake_directory.bake_report import save_png, update_report
from ..bake_directory.image_metrics import flip, heat, psnr, rmse, tonemap
from .apply import BAKE_RECORD_KEY, baked_slots
from ..bake_directory.exr_io import read_exr
from .render import compute_device, quiet_stdout, render_still
from .capture import lightmap_owners
from .scene_analysis import active_scene, bake_targets, empty_node_material, principled_surface, unbaked
from .surface_probe import probe_material
from .surface_shaders import BAKED_BSDFS, leaves


def inside_line_of_sight(scene, centre, location, see_through=()):
    """`location`, or 90 % of the way to the first surface the line of sight from `centre` towards it meets
    (objects named in `see_through` and objects hidden in renders let it pass): an orbit camera around the baked
    objects of a closed room would otherwise film the back of a wall."""
    offset = location - centre
    distance, direction = offset.length, offset.normalized()
    origin, travelled = centre.copy(), 0.0
    with active_scene(scene) as depsgraph:
        while travelled < distance:
            hit, position, _, _, obj, _ = scene.ray_cast(depsgraph, origin, direction, distance=distance - travelled)
            if not hit:
                break
            travelled = (position - centre).length
            original = obj.original if obj is not None else None
            if original is not None and original.name not in see_through and not original.hide_render:
                return centre + direction * (0.9 * travelled)
            origin = position + direction * 1e-4 * distance
            travelled += 1e-4 * distance
    return location


def _view_cameras(scene, plan, count):
    """The scene camera, then cameras orbiting the bounding box of the objects with SGs (of every baked object where
    only irradiance is baked), looking at its centre."""
    cameras = []
    if scene.camera is not None:
        cameras.append((scene.camera, False))
    points = []
    framed = set(plan.sg_objects) or {o.name for o in plan.baked_objects}
    with active_scene(scene) as depsgraph:
        targets = bake_targets(scene, [o for o in plan.baked_objects if o.name in framed], depsgraph)
    for target in targets:
        points += [target.matrix @ Vector(corner) for corner in target.obj.bound_box]
    if not points:
        return cameras
    lo = Vector(np.min(np.array(points), axis=0))
    hi = Vector(np.max(np.array(points), axis=0))
    centre, radius = (lo + hi) / 2, max((hi - lo).length / 2, 1e-3)
    baked = set(framed)
    for k in range(count - len(cameras)):
        azimuth = math.radians(35 + 110 * k)
        data = bpy.data.cameras.new("SGLF evaluate")
        data.lens = 30
        camera = bpy.data.objects.new("SGLF evaluate", data)
        orbit = centre + radius * 2.2 * Vector((math.cos(azimuth), -math.sin(azimuth), 0.55))
        camera.location = inside_line_of_sight(scene, centre, orbit, baked)
        camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
        scene.collection.objects.link(camera)
        cameras.append((camera, True))
    return cameras[:count]


def _swap_to_originals(scene):
    """Put the original materials back into the baked slots; returns the undo list."""
    undo = []
    for slot, original in list(baked_slots(scene)):
        undo.append((slot, slot.material))
        slot.material = original
    return undo


# Error is reported per class of the visible surface's roughness (the bake's accuracy depends on it).
ROUGHNESS_CLASSES = (("roughness < 0.3", 0.0, 0.3), ("0.3 <= roughness < 0.6", 0.3, 0.6),
                     ("roughness >= 0.6", 0.6, float("inf")))


def surface_images(scene, camera, path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """What each pixel sees, by a quick render with every slot swapped to an emission, undone before returning:
    (H, W) roughness of the original material (NaN where the world shows), (H, W) index into the returned material
    names (-1 where the world shows or a pixel mixes materials), and those names."""
    record = json.loads(scene.get(BAKE_RECORD_KEY, "{}"))
    emissions, names, undo, created, created_groups = {}, [], [], [], []
    try:
        for obj in lightmap_owners(scene):  # the scene's objects and those its instances show
            for index, slot in enumerate(getattr(obj, "material_slots", [])):
                original_name = record.get(obj.name, {}).get(str(index))
                # an unrecorded slot may show a baked copy through data it shares with a recorded one (the hidden
                # source of instance copies): its original, so both swap in the same emission
                original = bpy.data.materials.get(original_name) if original_name else unbaked(slot.material)
                key = original.name if original is not None else ""
                if key not in emissions:
                    names.append(key or "(no material)")
                    material, groups = _surface_id_material(original, float(len(names)))
                    created.append(material)
                    created_groups.extend(groups)
                    emissions[key] = material
                undo.append((slot, slot.material))
                slot.material = emissions[key]
        transparent = scene.render.film_transparent
        scene.render.film_transparent = True
        try:
            scene.camera = camera
            scene.cycles.samples = 4
            render_still(scene, path)
            pixels, _, _ = read_exr(path, channels=["R", "G", "A"])
        finally:
            scene.render.film_transparent = transparent
    finally:
        for slot, material in reversed(undo):
            slot.material = material
        for material in created:
            bpy.data.materials.remove(material)
        for group in reversed(created_groups):
            if group.users == 0:
                bpy.data.node_groups.remove(group)
    value, number, alpha = (pixels[..., c].astype(np.float64) for c in range(3))
    covered = alpha > 0.5
    roughness = np.where(covered, value / np.maximum(alpha, 1e-6), np.nan)
    number = number / np.maximum(alpha, 1e-6)
    # the pixel filter blends neighbours' emissions at edges: a pixel counts for a material only when it is whole
    whole = (alpha > 0.999) & (np.abs(number - np.round(number)) < 1e-3)
    return roughness, np.where(whole, np.round(number) - 1, -1).astype(np.int64), names


def _surface_id_material(original, number: float):
    """An emission material showing (roughness, number, 0): a probe copy of `original` whose baked BSDFs emit their
    own per-pixel roughness (textures included; Mix Shaders blend it) and its emitters and the shaders the renderer
    lights beside them roughness 1, or, for a material without a baked BSDF, its constant. Returns (material,
    node-group copies made for it)."""
    if original is not None and leaves(original):
        def emit(inputs, node):
            combine = inputs._new("ShaderNodeCombineColor")
            inputs.feed(combine.inputs[0], inputs.roughness() if node.type in BAKED_BSDFS else 1.0)
            combine.inputs[1].default_value = number
            return combine.outputs[0]

        return probe_material(original, " (SGLF roughness)", emit)
    material = empty_node_material("SGLF roughness")
    nodes = material.node_tree.nodes
    emission = nodes.new("ShaderNodeEmission")
    value = float(principled_surface(original)["roughness"]) if original is not None else 1.0
    emission.inputs["Color"].default_value = (value, number, 0.0, 1.0)
    material.node_tree.links.new(emission.outputs[0], nodes["Material Output"].inputs["Surface"])
    return material, []


def _masked_errors(flip_maps, masks, squared_error_maps=None) -> dict:
    values = np.concatenate([f[m] for f, m in zip(flip_maps, masks)])
    out = {"flip": float(values.mean()) if values.size else None, "pixels": int(values.size)}
    if squared_error_maps is not None:
        squared = np.concatenate([e[m] for e, m in zip(squared_error_maps, masks)])
        out["rmse"] = float(np.sqrt(squared.mean())) if squared.size else None
    return out


def flip_by_roughness(flip_maps, roughness_maps, squared_error_maps=None) -> dict:
    """Mean FLIP (and RMSE of the tone-mapped images, given per-pixel squared errors) per roughness class over all
    views' pixels of that class."""
    return {name: _masked_errors(flip_maps, [(r >= low) & (r < high) for r in roughness_maps], squared_error_maps)
            for name, low, high in ROUGHNESS_CLASSES}


def flip_by_material(flip_maps, material_maps, names, squared_error_maps=None) -> dict:
    """The same per material (original names) seen whole in some view's pixels."""
    out = {}
    for index, name in enumerate(names):
        entry = _masked_errors(flip_maps, [m == index for m in material_maps], squared_error_maps)
        if entry["pixels"]:
            out[name] = entry
    return out


def _render(scene, camera, path, samples, seed):
    scene.camera = camera
    scene.cycles.samples, scene.cycles.seed = samples, seed
    return render_still(scene, path).astype(np.float64)


EEVEE_WORKER = Path(__file__).resolve().parent / "eevee_worker.py"
EEVEE_SAMPLES = 16


# Blender logs a material whose shader failed to compile (EEVEE then draws it magenta) as
#   gpu.shader | ERROR MA<material> Linking:
#              |       | Error: <message>
SHADER_ERROR = re.compile(r"gpu\.shader\s*\|\s*ERROR MA(?P<material>.*?)\s+(?:Linking|Compiling)?:?\s*\n"
                          r"(?:\s*\|)+\s*(?:Error:\s*)?(?P<message>[^\n]*)")


def shader_errors(log: str) -> list[str]:
    """'material: message' for each material whose EEVEE shader failed to compile, from a render's log."""
    return list(dict.fromkeys(f"{m['material'].strip()}: {m['message'].strip()}" for m in SHADER_ERROR.finditer(log)))


SPHERE_PROBE_SETUP = "a sphere probe at the scene's centre"
WORLD_PROBE_SETUP = "reflections from the world's probe (no sphere probe)"


def render_eevee(scene, camera_names, work_dir: Path, samples: int = EEVEE_SAMPLES, timeout_s: float = 900.0,
                 without_bake: bool = False, best_lighting: bool = False):
    """EEVEE renders of the scene as it is now, one per camera, by a separate process working on a saved copy:
    ([(H, W, 3) images], [seconds per render], [materials whose shaders failed to compile, with the reason]).
    The first render's time includes shader compilation. without_bake: EEVEE as well as Blender allows without the
    bake (original materials, ray tracing, baked volume and sphere probes: eevee_worker.py); best_lighting: that
    lighting for the scene as it is (what the bake leaves to the renderer gets it). One render per view, as set up:
    with the best lighting's sphere probe, or with no probe at all."""
    by_setup, seconds, failed = render_eevee_setups(scene, camera_names, work_dir, samples, timeout_s, without_bake,
                                                    best_lighting, world_probe_too=False)
    (images,) = by_setup.values()
    return images, seconds, failed


def render_eevee_setups(scene, camera_names, work_dir: Path, samples: int = EEVEE_SAMPLES, timeout_s: float = 900.0,
                        without_bake: bool = False, best_lighting: bool = True, world_probe_too: bool = True):
    """render_eevee, and with world_probe_too (and the best lighting) each view again without the sphere probe:
    ({SPHERE_PROBE_SETUP: [images], WORLD_PROBE_SETUP: [images]}, seconds, failed). Which is better depends on the
    scene (docs §53: the probe helps demo:spheres and demo:room, harms demo:materials, courtyard and geometry)."""
    blend = work_dir / "eevee_views.blend"
    for stale in work_dir.glob("BLENDER_EEVEE_*.exr"):  # an earlier call's renders in the same folder
        stale.unlink()
    with active_scene(scene), quiet_stdout():
        bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    arguments = [str(blend), scene.name, str(work_dir), "--cameras", ",".join(camera_names),
                 "--samples", str(samples)] + (["--without-bake"] if without_bake else []) \
        + (["--best-lighting"] if best_lighting else []) + (["--world-probe-too"] if world_probe_too else [])
    if bpy.app.binary_path:  # inside Blender: a background Blender runs the worker
        command = [bpy.app.binary_path, "-b", "--factory-startup", "--python", str(EEVEE_WORKER), "--", *arguments]
    else:  # bpy as a module: the same Python runs it
        command = [sys.executable, str(EEVEE_WORKER), *arguments]
    out = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s,
                         env={**os.environ, "PYTHONPATH": ""})
    if out.returncode != 0:
        tail = (out.stderr or out.stdout).strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"EEVEE render process failed ({out.returncode}): {tail[0]}")
    seconds = [float(m.group(1)) for m in re.finditer(r"^SECONDS BLENDER_EEVEE \d+ ([0-9.]+)$", out.stdout, re.M)]
    probe_bake = re.search(r"^PROBE BAKE SECONDS ([0-9.]+)$", out.stdout, re.M)
    if probe_bake and seconds:  # the probe bake compiled the shaders the first render would have
        seconds[0] += float(probe_bake.group(1))
    def views(suffix):
        return [read_exr(work_dir / f"BLENDER_EEVEE_{k}{suffix}.exr", channels=["R", "G", "B"])[0].astype(np.float64)
                for k in range(len(camera_names))]

    by_setup = {SPHERE_PROBE_SETUP: views("")}  # a missing render raises here (OSError), as before
    if all((work_dir / f"BLENDER_EEVEE_{k}_world_probe.exr").is_file() for k in range(len(camera_names))):
        by_setup[WORLD_PROBE_SETUP] = views("_world_probe")  # none where the scene has no mesh, hence no probe
    return by_setup, seconds, shader_errors(out.stdout + "\n" + out.stderr)


def best_setup(by_setup: dict, references) -> tuple[str, list, dict]:
    """The probe setup whose EEVEE views have the lowest mean FLIP against the references, as a user keeps the
    better-looking one: (its name, its images, {setup: mean FLIP})."""
    scores = {setup: float(np.mean([flip(tonemap(reference), tonemap(image))[0]
                                    for image, reference in zip(images, references)]))
              for setup, images in by_setup.items()}
    chosen = min(scores, key=scores.get)
    return chosen, by_setup[chosen], scores


REFERENCE_SAMPLES_MIN = 1024
TEST_SAMPLES_MIN = 128
EEVEE_LEFT_OUT = "left out of this evaluation: Cycles' only"
EVALUATE_VIEWS = 2
EVALUATE_RESOLUTION = (256, 144)
EVALUATE_PIXELS = EVALUATE_RESOLUTION[0] * EVALUATE_RESOLUTION[1]


def evaluation_resolution(scene, pixels: int = EVALUATE_PIXELS) -> tuple[int, int]:
    """About `pixels` pixels at the aspect of the scene's own render (pixel aspect included): 256 x 144 for 16:9."""
    render = scene.render
    aspect = (render.resolution_x * render.pixel_aspect_x) / max(render.resolution_y * render.pixel_aspect_y, 1e-9)
    aspect = min(max(aspect, 1 / 16), 16)
    width = max(8, round((pixels * aspect) ** 0.5))
    return width, max(8, round(width / aspect))


def test_samples_for(settings, reference_samples: int = 0) -> int:
    """Samples of the baked scene's render: twice the light field's samples, at least 128, never more than the
    reference's. Surfaces the bake leaves to the renderer (glass, a coat) are path traced there too; the SG node
    groups make each sample of this render costly (about 60x a reference sample on `demo:materials`, docs §54)."""
    test = max(TEST_SAMPLES_MIN, 2 * settings.samples)
    return min(test, reference_samples) if reference_samples else test


def reference_samples_for(settings) -> int:
    """Reference spp for a bake: 8x the light field's samples, at least 1024. FLIP against a noisy reference
    penalises the noise-free EEVEE renders as much as any error: on `demo:materials`' floor, the FLIP between two
    64-spp halves is 0.039 where the bake's own error is 0.054 (docs §54). A reference sample costs a small share of
    a test sample, so the reference is converged further than the test render (test_samples_for)."""
    return max(REFERENCE_SAMPLES_MIN, 8 * settings.samples)


def _reference_key(camera, resolution, reference_samples) -> tuple:
    """What a view's reference depends on besides the scene itself: the camera's placement and lens, the image size
    and the samples."""
    placement = tuple(round(v, 6) for row in camera.matrix_world for v in row)
    return placement, round(camera.data.lens, 6), round(camera.data.sensor_width, 6), tuple(resolution), \
        int(reference_samples)


def evaluate_stage(scene, plan, out_dir, *, views: int = EVALUATE_VIEWS, resolution=None,
                   reference_samples: int = 128, test_samples: int | None = None, with_eevee: bool = True,
                   eevee_without_bake: bool = True, reference_cache: dict | None = None) -> dict:
    """test_samples defaults to reference_samples (the bake's own evaluation passes test_samples_for): surfaces the
    bake does not replace (emitters, glass) are still path traced in the test render, whose noise counts against the
    bake in Cycles' figures but not in EEVEE's. reference_cache: a dict the caller keeps between evaluations of bakes
    of one unchanged scene (the bench's trainings of one encoder); each view's two reference halves and surface
    images are rendered once per camera placement, image size and samples and reused from it. resolution: (width,
    height), by default evaluation_resolution(scene). eevee_without_bake: also render EEVEE alone, what a user
    compares with (False leaves errors.eevee_without_bake empty: a check of the bake's own error only)."""
    test_samples = test_samples or reference_samples
    resolution = tuple(resolution or evaluation_resolution(scene))
    start = time.perf_counter()
    out_dir = Path(out_dir)
    if BAKE_RECORD_KEY not in scene:
        raise BakeInputError(f"scene '{scene.name}' has no applied bake to evaluate; run the apply stage first")
    render, cycles = scene.render, scene.cycles
    saved = dict(engine=render.engine, x=render.resolution_x, y=render.resolution_y, pct=render.resolution_percentage,
                 fmt=render.image_settings.file_format, depth=render.image_settings.color_depth,
                 path=render.filepath, samples=cycles.samples, seed=cycles.seed, denoise=cycles.use_denoising,
                 adaptive=cycles.use_adaptive_sampling, camera=scene.camera)
    cameras = _view_cameras(scene, plan, views)
    results, references, tests, eevee = [], [], [], ({} if with_eevee else {"error": EEVEE_LEFT_OUT})
    flip_maps, roughness_maps, material_maps, squared_maps, noise_flip_maps = [], [], [], [], []
    noise_squared_maps = []  # per pixel ((half A - half B) / 2)^2: the full reference's noise variance, unbiased
    try:
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y, render.resolution_percentage = *resolution, 100
        render.image_settings.file_format, render.image_settings.color_depth = "OPEN_EXR", "32"
        cycles.use_denoising, cycles.use_adaptive_sampling = False, False
        with (tempfile.TemporaryDirectory(prefix=".sglf-evaluate-", dir=out_dir) as tmp,
              compute_device(scene, "cuda") if plan.settings.device == "cuda" else contextlib.nullcontext()):
            for k, (camera, _) in enumerate(cameras):
                ours = _render(scene, camera, Path(tmp) / "ours.exr", test_samples, 0)
                key = _reference_key(camera, resolution, reference_samples)
                if reference_cache is not None and key in reference_cache:
                    half_a, half_b, (roughness, materials, material_names) = reference_cache[key]
                else:
                    undo = _swap_to_originals(scene)
                    try:
                        half_a = _render(scene, camera, Path(tmp) / "a.exr", reference_samples // 2, 1)
                        half_b = _render(scene, camera, Path(tmp) / "b.exr", reference_samples // 2, 2)
                    finally:
                        for slot, material in reversed(undo):  # reversed: instances may share one slot
                            slot.material = material
                    roughness, materials, material_names = surface_images(scene, camera, Path(tmp) / "surface.exr")
                    if reference_cache is not None:
                        reference_cache[key] = (half_a, half_b, (roughness, materials, material_names))
                reference = 0.5 * (half_a + half_b)
                references.append(reference)
                tests.append(ours)
                ref_ldr, ours_ldr = tonemap(reference), tonemap(ours)
                mean_flip, flip_map = flip(ref_ldr, ours_ldr)
                flip_maps.append(flip_map)
                squared_maps.append(((ref_ldr - ours_ldr) ** 2).mean(axis=-1))
                roughness_maps.append(roughness)
                material_maps.append(materials)
                half_a_ldr, half_b_ldr = tonemap(half_a), tonemap(half_b)
                noise_squared_maps.append((((half_a_ldr - half_b_ldr) / 2) ** 2).mean(axis=-1))
                noise = float(np.sqrt(noise_squared_maps[-1].mean()))  # = RMSE(half A, half B) / 2
                # FLIP between the two half-sample references: the floor no bake can get under at this sample count
                noise_flip_maps.append(flip(half_a_ldr, half_b_ldr)[1])
                picture = f"evaluate_view{k}.png"
                gap = np.ones((ref_ldr.shape[0], 2, 3))
                save_png(out_dir / picture, np.concatenate([ref_ldr, gap, ours_ldr, gap, heat(flip_map, 1.0)], axis=1),
                         min_width=0)
                results.append({"view": camera.name, "rmse": rmse(ref_ldr, ours_ldr), "psnr": psnr(ref_ldr, ours_ldr),
                                "flip": mean_flip, "reference_noise_rmse": noise, "picture": picture})
            if with_eevee:
                eevee = _evaluate_eevee(scene, cameras, references, tests, out_dir, Path(tmp), roughness_maps,
                                        (material_maps, material_names), without_bake=eevee_without_bake)
    finally:
        for camera, temporary in cameras:
            if temporary:
                data = camera.data
                bpy.data.objects.remove(camera)
                bpy.data.cameras.remove(data)
        render.engine, render.resolution_x, render.resolution_y = saved["engine"], saved["x"], saved["y"]
        render.resolution_percentage, render.filepath = saved["pct"], saved["path"]
        render.image_settings.file_format, render.image_settings.color_depth = saved["fmt"], saved["depth"]
        cycles.samples, cycles.seed, cycles.use_denoising = saved["samples"], saved["seed"], saved["denoise"]
        cycles.use_adaptive_sampling, scene.camera = saved["adaptive"], saved["camera"]
    errors = {key: float(np.mean([r[key] for r in results])) for key in ("rmse", "psnr", "flip", "reference_noise_rmse")}
    errors["views"] = results
    errors["flip_by_roughness"] = flip_by_roughness(flip_maps, roughness_maps, squared_maps)
    errors["reference_noise_flip"] = float(np.mean([m.mean() for m in noise_flip_maps]))
    errors["reference_noise_flip_by_roughness"] = flip_by_roughness(noise_flip_maps, roughness_maps,
                                                                    noise_squared_maps)
    errors["flip_by_material"] = flip_by_material(flip_maps, material_maps, material_names, squared_maps)
    for name, entry in flip_by_material(noise_flip_maps, material_maps, material_names, noise_squared_maps).items():
        errors["flip_by_material"][name]["reference_noise_flip"] = entry["flip"]
        errors["flip_by_material"][name]["reference_noise_rmse"] = entry["rmse"]
    errors["eevee"] = eevee
    errors["eevee_without_bake"] = eevee.pop("without_bake", None) or {}
    errors["reference_samples"], errors["test_samples"] = reference_samples, test_samples
    seconds = time.perf_counter() - start
    update_report(out_dir, plan.stage_hash("capture"), timings_s={"evaluate": seconds}, errors=errors)
    return errors


def _evaluate_eevee(scene, cameras, references, cycles_tests, out_dir: Path, work_dir: Path, roughness_maps,
                    materials, without_bake: bool = True) -> dict:
    """EEVEE against the reference and against Cycles' evaluation of the same baked nodes; pictures per view.
    A failure to render with EEVEE (no OpenGL on the machine) is reported, not raised."""
    try:
        by_setup, seconds, failed = render_eevee_setups(scene, [camera.name for camera, _ in cameras], work_dir)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return {"error": str(exc)}
    setup, images, flip_by_setup = best_setup(by_setup, references)
    views, flip_maps, parity_maps = [], [], []
    for k, (image, reference, cycles) in enumerate(zip(images, references, cycles_tests)):
        ref_ldr, eevee_ldr = tonemap(reference), tonemap(image)
        mean_flip, flip_map = flip(ref_ldr, eevee_ldr)
        flip_maps.append(flip_map)
        parity, parity_map = flip(tonemap(cycles), eevee_ldr)
        parity_maps.append(parity_map)
        picture = f"evaluate_view{k}_eevee.png"
        gap = np.ones((ref_ldr.shape[0], 2, 3))
        save_png(out_dir / picture, np.concatenate([ref_ldr, gap, eevee_ldr, gap, heat(flip_map, 1.0)], axis=1),
                 min_width=0)
        singles = {"reference": ref_ldr, "eevee_baked": eevee_ldr}
        for name, image_ldr in singles.items():
            save_png(out_dir / f"evaluate_view{k}_{name}.png", image_ldr, min_width=0)
        views.append({"flip": mean_flip, "psnr": psnr(ref_ldr, eevee_ldr), "rmse": rmse(ref_ldr, eevee_ldr),
                      "flip_vs_cycles_bake": parity, "picture": picture,
                      "pictures": {name: f"evaluate_view{k}_{name}.png" for name in singles}})
    summary = {key: float(np.mean([v[key] for v in views])) for key in ("flip", "psnr", "rmse", "flip_vs_cycles_bake")}
    # Surfaces the bake leaves alone (rough materials with --rough-materials renderer) are lit by EEVEE itself,
    # which has no light from emissive meshes without its ray tracing: parity with Cycles' evaluation is per class.
    summary["flip_by_material"] = flip_by_material(flip_maps, *materials)
    if without_bake:
        summary["without_bake"] = _evaluate_eevee_without_bake(scene, cameras, references, images, out_dir, work_dir,
                                                               materials)
    summary.update(views=views, samples=EEVEE_SAMPLES, flip_by_roughness=flip_by_roughness(flip_maps, roughness_maps),
                   flip_vs_cycles_bake_by_roughness=flip_by_roughness(parity_maps, roughness_maps),
                   shader_errors=failed, probe_setup=setup, flip_by_probe_setup=flip_by_setup,
                   first_render_s=seconds[0] if seconds else None,
                   later_render_s=float(np.mean(seconds[1:])) if len(seconds) > 1 else None)
    return summary


def _evaluate_eevee_without_bake(scene, cameras, references, baked_images, out_dir: Path, work_dir: Path,
                                materials) -> dict:
    """EEVEE without the bake, set up as well as Blender allows (render_eevee without_bake), against the same
    reference; pictures per view: Cycles reference | EEVEE alone | EEVEE with the bake. A failure is reported."""
    try:
        by_setup, seconds, failed = render_eevee_setups(scene, [camera.name for camera, _ in cameras], work_dir,
                                                        without_bake=True, best_lighting=False)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return {"error": str(exc)}
    setup, images, flip_by_setup = best_setup(by_setup, references)
    views, flip_maps = [], []
    for k, (image, reference, baked) in enumerate(zip(images, references, baked_images)):
        ref_ldr, alone_ldr, baked_ldr = tonemap(reference), tonemap(image), tonemap(baked)
        mean_flip, flip_map = flip(ref_ldr, alone_ldr)
        flip_maps.append(flip_map)
        picture = f"evaluate_view{k}_three_way.png"
        gap = np.ones((ref_ldr.shape[0], 2, 3))
        save_png(out_dir / picture, np.concatenate([ref_ldr, gap, alone_ldr, gap, baked_ldr], axis=1), min_width=0)
        save_png(out_dir / f"evaluate_view{k}_eevee_alone.png", alone_ldr, min_width=0)
        views.append({"flip": mean_flip, "psnr": psnr(ref_ldr, alone_ldr), "rmse": rmse(ref_ldr, alone_ldr),
                      "picture": picture, "pictures": {"eevee_alone": f"evaluate_view{k}_eevee_alone.png"}})
    return {"flip": float(np.mean([v["flip"] for v in views])), "psnr": float(np.mean([v["psnr"] for v in views])),
            "views": views, "flip_by_material": flip_by_material(flip_maps, *materials),
            "setup": "original materials; screen-space ray tracing and fast GI; a volume probe over the scene "
                     f"(emission captured) baked by Blender; {setup}, the better of the two",
            "probe_setup": setup, "flip_by_probe_setup": flip_by_setup, "shader_errors": failed, "render_s": seconds}
