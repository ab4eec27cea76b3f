"""Hair in Blender: strands out of curves objects, the Cycles reference with Paper II's feature split,
the scene's key light and hair colour, and the background the filtered hair is composited over.

Reference (what the filter is trained to reproduce): Cycles traces the real strands (ribbons of their real
radius, fibre opacity through a Transparent BSDF mix) with a box pixel filter at many samples per pixel,
which is the paper's supersample-and-downsample. The lobes of Paper II are the colour of one Translucent
BSDF, (F_d + F_TRT, F_R, 0), with its normal pointing away from the light: lit by a sun of strength pi its
response is exactly colour x visibility from either side of the ribbon, so Cycles computes the visibility
(transparent shadows through the other strands) per sample and input and reference describe the same
shading. R and G of Combined are alpha-premultiplied; the targets are straight. (Why not Diffuse, passes or
AOVs: DESIGN.md section 8.)
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..bake_directory.bake_plan import BakeInputError
from ..bake_directory.exr_io import read_exr
from .filtering import DEFAULT_PASSES
from .raster import HairShading, PinholeCamera, Strands
from ..shaders.node_group import NodeOps
from ..blender_addon.render import quiet_stdout
from ..blender_addon.scene_analysis import active_scene, empty_node_material, enable_nodes, remove_datablocks, uses_nodes

TEMP_PREFIX = "SGLF hair"
DEFAULT_HAIR_COLOR = (0.35, 0.2, 0.1)
MAX_FILTER_PIXELS = 4096 * 4096  # features, network activations and images stay within a few GB


def hair_objects(scene) -> list:
    return [obj for obj in scene.objects if obj.type == "CURVES" and not obj.hide_render]


def strands_from_objects(objects, depsgraph) -> Strands:
    """All strands of the evaluated curves objects as one Strands (world and model space)."""
    worlds, models, radii, offsets, grooms, base = [], [], [], [0], [], 0
    for number, obj in enumerate(objects):
        evaluated = obj.evaluated_get(depsgraph)
        data = evaluated.data
        count = len(data.points)
        if count == 0:
            continue
        model = np.empty(count * 3, np.float32)
        data.attributes["position"].data.foreach_get("vector", model)
        model = model.reshape(-1, 3).astype(np.float64)
        radius = np.full(count, 0.005, np.float32)
        if "radius" in data.attributes:
            data.attributes["radius"].data.foreach_get("value", radius)
        curve_offsets = np.empty(len(data.curves) + 1, np.int32)
        data.curve_offset_data.foreach_get("value", curve_offsets)
        matrix = np.array(evaluated.matrix_world, np.float64)
        worlds.append(model @ matrix[:3, :3].T + matrix[:3, 3])
        models.append(model)
        scale = float(np.cbrt(abs(np.linalg.det(matrix[:3, :3])))) or 1.0
        radii.append(radius.astype(np.float64) * scale)
        offsets.extend((curve_offsets[1:] + base).tolist())
        grooms.append(np.full(len(curve_offsets) - 1, number))
        base += count
    if base == 0:
        raise BakeInputError("the scene has no hair to filter: no render-visible curves object with strands")
    return Strands(np.concatenate(worlds), np.concatenate(models), np.concatenate(radii), np.array(offsets),
                   np.concatenate(grooms))


def pinhole_camera(scene, depsgraph, camera_obj=None, width=None, height=None) -> PinholeCamera:
    camera_obj = camera_obj or scene.camera
    if camera_obj is None:
        raise BakeInputError(f"scene '{scene.name}' has no camera to render the hair from")
    cam = camera_obj.data
    if cam.type != "PERSP":
        raise BakeInputError(f"camera '{camera_obj.name}' is {cam.type.lower()}; hair filtering needs a "
                             "perspective camera")
    render = scene.render
    width = width or int(render.resolution_x * render.resolution_percentage / 100)
    height = height or int(render.resolution_y * render.resolution_percentage / 100)
    fit = cam.sensor_fit
    horizontal = fit == "HORIZONTAL" or (fit == "AUTO" and width >= height)
    sensor = cam.sensor_width if fit != "VERTICAL" else cam.sensor_height
    focal_px = cam.lens / sensor * (width if horizontal else height)
    side = max(width, height) if fit == "AUTO" else (width if horizontal else height)
    matrix = camera_obj.evaluated_get(depsgraph).matrix_world
    return PinholeCamera(np.array(matrix.inverted(), np.float64), focal_px, width, height,
                         (cam.shift_x * side, cam.shift_y * side))


def key_light(scene, depsgraph, centre) -> tuple[np.ndarray, np.ndarray, str]:
    """The one light Paper II's model allows: (unit direction to it, irradiance RGB at `centre`, name).

    The strongest render-visible lamp by irradiance at the hair's centre: a sun gives its strength; point,
    spot and area lamps their power over 4 pi d^2 (pi d^2 for area lamps, which emit into a hemisphere).
    """
    best = None
    for obj in scene.objects:
        if obj.type != "LIGHT" or obj.hide_render:
            continue
        light = obj.data
        matrix = obj.evaluated_get(depsgraph).matrix_world
        color = np.array(light.color, np.float64)
        if light.type == "SUN":
            direction = np.array(matrix.to_3x3() @ Vector((0.0, 0.0, 1.0)), np.float64)
            irradiance = light.energy
        else:
            offset = np.array(matrix.translation, np.float64) - centre
            distance = max(float(np.linalg.norm(offset)), 1e-6)
            direction = offset / distance
            irradiance = light.energy / ((math.pi if light.type == "AREA" else 4 * math.pi) * distance ** 2)
        candidate = (irradiance * color.mean(), direction / np.linalg.norm(direction), irradiance * color, obj.name)
        if best is None or candidate[0] > best[0]:
            best = candidate
    if best is None:
        raise BakeInputError(f"scene '{scene.name}' has no lamp; hair filtering shades with one key light")
    return best[1], best[2], best[3]


def hair_color(obj) -> tuple[np.ndarray, str | None]:
    """The strand colour of the object's first material (Principled Hair 'Color' or a Base Color); default
    brown when none is readable. The second value explains a fallback."""
    material = obj.active_material or (obj.data.materials[0] if len(obj.data.materials) else None)
    if material is None or not uses_nodes(material):
        return np.array(DEFAULT_HAIR_COLOR), f"'{obj.name}' has no node material; default hair colour used"
    for node in material.node_tree.nodes:
        for name in ("Color", "Base Color"):
            socket = node.inputs.get(name) if node.type in ("BSDF_HAIR_PRINCIPLED", "BSDF_HAIR",
                                                              "BSDF_PRINCIPLED") else None
            if socket is not None and not socket.is_linked:
                return np.array(socket.default_value[:3], np.float64), None
    return np.array(DEFAULT_HAIR_COLOR), f"'{obj.name}': hair colour not readable from its material; default used"


def _lobe_material(to_light, shading: HairShading):
    """Translucent((F_d + F_TRT, F_R, 0), N = -L), mixed with Transparent by fibre opacity."""
    material = empty_node_material(f"{TEMP_PREFIX} lobes")
    nodes, links = material.node_tree.nodes, material.node_tree.links
    geometry = nodes.new("ShaderNodeNewGeometry")
    ops = NodeOps(material.node_tree)
    L = tuple(float(v) for v in to_light)
    tangent = ops.normalize(geometry.outputs["Tangent"])
    cos_tl = ops.clamp(ops.dot(tangent, L), -1.0, 1.0)
    diffuse_factor = ops.sqrt(ops.maximum(ops.sub(1.0, ops.mul(cos_tl, cos_tl)), 0.0))
    half = ops.normalize(ops.vadd(geometry.outputs["Incoming"], L))
    angle_th = ops.acos(ops.clamp(ops.dot(tangent, half), -1.0, 1.0))

    def lobe(shift_deg, exponent):
        return ops.power(ops.maximum(ops.sin(ops.add(angle_th, math.radians(shift_deg))), 0.0), exponent)

    color_factor = ops.add(diffuse_factor, lobe(shading.shift_trt_deg, shading.exponent_trt))
    highlight = lobe(shading.shift_r_deg, shading.exponent_r)
    rgb = nodes.new("ShaderNodeCombineColor")
    links.new(color_factor, rgb.inputs[0])
    links.new(highlight, rgb.inputs[1])
    # Ribbons face the camera ray; Cycles lets a light behind that face reach only transmission closures and
    # one in front only reflection ones, except that a transmission closure is sampled on both sides: so
    # Translucent. An unlinked Normal socket means "the surface normal", so -L goes in through a node, and
    # bump-map correction (which bends a given normal toward the ribbon's, dimming up to 3x) is off.
    material.cycles.use_bump_map_correction = False
    normal = nodes.new("ShaderNodeCombineXYZ")
    for axis in range(3):
        normal.inputs[axis].default_value = -L[axis]
    lobes = nodes.new("ShaderNodeBsdfTranslucent")
    links.new(normal.outputs[0], lobes.inputs["Normal"])
    links.new(rgb.outputs[0], lobes.inputs["Color"])
    mix = nodes.new("ShaderNodeMixShader")
    mix.inputs["Fac"].default_value = shading.opacity
    links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[1])
    links.new(lobes.outputs[0], mix.inputs[2])
    links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
    return material


def render_reference(objects, camera: PinholeCamera, to_light, samples: int = 256,
                     shading: HairShading = HairShading(), seed: int = 0, threads: int = 0) -> np.ndarray:
    """Cycles reference of the strands of `objects`: (3, H, W) straight colour factor, highlight, alpha.

    Only the given curves objects are rendered (no head, no world light): the hair alone, as the filter
    sees it. Colour factor includes the ambient term; where alpha is 0 it is 1 and the highlight 0.
    """
    created = []
    try:
        scene = bpy.data.scenes.new(f"{TEMP_PREFIX} reference")
        created.append((bpy.data.scenes, scene))
        for obj in objects:
            scene.collection.objects.link(obj)
        world = bpy.data.worlds.new(f"{TEMP_PREFIX} black")
        created.append((bpy.data.worlds, world))
        enable_nodes(world)
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                node.inputs["Strength"].default_value = 0.0
        scene.world = world
        sun = bpy.data.lights.new(f"{TEMP_PREFIX} sun", "SUN")
        created.append((bpy.data.lights, sun))
        sun.energy, sun.angle = math.pi, 0.0
        sun_obj = bpy.data.objects.new(f"{TEMP_PREFIX} sun", sun)
        created.append((bpy.data.objects, sun_obj))
        to_light = np.asarray(to_light, np.float64) / np.linalg.norm(to_light)
        sun_obj.rotation_euler = Vector(tuple(to_light)).to_track_quat("Z", "Y").to_euler()
        scene.collection.objects.link(sun_obj)
        cam_data = bpy.data.cameras.new(f"{TEMP_PREFIX} camera")
        created.append((bpy.data.cameras, cam_data))
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.sensor_width = 36.0
        cam_data.lens = camera.focal_px / camera.width * 36.0
        cam_data.shift_x = camera.shift_px[0] / camera.width
        cam_data.shift_y = camera.shift_px[1] / camera.width
        cam_data.clip_start, cam_data.clip_end = 1e-3, 1e4
        cam_obj = bpy.data.objects.new(f"{TEMP_PREFIX} camera", cam_data)
        created.append((bpy.data.objects, cam_obj))
        cam_obj.matrix_world = Matrix(np.linalg.inv(camera.world_to_camera).tolist())
        scene.collection.objects.link(cam_obj)
        scene.camera = cam_obj
        material = _lobe_material(to_light, shading)
        created.append((bpy.data.materials, material))
        view_layer = scene.view_layers[0]
        view_layer.material_override = material
        render = scene.render
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y, render.resolution_percentage = camera.width, camera.height, 100
        render.film_transparent = True
        render.use_compositing = False
        render.use_sequencer = False
        render.image_settings.media_type = "MULTI_LAYER_IMAGE"
        render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
        render.image_settings.color_depth = "32"
        render.threads_mode = "FIXED" if threads else "AUTO"
        if threads:
            render.threads = threads
        cycles = scene.cycles
        cycles.device = "CPU"
        cycles.samples = samples
        cycles.use_adaptive_sampling = False
        cycles.use_denoising = False
        cycles.seed = seed
        cycles.pixel_filter_type = "BOX"
        cycles.filter_width = 1.0
        cycles.max_bounces = 0
        cycles.transparent_max_bounces = 256
        cycles.sample_clamp_direct = 0.0
        cycles.sample_clamp_indirect = 0.0
        scene.cycles_curves.shape = "RIBBONS"
        scene.view_settings.view_transform = "Standard"
        with tempfile.TemporaryDirectory(prefix="sglf_hair_") as tmp:
            path = Path(tmp) / "reference.exr"
            render.filepath = str(path)
            with active_scene(scene), quiet_stdout():
                bpy.ops.render.render(write_still=True, scene=scene.name)
            layer = view_layer.name
            names = [f"{layer}.Combined.{c}" for c in "RGA"]
            pixels, _, _ = read_exr(path, channels=names)
    finally:
        remove_datablocks(created)
    premultiplied = np.moveaxis(pixels.astype(np.float64), -1, 0)
    alpha = np.clip(premultiplied[2], 0, 1)
    safe = np.where(alpha > 1e-4, alpha, 1.0)
    color = np.where(alpha > 1e-4, (premultiplied[0] + shading.ambient * alpha) / safe, 1.0)
    highlight = np.where(alpha > 1e-4, premultiplied[1] / safe, 0.0)
    return np.stack([color, highlight, alpha])


# ---------------------------------------------------------------- training pairs

TRAIN_STYLES = ("straight", "wavy", "curly")
HELD_OUT_STYLE = "clumped"  # never seen in training


def dataset_groom(style: str, density: float):
    """The demo head with a denser groom of `style`; returns (scene, hair objects)."""
    from ..blender_addon.demo_scenes import _set_modifier_inputs, build_demo_scene
    scene = build_demo_scene(f"demo:hair-{style}")
    objects = hair_objects(scene)
    for obj in objects:
        _set_modifier_inputs(obj.modifiers["Generate Hair Curves"], {"Density": density})
    return scene, objects


# ---------------------------------------------------------------- Filter Hair (panel and headless)

@dataclass
class HairFilterResult:
    image: np.ndarray  # (H, W, 3) linear, the filtered hair over the background
    unfiltered: np.ndarray  # (H, W, 3) the same with plain stochastic transparency (what the filter saw)
    outputs: np.ndarray  # (3, H, W) filtered colour factor, highlight, alpha
    paths: dict
    seconds: dict
    warnings: list = field(default_factory=list)


def opaque_depth(scene, depsgraph, camera: PinholeCamera, pixels: np.ndarray) -> np.ndarray:
    """(H*W,) view depth of the nearest opaque (mesh) surface at the given pixel centres, +inf elsewhere."""
    from ..blender_addon.capture import scene_bvh
    depth = np.full(camera.width * camera.height, np.inf)
    bvh, _ = scene_bvh(scene, depsgraph)
    if bvh is None or len(pixels) == 0:
        return depth
    m = np.asarray(camera.world_to_camera, np.float64)
    rotation_t = m[:3, :3].T
    eye = camera.position
    ys, xs = np.divmod(pixels, camera.width)
    px = (xs + 0.5 - camera.width / 2 - camera.shift_px[0]) / camera.focal_px
    py = -(ys + 0.5 - camera.height / 2 + camera.shift_px[1]) / camera.focal_px
    directions = np.stack([px, py, -np.ones_like(px)], axis=1) @ rotation_t.T
    origin = Vector(tuple(eye))
    for pixel, direction in zip(pixels.tolist(), directions.tolist()):
        hit, _, _, distance = bvh.ray_cast(origin, Vector(direction))
        if hit is not None:
            depth[pixel] = distance / float(np.linalg.norm(direction))  # along the ray -> view depth
    return depth


def render_background(scene, camera_obj, width: int, height: int, samples: int, exclude) -> np.ndarray:
    """Cycles render of the scene without the hair objects, through the scene's camera: (H, W, 3) linear."""
    from ..blender_addon.render import render_still
    created = []
    try:
        temp = bpy.data.scenes.new(f"{TEMP_PREFIX} background")
        created.append((bpy.data.scenes, temp))
        excluded = {obj.name for obj in exclude}
        for obj in scene.objects:
            if not obj.hide_render and obj.name not in excluded:
                temp.collection.objects.link(obj)
        temp.world = scene.world
        temp.camera = camera_obj
        render = temp.render
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
        render.use_compositing = render.use_sequencer = False
        render.image_settings.file_format = "OPEN_EXR"
        render.image_settings.color_depth = "32"
        temp.view_settings.view_transform = "Standard"
        temp.cycles.device = "CPU"
        temp.cycles.samples = samples
        temp.cycles.use_denoising = samples >= 16
        with tempfile.TemporaryDirectory(prefix="sglf_hair_") as tmp:
            return render_still(temp, Path(tmp) / "background.exr").astype(np.float64)
    finally:
        remove_datablocks(created)


def filter_hair(scene, out_dir, model_path=None, width: int | None = None, height: int | None = None,
                background_samples: int = 16, passes: int = DEFAULT_PASSES, network: str | None = None,
                progress=lambda fraction, message: None) -> HairFilterResult:
    """Render the cheap stochastic input for the scene's camera, filter it with the ONNX model through
    onnxruntime, composite colour factor x hair colour + highlight over a Cycles render of the rest of the
    scene, and write filtered.exr / filtered.png / unfiltered.png / hair_filter.json into out_dir. The model is
    `model_path`, or else the shipped `network` (base: faster; large: more accurate; None: the default, large)."""
    from ..bake_directory.bake_report import save_png
    from .filtering import load_filter
    from .raster import composite, hair_color_map, render_stochastic
    from ..bake_directory.image_metrics import tonemap
    from ..bake_directory.atomic import atomic_output
    from ..bake_directory.exr_io import write_exr
    import json
    import time

    warnings, seconds = [], {}
    objects = hair_objects(scene)
    if not objects:
        raise BakeInputError(f"scene '{scene.name}' has no hair to filter (no render-visible curves object)")
    hair_filter = load_filter(model_path, network=network)  # a bad model fails before any rendering
    out_dir = Path(out_dir)
    with active_scene(scene):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        camera = pinhole_camera(scene, depsgraph, width=width, height=height)
        if camera.width * camera.height > MAX_FILTER_PIXELS:
            gigabytes = camera.width * camera.height * 4 * (hair_filter.samples * 6 + 40) / 1e9
            raise BakeInputError(f"{camera.width}x{camera.height} needs about {gigabytes:.0f} GB to filter; "
                                 f"at most {MAX_FILTER_PIXELS // 1_000_000} megapixels (4096x4096)")
        strands = strands_from_objects(objects, depsgraph)
        low, high = strands.bounds()
        to_light, irradiance, light_name = key_light(scene, depsgraph, (low + high) / 2)
        colors, notes = zip(*(hair_color(obj) for obj in objects))
        warnings += [note for note in notes if note]
        if len({tuple(np.round(c, 3)) for c in colors}) > 1:
            warnings.append(f"{len(objects)} hair objects with different colours: the filter knows one colour, "
                            "so each pixel takes the mean colour of the grooms its samples hit")
        progress(0.05, f"stochastic input ({hair_filter.samples} spp) and the opaque scene's depth")
        start = time.perf_counter()
        stochastic = render_stochastic(strands, camera, to_light, hair_filter.samples,
                                       opaque_depth_at=lambda pixels: opaque_depth(scene, depsgraph, camera, pixels))
        seconds["stochastic_input"] = time.perf_counter() - start
        progress(0.35, f"filtering (onnxruntime, {passes} pass{'es' if passes > 1 else ''})")
        start = time.perf_counter()
        outputs, padded = hair_filter.filter(stochastic, passes)
        seconds["filter"] = time.perf_counter() - start
        if padded:
            warnings.append(f"{camera.width}x{camera.height} is not a multiple of the network's stride "
                            f"{hair_filter.stride}: padded with empty pixels and cropped back")
        progress(0.45, f"background ({background_samples} spp Cycles)")
        start = time.perf_counter()
        background = render_background(scene, scene.camera, camera.width, camera.height, background_samples,
                                       objects)
        seconds["background"] = time.perf_counter() - start
    color_map = hair_color_map(stochastic.extras["groom"], np.array(colors))
    image = composite(outputs, color_map, background, irradiance)
    unfiltered = composite(stochastic.unfiltered(), color_map, background, irradiance)
    paths = {"filtered_exr": out_dir / "filtered.exr", "filtered_png": out_dir / "filtered.png",
             "unfiltered_png": out_dir / "unfiltered.png", "summary": out_dir / "hair_filter.json"}
    write_exr(paths["filtered_exr"], image.astype(np.float32), precision="half")
    save_png(paths["filtered_png"], tonemap(image), min_width=1)
    save_png(paths["unfiltered_png"], tonemap(unfiltered), min_width=1)
    summary = {"model": str(hair_filter.path), "config": hair_filter.config, "samples": hair_filter.samples,
               "filter_passes": passes,
               "size": [camera.width, camera.height], "key_light": light_name,
               "hair_objects": [obj.name for obj in objects], "warnings": warnings,
               "seconds": {k: round(v, 3) for k, v in seconds.items()}}
    with atomic_output(paths["summary"]) as tmp:
        tmp.write_text(json.dumps(summary, indent=1))
    progress(1.0, "done")
    return HairFilterResult(image, unfiltered, outputs, paths, seconds, warnings)

