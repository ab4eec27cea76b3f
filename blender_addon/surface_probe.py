"""Per-texel material values measured from the material itself (capture stage, DESIGN section 10).

Where a baked BSDF's inputs are driven by links (image or procedural textures, attributes, node groups), the texel
maps' roughness, metallic, base colour and F0 are not constants. They are measured by Cycles: each object's slots are
swapped for probe copies of their materials in which every baked BSDF is replaced by an Emission of one quantity
computed from the BSDF's own inputs (surface_shaders.LeafInputs, the same nodes the baked copy shades with), and an
EMIT bake with the lightmap layer writes it into an image of the object's atlas tile. PROBE_SAMPLES jittered samples
per texel average the texture over the texel's footprint. Mix Shader factors blend the quantities as they blend the
BSDFs, and each texel's values are divided by the BSDFs' share of its surface (the rest is emission, holdout or
transparency). Slots, selection and render settings are restored before returning, also on errors; the probes are
removed.
"""
from __future__ import annotations

import contextlib
import time

import bpy
import numpy as np

from .surface_shaders import BAKED_BSDFS, KEPT_SHADERS, RENDERER_LIT, LeafInputs, copy_material, rewrite_surface
from .scene_analysis import quiet_stdout, unbaked

PROBE_SUFFIX = " (SG probe)"
PROBE_IMAGE = "SGLF surface probe"
PROBE_SAMPLES = 16
EDGE_MARGIN = 3  # texels: the capture's gutter (UV_PADDING) and one more
# Three bakes, three colour channels each: (roughness, metallic, weight), base colour, F0. Texel-map channel order.
# The weight is the baked BSDFs' share of the surface (Mix Shader factors with emission, holdout or a Transparent
# BSDF, which emit nothing in the probes): every quantity is divided by it, and a texel the BSDFs do not cover (in
# the holes of a cut-out) takes the mean of the object's covered texels.
MIN_WEIGHT = 0.01
PASSES = ("roughness_metallic", "base", "f0")
SURFACE_CHANNELS = 8  # roughness, metallic, base RGB, F0 RGB


def _quantity(inputs: LeafInputs, name: str):
    if name == "roughness_metallic":
        combine = inputs._new("ShaderNodeCombineColor")
        inputs.feed(combine.inputs[0], inputs.roughness())
        inputs.feed(combine.inputs[1], inputs.metallic())
        combine.inputs[2].default_value = 1.0  # the weight
        return combine.outputs[0]
    return inputs.base_colour() if name == "base" else inputs.f0()


def probe_material(original, suffix: str, emit,
                   kinds=BAKED_BSDFS | RENDERER_LIT | (KEPT_SHADERS - {"BSDF_TRANSPARENT"})):
    """A copy of `original` (named NAME + suffix) whose shaders of `kinds` are each replaced by an Emission of
    emit(LeafInputs, node) (a socket or a constant colour), cut out by a Principled BSDF's Alpha as the BSDF is; a
    Transparent BSDF stays (it emits nothing, and a camera sees through it). With an active Image Texture node for a
    bake to write into. Returns (material, the node-group copies made for it)."""
    material = copy_material(original, suffix)

    def build_leaf(tree, node):
        inputs = LeafInputs(tree, node)
        return inputs.cut_out(inputs.emission_of(emit(inputs, node)))

    groups = rewrite_surface(material, build_leaf, suffix=suffix, kinds=kinds)
    material.node_tree.nodes.active = material.node_tree.nodes.new("ShaderNodeTexImage")
    return material, groups


def _probe_material(original, name: str):
    """The probe of one PASSES quantity: baked BSDFs emit it, the material's own emitters and the shaders the renderer
    lights emit nothing."""
    return probe_material(original, f"{PROBE_SUFFIX} {name}",
                          lambda inputs, node: _quantity(inputs, name) if node.type in BAKED_BSDFS else (0.0, 0.0, 0.0))


def bake_tile(scene, target, tile, image, material_for_slot, *, bake_type="EMIT", pass_filter=frozenset(),
               scale: int = 1, margin: int = EDGE_MARGIN) -> np.ndarray:
    """Bake the target (`bake_type`, with `pass_filter`) into `image` (resized to its tile, `scale` pixels per texel)
    with each slot's material swapped for material_for_slot(original) (which must hold an active Image Texture node;
    its image is set here); the slots are restored before returning. Returns (h, w, 4) RGBA, row 0 = the tile's top
    row; alpha is 0 where the bake wrote nothing."""
    x, y, w, h = (int(v) * scale for v in tile.pixel_rect)
    if tuple(image.size) != (w, h):
        image.scale(w, h)
    undo = []
    with _bake_object(scene, target) as baked:
        try:
            for slot in baked.material_slots:
                original = unbaked(slot.material) if slot.material is not None else None
                if original is None:
                    continue
                probe = material_for_slot(original)
                probe.node_tree.nodes.active.image = image
                undo.append((slot, slot.material))
                slot.material = probe
            with bpy.context.temp_override(scene=scene, view_layer=scene.view_layers[0], active_object=baked,
                                           object=baked, selected_objects=[baked],
                                           selected_editable_objects=[baked]), quiet_stdout():
                # texels whose centre misses every triangle (chart edges) get their nearest baked neighbour
                bpy.ops.object.bake(type=bake_type, pass_filter=set(pass_filter), uv_layer=tile.uv_layer,
                                    margin=margin, margin_type="EXTEND", use_clear=True, target="IMAGE_TEXTURES")
        finally:
            for slot, material in reversed(undo):
                slot.material = material
    pixels = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(h, w, 4)[::-1]  # image rows from the bottom, atlas rows from the top


RAY_VISIBILITY = ("visible_camera", "visible_diffuse", "visible_glossy", "visible_transmission",
                  "visible_volume_scatter", "visible_shadow")


def bakes_in_place(target) -> bool:
    """Whether Cycles bakes the target's own object (a plain mesh of the scene) rather than a temporary copy."""
    obj = target.obj
    return obj.type == "MESH" and not obj.modifiers and target.instancer is None


@contextlib.contextmanager
def hidden_from_rays(obj):
    """`obj` (and so its instances) invisible to every Cycles ray for the block: a temporary copy that bakes its
    surface in its place must not find the original's coincident surface at distance 0 (a lighting bake of a copy
    beside its original measured 0 everywhere). Its settings come back after."""
    saved = {name: getattr(obj, name) for name in RAY_VISIBILITY}
    try:
        for name in RAY_VISIBILITY:
            setattr(obj, name, False)
        yield
    finally:
        for name, value in saved.items():
            setattr(obj, name, value)


@contextlib.contextmanager
def _bake_object(scene, target):
    """What Cycles bakes for a capture target: the object itself when it renders its mesh data where it stands;
    otherwise (a modifier stack, the SG Lightmap UV modifier, text, curves, an instance) a temporary mesh object
    holding its evaluated surface at the target's matrix, which Blender's bake can take (it bakes mesh objects only
    and looks the UV layer up on the mesh data)."""
    obj = target.obj
    if bakes_in_place(target):
        yield obj
        return
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = bpy.data.meshes.new_from_object(obj.evaluated_get(depsgraph), preserve_all_data_layers=True,
                                           depsgraph=depsgraph)
    copy = bpy.data.objects.new(f"{obj.name} (SG probe)", mesh)
    copy.matrix_world = target.matrix
    for index, slot in enumerate(obj.material_slots):
        if index < len(copy.material_slots):
            copy.material_slots[index].material = slot.material
    scene.collection.objects.link(copy)
    try:
        yield copy
    finally:
        bpy.data.objects.remove(copy)
        bpy.data.meshes.remove(mesh)


class CyclesBakeSettings:
    """Cycles with `samples` (PROBE_SAMPLES) and no denoising for the block; the scene's settings come back after.
    traces_light=False (EMIT bakes: each point's own emission, no rays): the world is not importance sampled, since
    Cycles builds its importance map at every bake's sync (0.7 s per object with the shipped HDRIs)."""

    def __init__(self, scene, samples: int = PROBE_SAMPLES, traces_light: bool = True):
        self.scene, self.samples, self.traces_light = scene, samples, traces_light

    def __enter__(self):
        render, cycles, world = self.scene.render, self.scene.cycles, self.scene.world
        self.saved = (render.engine, cycles.samples, cycles.use_denoising)
        render.engine, cycles.samples, cycles.use_denoising = "CYCLES", self.samples, False
        self.saved_world_sampling = None  # (world, its sampling method) where the block turned it off
        if world is not None and world.library is None and not self.traces_light:
            self.saved_world_sampling = (world, world.cycles.sampling_method)
            world.cycles.sampling_method = "NONE"
        return self

    def __exit__(self, *exc):
        render, cycles = self.scene.render, self.scene.cycles
        render.engine, cycles.samples, cycles.use_denoising = self.saved
        if self.saved_world_sampling is not None:
            world, method = self.saved_world_sampling
            world.cycles.sampling_method = method


def remove_probes(materials, groups, image):
    """Remove a bake's probe materials, the node-group copies made for them (once unused) and its image."""
    for material in materials:
        bpy.data.materials.remove(material)
    for group in reversed(list(groups)):
        if group.users == 0:
            bpy.data.node_groups.remove(group)
    bpy.data.images.remove(image)


def measure_surfaces(scene, targets, tiles, atlas_shape, object_ids, should_measure) -> tuple[np.ndarray, np.ndarray,
                                                                                               dict]:
    """Bake the surface quantities of the capture `targets` (scene_analysis.BakeTarget, each with its tile) whose
    materials `should_measure(material)`.
    object_ids: (H, W) the atlas' object id per texel (0 = none). Returns ((H, W, 8) values, (H, W) measured mask,
    {'seconds', 'objects'})."""
    start = time.perf_counter()
    height, width = atlas_shape
    values = np.zeros((height, width, SURFACE_CHANNELS), np.float32)
    measured = np.zeros((height, width), bool)
    chosen = [(target, tile) for target, tile in zip(targets, tiles) if any(
        s.material is not None and should_measure(unbaked(s.material)) for s in target.obj.material_slots)]
    if not chosen:
        return values, measured, {"seconds": 0.0, "objects": []}
    probes, created_groups = {}, []
    image = bpy.data.images.new(PROBE_IMAGE, 4, 4, alpha=True, float_buffer=True)

    def probe_for(name):
        def material_for_slot(original):
            if (original.name, name) not in probes:
                probes[(original.name, name)], groups = _probe_material(original, name)
                created_groups.extend(groups)
            return probes[(original.name, name)]
        return material_for_slot

    try:
        with CyclesBakeSettings(scene, traces_light=False):
            for target, tile in chosen:
                x, y, w, h = tile.pixel_rect
                mine = object_ids[y:y + h, x:x + w] == tile.id
                block = values[y:y + h, x:x + w]
                for k, name in enumerate(PASSES):
                    baked = bake_tile(scene, target, tile, image, probe_for(name))[..., :3]
                    if k == 0:  # its third channel is the weight; roughness and metallic are the first two
                        weight = baked[..., 2]
                        covered = mine & (weight > MIN_WEIGHT)
                    columns = slice(0, 2) if k == 0 else slice(3 * k - 1, 3 * k + 2)
                    block[covered, columns] = (baked[covered] / weight[covered, None])[:, :columns.stop - columns.start]
                if covered.any():  # a texel wholly in a hole (never seen) gets the object's mean
                    block[mine & ~covered] = block[covered].mean(axis=0)
                    measured[y:y + h, x:x + w] |= mine
    finally:
        remove_probes(probes.values(), created_groups, image)
    np.clip(values, 0.0, 1.0, out=values)
    return values, measured, {"seconds": round(time.perf_counter() - start, 3), "objects": [t.name for t, _ in chosen]}


def mean_of_links(scene, target, tile, object_ids, material, inputs) -> dict:
    """The mean over a capture target's texels (scene_analysis.BakeTarget) of what the links into `inputs` of `material` carry: {(node name, input
    identifier): RGB}, each by an EMIT bake of a copy of the material whose surface is an Emission of that link.
    Only nodes of the material's own tree are named (not inside node groups)."""
    x, y, w, h = tile.pixel_rect
    mine = object_ids[y:y + h, x:x + w] == tile.id
    image = bpy.data.images.new(PROBE_IMAGE, 4, 4, alpha=True, float_buffer=True)
    made, means = [], {}
    try:
        with CyclesBakeSettings(scene, traces_light=False):
            for node_name, identifier in inputs:
                def material_for_slot(original, node_name=node_name, identifier=identifier):
                    copy = original.copy()
                    made.append(copy)
                    tree = copy.node_tree
                    if original == material:
                        socket = next(s for s in tree.nodes[node_name].inputs if s.identifier == identifier)
                        emission = tree.nodes.new("ShaderNodeEmission")
                        tree.links.new(socket.links[0].from_socket, emission.inputs["Color"])
                        for output in [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]:
                            tree.links.new(emission.outputs[0], output.inputs["Surface"])
                    tree.nodes.active = tree.nodes.new("ShaderNodeTexImage")
                    return copy

                baked = bake_tile(scene, target, tile, image, material_for_slot)[..., :3]
                means[(node_name, identifier)] = tuple(float(v) for v in baked[mine].mean(axis=0))
    finally:
        for copy in made:
            bpy.data.materials.remove(copy)
        bpy.data.images.remove(image)
    return means
