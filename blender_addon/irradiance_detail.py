"""The irradiance detail image (capture stage): the diffuse light of every baked surface at `irradiance_detail` times
the texel density, baked by Cycles.

The light fields give each texel its irradiance as the cosine-weighted mean of its panorama: at Draft's 4 texels/m
(25 cm texels) a lamp's shadow on the floor blurs over a texel or two, and EEVEE's own per-pixel shadows beat it
(docs/decisions.md, "Diffuse light at its own resolution"). Cycles' DIFFUSE bake (direct and indirect light, not
its colour) of a white Lambertian copy of each surface, with the material's own normal or bump map, is E / pi per
pixel for a fraction of the light fields' cost: no directions are stored, one value per pixel. It is baked into the
same atlas layout, `detail` pixels per texel, so the baked material reads it with the atlas UV it already computes.

Direct and indirect light are baked together at the detail's resolution: light that reaches a surface through a
Translucent BSDF or glass is indirect to Cycles (a shadow ray stops there), and at the texels' own resolution a leaf
card's light and a glass sphere's caustic blurred over 25-cm texels (docs/design-additions.md §50). One pass per
object: each bake is a Cycles sync of the whole scene, most of it the world's importance map (§51).
Same scene and the scene's own bounce budget (a bake point is a camera ray's hit: its paths count bounces as a
render's do, while the light fields leave one out because their camera sits on the surface), the user's lamps and
world as they are. The white copy shows only to the bake's own camera ray: a path that comes back to the object sees
its real material, or the demo room's light would bounce off a white floor (measured: walls 8 % too bright). Each
object's slots are swapped for the white copies for its own bake and restored after; the copies are removed.
"""
from __future__ import annotations

import contextlib
import math
import time

import bpy
import numpy as np

from ..bake_directory.bake_plan import IRRADIANCE_DETAIL_SAMPLES, BakeCancelled
from ..bake_directory.texel_raster import dilate
from .surface_probe import CyclesBakeSettings, bake_tile, bakes_in_place, hidden_from_rays, remove_probes
from .surface_shaders import BAKED_BSDFS, RENDERER_LIT, LeafInputs, copy_material, rewrite_surface

DETAIL_FILE = "irradiance_detail.exr"
DETAIL_SUFFIX = " (SG irradiance)"
DETAIL_IMAGE = "SGLF irradiance bake"


def white_diffuse_material(original):
    """A copy of `original` whose baked BSDFs (and Transparent BSDFs) are each, where the bake measures (a camera ray
    for Cycles' bake), a white Diffuse BSDF with that BSDF's own normal (normal or bump map), the shaders the renderer
    lights beside them (RENDERER_LIT) nothing there, and each of them itself for every other ray: light that bounces
    off another part of the same object keeps its colour (a room modelled as one object with red, green and white
    walls). With an active Image Texture node for the bake. Returns (material, node-group copies made for it)."""
    material = copy_material(original, DETAIL_SUFFIX)

    def build_leaf(tree, node):
        inputs = LeafInputs(tree, node)
        if node.type in RENDERER_LIT:  # not the bake's: nothing where it measures (translucent light from behind)
            diffuse = inputs._new("ShaderNodeBsdfTransparent")
        else:
            diffuse = inputs._new("ShaderNodeBsdfDiffuse")
            diffuse.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        if "Normal" in diffuse.inputs:
            inputs.feed(diffuse.inputs["Normal"], inputs.normal())
        where = inputs._new("ShaderNodeMixShader")
        tree.links.new(inputs._new("ShaderNodeLightPath").outputs["Is Camera Ray"], where.inputs[0])
        tree.links.new(node.outputs[0], where.inputs[1])
        tree.links.new(diffuse.outputs[0], where.inputs[2])
        return where.outputs[0]

    # a Transparent BSDF mixed in (a cut-out) is white too where the bake measures: the light of a texel half hole is
    # that of its opaque half, not dimmed by the hole
    groups = rewrite_surface(material, build_leaf, suffix=DETAIL_SUFFIX,
                             kinds=BAKED_BSDFS | RENDERER_LIT | {"BSDF_TRANSPARENT"})
    material.node_tree.nodes.active = material.node_tree.nodes.new("ShaderNodeTexImage")
    return material, groups


def bake_irradiance_detail(scene, targets, tiles, atlas_shape, detail: int, samples: int = IRRADIANCE_DETAIL_SAMPLES,
                           progress=lambda fraction, message: None, should_cancel=lambda: False):
    """Irradiance E (W/m^2 per unit radiance, as the light fields' quadrature gives it) of the capture `targets`, each
    baked into its tile (capture.ObjectTile) at `detail` pixels per texel, direct and indirect light with `samples`.
    Returns ((H * detail, W * detail, 3) float32 E, row 0 = the atlas' top; (H * detail, W * detail) mask of the pixels
    a bake wrote; {'seconds', 'samples', ...})."""
    start = time.perf_counter()
    height, width = atlas_shape[0] * detail, atlas_shape[1] * detail
    irradiance = np.zeros((height, width, 3), np.float32)
    written = np.zeros((height, width), bool)
    whites, created_groups = {}, []
    image = bpy.data.images.new(DETAIL_IMAGE, 4, 4, alpha=True, float_buffer=True)

    def white_for_slot(original):
        if original.name not in whites:
            whites[original.name], groups = white_diffuse_material(original)
            created_groups.extend(groups)
        return whites[original.name]

    try:
        for k, (target, tile) in enumerate(zip(targets, tiles)):
            if should_cancel():
                raise BakeCancelled("capture cancelled")
            progress(k / max(len(targets), 1), f"diffuse light of '{target.name}'")
            # a copy baked in the object's place: the original (all its instances) leaves the rays to it
            with contextlib.nullcontext() if bakes_in_place(target) else hidden_from_rays(target.obj):
                with CyclesBakeSettings(scene, samples):  # a margin of one texel's pixels: half the gutter each side
                    light = bake_tile(scene, target, tile, image, white_for_slot, bake_type="DIFFUSE",
                                      pass_filter={"DIRECT", "INDIRECT"}, scale=detail, margin=detail)
            x, y, w, h = (int(v) * detail for v in tile.pixel_rect)
            mine = light[..., 3] > 0
            block = irradiance[y:y + h, x:x + w]
            block[mine] = light[..., :3][mine] * math.pi  # the pass is E / pi: a white Lambertian's radiance
            written[y:y + h, x:x + w] |= mine
    finally:
        remove_probes(whites.values(), created_groups, image)
    irradiance = np.nan_to_num(np.maximum(irradiance, 0.0), nan=0.0, posinf=0.0)
    return irradiance, written, {"seconds": round(time.perf_counter() - start, 3), "samples": samples,
                                 "detail": detail, "size": [width, height]}


def filled(irradiance: np.ndarray, written: np.ndarray, rings: int) -> np.ndarray:
    """Pixels no bake wrote, up to `rings` pixels from written ones, copied from a neighbour: a renderer's bilinear
    (and EEVEE's mipmapped) lookup near a chart's edge then blends the chart's own light, not black."""
    out, _ = dilate({"E": irradiance}, written, rings)
    return out["E"]


def texel_means(irradiance: np.ndarray, written: np.ndarray, detail: int, texels: np.ndarray) -> np.ndarray:
    """(T, 3) mean of the written detail pixels inside each texel (T, 2) [row, col]; NaN where none was written."""
    height, width = irradiance.shape[0] // detail, irradiance.shape[1] // detail
    blocks = irradiance.reshape(height, detail, width, detail, 3)
    weights = written.reshape(height, detail, width, detail).astype(np.float64)
    rows, cols = texels[:, 0], texels[:, 1]
    total = np.einsum("tijc,tij->tc", blocks[rows, :, cols, :].astype(np.float64), weights[rows, :, cols, :])
    count = weights[rows, :, cols, :].sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count[:, None]
