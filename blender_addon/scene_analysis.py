"""Scene analysis: decide what the bake models (DESIGN section 6) and build the BakePlan.

Reads the scene only; never changes it.
"""
from __future__ import annotations

import contextlib

import bpy
import numpy as np

try:  # inside the installed extension the numpy side is a sibling package
    from ..shaders.bake_plan import (GLOSSY_ROUGHNESS_MAX, ROUGH_METALLIC_MAX, BakeInputError, BakePlan, BakeSettings,
                                     EnvironmentPlan, MaterialPlan, ObjectPlan, auto_sg_count)
except ImportError:  # bpy as a module with the repository on sys.path
    from shaders.bake_plan import (GLOSSY_ROUGHNESS_MAX, ROUGH_METALLIC_MAX, BakeInputError, BakePlan, BakeSettings,
                                   EnvironmentPlan, MaterialPlan, ObjectPlan, auto_sg_count)

# An environment whose luminance-weighted chroma (max-min)/max stays below this is treated as grey:
# one IWEV channel instead of three.
ACHROMATIC_CHROMA_MAX = 0.05


def uses_nodes(id_block) -> bool:
    """Blender 5 always shades with the node tree (use_nodes is deprecated); older versions may not."""
    if id_block is None or id_block.node_tree is None:
        return False
    return bpy.app.version >= (5, 0, 0) or id_block.use_nodes


def enable_nodes(id_block) -> None:
    if bpy.app.version < (5, 0, 0):
        id_block.use_nodes = True


def remove_datablocks(created) -> None:
    """Remove (collection, datablock) pairs, last made first; ones already gone are skipped."""
    for collection, block in reversed(created):
        try:
            collection.remove(block)
        except (ReferenceError, RuntimeError):
            pass


def empty_node_material(name: str):
    """A new material whose node tree holds only its Material Output (to be wired by the caller)."""
    material = bpy.data.materials.new(name)
    enable_nodes(material)
    for node in list(material.node_tree.nodes):
        if node.type != "OUTPUT_MATERIAL":
            material.node_tree.nodes.remove(node)
    return material


def _surface_bsdf(material):
    if not uses_nodes(material):
        return None
    output = next((n for n in material.node_tree.nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return None
    node = output.inputs["Surface"].links[0].from_node
    return node if node.type == "BSDF_PRINCIPLED" else None


def _input_value(node, name, default):
    socket = node.inputs.get(name)
    if socket is None:
        return default, False
    if socket.is_linked:
        return default, True
    value = socket.default_value
    return (tuple(value) if hasattr(value, "__len__") else float(value)), False


BAKED_COPY_KEY = "sglf_original"  # set by the apply stage on its copies; the plan looks through them


def unbaked(material):
    """The user's material behind an SG-baked copy (the plan of a baked scene equals the plan before)."""
    if material is not None and BAKED_COPY_KEY in material:
        return bpy.data.materials.get(material[BAKED_COPY_KEY], material)
    return material


def analyse_material(material, settings: BakeSettings) -> MaterialPlan:
    material = unbaked(material)
    name = material.name if material else "(no material)"
    bsdf = _surface_bsdf(material)
    if bsdf is None:
        reason = ("no material: Blender renders it diffuse grey" if material is None
                  else "surface is not a Principled BSDF: treated as diffuse")
        return MaterialPlan(name, 1.0, 0.0, False, 0, reason)
    roughness, textured = _input_value(bsdf, "Roughness", 0.5)
    metallic, _ = _input_value(bsdf, "Metallic", 0.0)
    if textured:
        return MaterialPlan(name, float(roughness), float(metallic), True,
                            settings.sg_count or 16, "roughness is textured: treated as glossy, the most SGs")
    rough_metal = roughness >= GLOSSY_ROUGHNESS_MAX and metallic >= ROUGH_METALLIC_MAX
    glossy = roughness < GLOSSY_ROUGHNESS_MAX or rough_metal
    most = settings.sg_count or 16
    count = 0 if not glossy else most if settings.uniform_sg_count else auto_sg_count(roughness, most)
    irradiance_only = False
    if rough_metal:
        reason = (f"roughness {roughness:.2f} >= {GLOSSY_ROUGHNESS_MAX} but metallic {metallic:.2f}: "
                  "all its light is specular, so light-field SGs")
    elif glossy:
        reason = f"roughness {roughness:.2f} < {GLOSSY_ROUGHNESS_MAX}: glossy, needs light-field SGs"
    elif _is_emissive(material):
        reason = f"roughness {roughness:.2f}, emissive: not baked, its emission is the light it shows"
    elif settings.rough_materials == "irradiance":
        irradiance_only = True
        reason = (f"roughness {roughness:.2f} >= {GLOSSY_ROUGHNESS_MAX}: irradiance lightmap, no SGs (its lobe is "
                  "wider than ~40 deg; the specular is the split-sum estimate of the irradiance's)")
    else:
        reason = (f"roughness {roughness:.2f} >= {GLOSSY_ROUGHNESS_MAX}: not baked (rough materials: renderer), "
                  "the renderer's own lighting; in EEVEE only its irradiance volumes give it indirect light")
    if glossy and count < most:
        reason += f"; {count} SGs are within the error budget at this roughness"
    return MaterialPlan(name, float(roughness), float(metallic), glossy, count, reason, irradiance_only)


def principled_surface(material) -> dict:
    """Base colour, roughness, metallic and normal-incidence Fresnel F0 of a material's Principled BSDF,
    as Blender 4+ defines them: F0 = mix(((ior-1)/(ior+1))^2 * 2 * specular_level * tint, base, metallic).
    Materials without one render as Blender's default grey diffuse."""
    bsdf = _surface_bsdf(material)
    if bsdf is None:
        return {"base_color": [0.8, 0.8, 0.8], "roughness": 1.0, "metallic": 0.0, "f0": [0.04, 0.04, 0.04],
                "textured": False}
    base, linked_base = _input_value(bsdf, "Base Color", (0.8, 0.8, 0.8, 1.0))
    roughness, linked_rough = _input_value(bsdf, "Roughness", 0.5)
    metallic, linked_metal = _input_value(bsdf, "Metallic", 0.0)
    ior, _ = _input_value(bsdf, "IOR", 1.5)
    level, _ = _input_value(bsdf, "Specular IOR Level", 0.5)
    tint, _ = _input_value(bsdf, "Specular Tint", (1.0, 1.0, 1.0, 1.0))
    base = np.clip(np.asarray(base[:3], float), 0.0, 1.0)
    dielectric = min(((ior - 1) / (ior + 1)) ** 2 * 2 * level, 1.0) * np.clip(np.asarray(tint[:3], float), 0, 1)
    metallic = float(np.clip(metallic, 0.0, 1.0))
    f0 = (1 - metallic) * dielectric + metallic * base
    return {"base_color": [float(c) for c in base], "roughness": float(np.clip(roughness, 0.0, 1.0)),
            "metallic": metallic, "f0": [float(c) for c in f0],
            "textured": bool(linked_base or linked_rough or linked_metal)}


def _is_emissive(material) -> bool:
    bsdf = _surface_bsdf(material)
    if bsdf is None:
        return False
    strength, linked_s = _input_value(bsdf, "Emission Strength", 0.0)
    color, linked_c = _input_value(bsdf, "Emission Color", (0, 0, 0, 1))
    return (linked_s or strength > 0) and (linked_c or max(color[:3]) > 0)


def loop_triangle_arrays(mesh):
    """(loops (T, 3), vertices (T, 3), material index (T,), vertex coordinates (V, 3)) of a mesh's triangles."""
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    loops = np.empty(count * 3, np.int64)
    verts = np.empty(count * 3, np.int64)
    mat_index = np.empty(count, np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    mesh.loop_triangles.foreach_get("vertices", verts)
    mesh.loop_triangles.foreach_get("material_index", mat_index)
    coords = np.empty(len(mesh.vertices) * 3, np.float64)
    mesh.vertices.foreach_get("co", coords)
    return loops.reshape(-1, 3), verts.reshape(-1, 3), mat_index, coords.reshape(-1, 3)


def transform_points(matrix, points):
    m = np.array(matrix, dtype=np.float64)
    return points @ m[:3, :3].T + m[:3, 3]


def triangle_areas(points, verts):
    a, b, c = (points[verts[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def _world_area(obj, depsgraph) -> float:
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        if len(mesh.polygons) == 0:
            return 0.0
        _, verts, _, coords = loop_triangle_arrays(mesh)
        return float(triangle_areas(transform_points(obj.matrix_world, coords), verts).sum())
    finally:
        evaluated.to_mesh_clear()


def _uniform_colour_environment(color, black_reason: str) -> EnvironmentPlan:
    color = tuple(color)[:3]
    if max(color) <= 0:
        return EnvironmentPlan(False, "none", False, False, 0, black_reason)
    chromatic = (max(color) - min(color)) / max(color) > ACHROMATIC_CHROMA_MAX
    return EnvironmentPlan(True, "color", chromatic, True, 3 if chromatic else 1,
                           "uniform world colour: " + ("RGB" if chromatic else "mono") + " env visibility")


def analyse_environment(scene) -> EnvironmentPlan:
    world = scene.world
    if not uses_nodes(world):
        color = world.color if world is not None else (0.0, 0.0, 0.0)
        return _uniform_colour_environment(color, "no world: nothing to shadow")
    output = next((n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return EnvironmentPlan(False, "none", False, False, 0, "world has no surface shader")
    background = output.inputs["Surface"].links[0].from_node
    strength, linked_strength = _input_value(background, "Strength", 1.0)
    color_socket = background.inputs.get("Color")
    if not linked_strength and strength <= 0:
        return EnvironmentPlan(False, "none", False, False, 0, "world strength is 0: black environment")
    if color_socket is not None and color_socket.is_linked:
        source = color_socket.links[0].from_node
        if source.type == "TEX_ENVIRONMENT" and source.image is not None:
            chroma = _image_chroma(source.image)
            chromatic = chroma > ACHROMATIC_CHROMA_MAX
            return EnvironmentPlan(True, "hdri", chromatic, True, 3 if chromatic else 1,
                                   f"HDRI '{source.image.name}', chroma {chroma:.3f}: "
                                   + ("RGB" if chromatic else "mono") + " env visibility")
        return EnvironmentPlan(True, "hdri", True, True, 3, "procedural world: RGB env visibility")
    color = color_socket.default_value if color_socket is not None else (1.0, 1.0, 1.0)
    return _uniform_colour_environment(color, "world colour is black")


def _image_chroma(image) -> float:
    """Luminance-weighted mean of (max - min) / max over the image's finite, positive pixels."""
    pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    rgb = pixels.reshape(-1, image.channels)[:, :3].astype(np.float64)
    rgb = rgb[np.all(np.isfinite(rgb), axis=1)]
    rgb = np.maximum(rgb, 0)
    peak = rgb.max(axis=1)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    valid = peak > 0
    if not np.any(valid):
        return 0.0
    chroma = (peak[valid] - rgb[valid].min(axis=1)) / peak[valid]
    return float(np.sum(chroma * lum[valid]) / max(np.sum(lum[valid]), 1e-30))


@contextlib.contextmanager
def active_scene(scene):
    """Make `scene` the window's scene for the block: only the active scene has an evaluated depsgraph
    (modifiers applied). The previous scene comes back afterwards, also on errors."""
    window = bpy.context.window
    previous = window.scene if window is not None else None
    if window is not None and previous != scene:
        window.scene = scene
    try:
        yield bpy.context.evaluated_depsgraph_get()
    finally:
        if window is not None and previous is not None and window.scene != previous:
            window.scene = previous


def build_plan(scene, settings: BakeSettings) -> BakePlan:
    """Analyse `scene` and decide what to bake. Raises BakeInputError with one clear message."""
    with active_scene(scene) as depsgraph:
        return _build_plan(scene, settings, depsgraph)


def _build_plan(scene, settings: BakeSettings, depsgraph) -> BakePlan:
    settings.validate()
    visible = [o for o in scene.objects if not o.hide_render]
    meshes = [o for o in visible if o.type == "MESH"]
    if not meshes:
        kinds = sorted({o.type.lower() for o in visible})
        raise BakeInputError("nothing to bake: the scene has no mesh objects"
                             + (f" (only {', '.join(kinds)})" if kinds else " (it is empty)"))
    objects, emissive, warnings = [], [], []
    for obj in meshes:
        mats = [slot.material for slot in obj.material_slots] or [None]
        mat_plans = [analyse_material(m, settings) for m in mats]
        if any(_is_emissive(unbaked(m)) for m in mats if m is not None):
            emissive.append(obj.name)
        area = _world_area(obj, depsgraph)
        glossy = [mp.name for mp in mat_plans if mp.glossy]
        lightmapped = [mp.name for mp in mat_plans if mp.irradiance_only]
        baked = bool(glossy or lightmapped)
        if area <= 0:
            warnings.append(f"'{obj.name}': no faces with area, skipped")
            objects.append(ObjectPlan(obj.name, 0.0, 0, False, mat_plans, "no faces with area"))
            continue
        texels = int(np.ceil(area * settings.texel_density**2)) if baked else 0
        reason = "; ".join(([f"glossy material(s): {', '.join(glossy)}"] if glossy else [])
                           + ([f"irradiance lightmap: {', '.join(lightmapped)}"] if lightmapped else [])) \
            or "no glossy or lightmapped material: not baked, left to the renderer's own lighting"
        objects.append(ObjectPlan(obj.name, round(area, 6), texels, baked, mat_plans, reason))
    if not any(o.bake_lightfield for o in objects):
        raise BakeInputError("nothing to bake: no mesh has a glossy material (roughness below "
                             f"{GLOSSY_ROUGHNESS_MAX}) or a rough one to lightmap; the light field would not be used")
    lamps = [o.name for o in visible if o.type == "LIGHT" and o.data.energy > 0]
    hair = [o.name for o in visible if o.type == "CURVES"]
    environment = analyse_environment(scene)
    if environment.iwev and not any(m.glossy for o in objects if o.bake_lightfield for m in o.materials):
        environment.iwev, environment.iwev_channels = False, 0
        environment.reason += "; env visibility off: no glossy material (the irradiance lightmaps hold the sky)"
    if not lamps and not emissive and not environment.present:
        warnings.append("no lamps, emissive meshes or environment: the bake will be black")
    return BakePlan(scene=scene.name, settings=settings, objects=objects, environment=environment, lamps=lamps,
                    emissive_objects=emissive, hair_objects=hair, warnings=warnings)
