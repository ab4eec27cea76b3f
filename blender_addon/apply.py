"""Apply stage: SG textures into one packed image, the "SG Lightfield" node group, and a non-destructive
material write-back with an exact undo (Remove SG Bake).

Non-destructive by construction: every baked material slot gets a copy of its material ("NAME (SG bake)")
whose nodes are replaced by the baked shading; the user's original material is never edited, only kept
alive with a fake user while a bake refers to it. `remove_bake` puts the originals back into the slots and
deletes what the bake made (copies, node group, image, lightmap UV layers and tile properties).

Diffuse comes from an irradiance tile computed from the rendered light fields (plus the L_E*V images of the
sky when IWEV holds the environment) by quadrature (exact up to the light-field resolution and one texture
lookup), not from the SGs: the bake measures both and reports
how far the SG irradiance is from it (report.json: apply.irradiance_from_sgs_rel_error). With an irradiance detail
above 1 (every preset) it comes instead from the capture's detail image (irradiance_detail.py), read at the same atlas
UV; apply reports the ratio of its texel means' total to the light fields' (apply.irradiance_detail_over_lightfields).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import bpy
import numpy as np

from ..bake_directory.bake_plan import BakeInputError
from ..bake_directory.bake_report import update_report
from ..bake_directory.exr_io import read_exr, write_exr
from ..bake_directory.lightfield_tiles import read_images
from ..shaders.node_group import (GROUP_NAME, UNIFORM_BLOCK_LIMIT, VERSION_KEY, SGTextureLayout, build_node_group,
                                  eevee_uniform_bytes, flattened_node_count, material_output)
from ..shaders.octahedral import pixel_directions, pixel_solid_angles
from ..shaders.sg_math import CLAMPED_COSINE_LEGENDRE, sg_irradiance
from ..shaders.sg_shading import SH_L2_BAND, NumpyOps, encode_sharpness, sh_l2_basis
from ..bake_directory.sg_textures import (is_sh_texture, pack_tiles, read_sg_texture, read_sh_texture, scatter_dilated,
                               sg_texture_path)
from ..bake_directory.texel_maps import channels, read_texel_maps, smooth_over_texels, texels_of_objects
from . import lightmap_modifier
from .irradiance_detail import DETAIL_FILE, texel_means
from .scene_analysis import active_scene, bake_targets
from .capture import BLOCK_KEY, LIGHTMAP_LAYER, OFFSET_KEY, SCALE_KEY, remove_lightmap_uvs
from .surface_shaders import (COPY_KEY, COPY_SUFFIX, LeafInputs, analyse_surface, copy_material,
                              remove_unused_group_copies, rewrite_surface)

BAKE_RECORD_KEY = "sglf_bake"  # on the scene: JSON {object: {slot index: original material}}
FAKE_USER_KEY = "sglf_fake_user_set"  # on an original: we set its fake user (and clear it again)
IMAGE_NAME = "SG Lightfield textures"
DETAIL_IMAGE_NAME = "SG Lightfield irradiance"
PACKED_FILE = "sg_packed.exr"


def irradiance_from_lightfields(images: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E(n) = sum over pixels of L max(n.d, 0) solid angle: (T, C)."""
    if not len(images):
        return np.zeros((0, images.shape[-1]))
    r = images.shape[1]
    d = pixel_directions(r).reshape(-1, 3)
    w = pixel_solid_angles(r).reshape(-1)
    cosine = np.maximum(np.asarray(normals, np.float64) @ d.T, 0.0) * w  # (T, P)
    return np.einsum("tp,tpc->tc", cosine, images.reshape(len(images), -1, images.shape[-1]).astype(np.float64))


def read_irradiance_detail(out_dir: Path, plan, layout: str = "") -> tuple[Path | None, np.ndarray | None]:
    """The capture's irradiance detail image (path, (H * detail, W * detail, 3) E) when the settings ask for one;
    `layout`: the texel maps' layout hash, which the image must have been baked for."""
    detail = plan.settings.irradiance_detail
    if detail <= 1:
        return None, None
    path = Path(out_dir) / DETAIL_FILE
    if not path.is_file():
        raise BakeInputError(f"{path}: missing; the settings ask for irradiance detail {detail}: run the capture stage")
    irradiance, _, metadata = read_exr(path)
    if metadata.get("plan_hash") != plan.stage_hash("capture") or metadata.get("detail") != str(detail):
        raise BakeInputError(f"{path}: made for another capture or detail ({metadata.get('detail')}, the settings ask "
                             f"for {detail}); run the capture stage again")
    if layout and metadata.get("layout") != layout:
        raise BakeInputError(f"{path}: made for another lightmap layout than the texel maps' (an object's texel scale "
                             "or geometry changed since); run the capture stage again")
    return path, irradiance


def build_packed_image(out_dir: Path, plan) -> tuple[SGTextureLayout, Path, dict]:
    """Pack SG + irradiance tiles into DIR/sg_packed.exr (half RGBA); returns layout, path, measurements, the
    environment's SGs and the irradiance detail image's path (None when the irradiance is a tile)."""
    atlas, texel_info = read_texel_maps(out_dir, plan.stage_hash("capture"))
    shape = atlas.shape[:2]
    detail_path, detail = read_irradiance_detail(out_dir, plan, texel_info.get("layout_hash", ""))
    lightfield = sg_texture_path(out_dir, "lightfield")
    encoded = bool(plan.sg_objects)  # else only irradiance lightmaps: no SG texture
    if encoded and not Path(lightfield).is_file():
        raise BakeInputError(f"{lightfield}: not trained yet; run the train stage first")
    sh = encoded and is_sh_texture(lightfield)  # the benchmark's SH L2 baseline instead of SGs
    n = 0
    if sh:
        coefficients, _ = read_sh_texture(lightfield, plan.stage_hash("train"))
    elif encoded:
        axis, sharpness, amplitude, meta = read_sg_texture(lightfield, plan.stage_hash("train"))
        n = int(meta["sg_count"])
    if encoded or detail is None:
        texels, images = read_images(out_dir / "lightfield", plan.stage_hash("render"))
    else:  # irradiance lightmaps only, their light in the detail image: the render stage made no light fields
        texels, images = np.zeros((0, 2), np.int64), np.zeros((0, 1, 1, 3), np.float32)
    shading = channels(atlas, "N.X", 3)[texels[:, 0], texels[:, 1]].astype(np.float64)
    irradiance = encoded_irradiance = irradiance_from_lightfields(images, shading)
    if plan.environment.iwev and len(texels):  # the light field leaves the sky to IWEV; diffuse still needs its light
        sky_texels, sky = read_images(out_dir / "env_occluded", plan.stage_hash("render"))
        if not np.array_equal(sky_texels, texels):
            raise BakeInputError(f"{out_dir}: env_occluded and lightfield texels differ; render again")
        irradiance = irradiance + irradiance_from_lightfields(sky, shading)
    # How far the encoding's own irradiance is from that of what it encodes (with IWEV, the light field without
    # the sky), on the texels that have an encoding.
    with_sgs = texels_of_objects(atlas, texel_info, texels, plan.sg_objects)
    r, c = texels[with_sgs, 0], texels[with_sgs, 1]
    if sh:  # Funk-Hecke with the clamped cosine: band l scaled by its Legendre coefficient
        basis = np.stack(np.broadcast_arrays(*sh_l2_basis(NumpyOps(), shading[with_sgs])), -1)  # (T, 9)
        cosine_bands = np.array([CLAMPED_COSINE_LEGENDRE[band] for band in SH_L2_BAND])
        from_encoding = np.einsum("tk,tkc->tc", basis * cosine_bands, coefficients[r, c].astype(np.float64))
    elif encoded:
        from_encoding = sg_irradiance(axis[r, c].astype(np.float64), sharpness[r, c].astype(np.float64),
                                      amplitude[r, c].astype(np.float64), shading[with_sgs, None, :]).sum(axis=1)
    else:
        from_encoding = np.zeros((0, irradiance.shape[1]))
    exact = encoded_irradiance[with_sgs].sum(axis=1)
    lit = exact > 1e-6 * max(exact.max(initial=0.0), 1e-30)
    rel = np.abs(from_encoding - encoded_irradiance[with_sgs]).sum(axis=1)[lit] / exact[lit]
    iwev_count, env_sgs, tiles = 0, [], {}
    if plan.environment.iwev:
        w_axis, w_sharpness, w_amplitude, w_meta = read_sg_texture(sg_texture_path(out_dir, "env_visibility"),
                                                                   plan.stage_hash("train"))
        iwev_count = int(w_meta["sg_count"])
        env_path = out_dir / "env_sgs.json"
        if not env_path.is_file():
            raise BakeInputError(f"{out_dir}: no env_sgs.json; run the train stage again")
        env = json.loads(env_path.read_text())
        if env.get("plan_hash") != plan.stage_hash("train"):
            raise BakeInputError(f"{env_path}: made for another plan; run the train stage again")
        env_sgs = [tuple(sg) for sg in env["sgs"]]
    layout = SGTextureLayout(n, iwev_count=iwev_count, has_irradiance=True, atlas_size=(shape[1], shape[0]),
                             sh_count=coefficients.shape[2] if sh else 0,
                             irradiance_detail=plan.settings.irradiance_detail if detail is not None else 1)
    for j in range(layout.sh_count):
        tiles[("sh", j)] = np.concatenate([coefficients[..., j, :], np.zeros(shape + (1,))], -1)
    for j in range(iwev_count):
        amp = w_amplitude[..., j, :]
        amp = np.repeat(amp, 3, axis=-1) if amp.shape[-1] == 1 else amp  # mono W_E: the same value in R, G, B
        tiles[("iwev", j)] = np.concatenate([w_axis[..., j, :], encode_sharpness(w_sharpness[..., j])[..., None]], -1)
        tiles[("iwev_amp", j)] = np.concatenate([amp, np.zeros(shape + (1,))], -1)
    for j in range(n):
        tiles[("sg", j)] = np.concatenate([axis[..., j, :], encode_sharpness(sharpness[..., j])[..., None]], -1)
        tiles[("amp", j)] = np.concatenate([amplitude[..., j, :], np.zeros(shape + (1,))], -1)
    measured = {}
    if detail is None:
        lightmap = smooth_over_texels(atlas, texels, irradiance)  # for the diffuse; the check above took the unsmoothed
        tiles[("irradiance", 0)] = np.concatenate([scatter_dilated(shape, texels, lightmap), np.ones(shape + (1,))], -1)
    else:  # two independent estimates of the texels' irradiance: Cycles' bake, the light fields' quadrature
        means = texel_means(detail, np.ones(detail.shape[:2], bool), plan.settings.irradiance_detail, texels)
        total = float(irradiance.sum())
        measured = {"irradiance_detail_over_lightfields": float(means.sum()) / total if total > 0 else None}
    path = write_exr(out_dir / PACKED_FILE, pack_tiles(layout, tiles, shape), precision="half",
                     channels=["R", "G", "B", "A"], metadata={"plan_hash": plan.stage_hash("train"),
                                                              "layout": json.dumps(layout.to_dict())})
    measured.update({"irradiance_from_sgs_rel_error_median": float(np.median(rel)) if len(rel) else 0.0,
                     "irradiance_from_sgs_rel_error_p95": float(np.percentile(rel, 95)) if len(rel) else 0.0,
                     "irradiance_from_sgs_rel_error_max": float(rel.max()) if len(rel) else 0.0})
    return layout, path, measured, env_sgs, detail_path


def _load_image(path: Path, pack: bool, name: str = IMAGE_NAME):
    image = bpy.data.images.get(name)
    if image is None:
        image = bpy.data.images.load(str(path), check_existing=False)
        image.name = name
    else:
        if image.packed_file is not None:
            image.unpack(method="REMOVE")
        image.filepath = str(path)
        image.reload()
    image.colorspace_settings.name = "Non-Color"
    image.alpha_mode = "CHANNEL_PACKED"  # alpha holds encoded sharpness: never premultiply
    if pack:
        image.pack()
    elif bpy.data.filepath:
        try:
            image.filepath = bpy.path.relpath(str(path))
        except ValueError:  # another drive: keep the absolute path
            pass
    return image


def _lightmap_uv(tree):
    """Nodes in `tree` giving the atlas UV of the shaded point: the lightmap layer placed in the tile of the object
    or instance. Instancer attributes: a geometry-node instance's own tile, else the object's; plus, for a member of
    a collection instance, where the empty's block of tiles is (capture.BLOCK_KEY; 0 elsewhere)."""
    uv = tree.nodes.new("ShaderNodeUVMap")
    uv.uv_map = LIGHTMAP_LAYER
    offset, scale, block = (tree.nodes.new("ShaderNodeAttribute") for _ in range(3))
    for node, key in ((offset, OFFSET_KEY), (scale, SCALE_KEY), (block, BLOCK_KEY)):
        node.attribute_type, node.attribute_name = "INSTANCER", key
    in_tile = tree.nodes.new("ShaderNodeVectorMath")
    in_tile.operation = "MULTIPLY_ADD"
    tree.links.new(uv.outputs["UV"], in_tile.inputs[0])
    tree.links.new(scale.outputs["Vector"], in_tile.inputs[1])
    tree.links.new(offset.outputs["Vector"], in_tile.inputs[2])
    atlas_uv = tree.nodes.new("ShaderNodeVectorMath")
    atlas_uv.operation = "ADD"
    tree.links.new(in_tile.outputs["Vector"], atlas_uv.inputs[0])
    tree.links.new(block.outputs["Vector"], atlas_uv.inputs[1])
    made = (uv, scale, offset, in_tile, block, atlas_uv)
    left = min((n.location.x for n in tree.nodes if n not in made), default=0.0)
    for i, node in enumerate(made):
        node.location, node.hide = (left - 1100 + 200 * i, 400), True
    return atlas_uv.outputs["Vector"]


def _baked_material(original, group, irradiance_group):
    """The baked copy of `original`: its own node tree with every baked BSDF replaced by an emission of the bake's
    shading (surface_shaders.rewrite_surface). The SG group takes the BSDF's own inputs (normal or bump map,
    roughness, metallic, F0 and diffuse albedo computed per pixel from base colour, metallic, IOR, specular level and
    tint); a Diffuse BSDF shows its colour times the group's Irradiance (E / pi); a Principled BSDF's emission is
    kept, and its coat stays for the renderer to light over the baked layers (LeafInputs.under_coat), and its Alpha
    cuts the baked lighting out as it cuts the BSDF; see-through materials keep the user's BSDFs on back faces
    (LeafInputs.see_through).
    An earlier copy is replaced by a fresh one (its users follow), so a re-apply starts from the user's material.
    `irradiance_group()` makes the irradiance-only group, called only when a Diffuse BSDF needs it."""
    stale = bpy.data.materials.get(original.name + COPY_SUFFIX)
    if stale is not None and stale.get(COPY_KEY) == original.name:
        stale.name = stale.name + " (stale)"
    else:
        stale = None
    material = copy_material(original)
    if stale is not None:
        stale.user_remap(material)
        bpy.data.materials.remove(stale)
    uv_of_tree = {}
    two_sided = analyse_surface(original).two_sided

    def build_leaf(tree, bsdf):
        inputs = LeafInputs(tree, bsdf)
        key = tree.as_pointer()
        if key not in uv_of_tree:
            uv_of_tree[key] = _lightmap_uv(tree)
        node = inputs._new("ShaderNodeGroup", node_tree=irradiance_group() if bsdf.type == "BSDF_DIFFUSE" else group)
        node.hide = False
        tree.links.new(uv_of_tree[key], node.inputs["UV"])
        inputs.feed(node.inputs["Normal"], inputs.normal())
        inputs.feed(node.inputs["Roughness"], inputs.roughness())
        inputs.feed(node.inputs["F0"], inputs.f0())
        inputs.feed(node.inputs["Albedo"], inputs.albedo())
        inputs.feed(node.inputs["Metallic"], inputs.metallic())
        if bsdf.type == "BSDF_DIFFUSE":
            shaded = inputs.emission_of(inputs.multiply_colours(node.outputs["Irradiance"], inputs.base_colour()))
        else:  # one emission per output, summed as closures: the group's Total, or the same sum in math nodes, renders
            # black in Cycles 5.0 when a Bump node with a textured height feeds Normal (measured: the Glossy,
            # Environment and Diffuse outputs each render right, and so do their emissions added as shaders)
            shaded = None
            for output in ("Glossy", "Environment", "Diffuse"):
                if output == "Environment" and not group.get("sglf_has_environment", True):
                    continue
                emission = inputs.emission_of(node.outputs[output])
                shaded = emission if shaded is None else inputs.add_shaders(shaded, emission)
        return inputs.see_through(inputs.under_coat(inputs.add_shaders(shaded, inputs.emission())), two_sided)

    rewrite_surface(material, build_leaf)
    return material


def is_bake_group(tree) -> bool:
    """Whether a node tree is one of the bake's node groups (an evaluator 'SG Lightfield ...' or a group inside one)."""
    return tree is not None and VERSION_KEY in tree and tree.name.startswith(GROUP_NAME)


def baked_groups(material, renderer: str = "EEVEE") -> list:
    """The bake's node groups (SG Lightfield ...) that `renderer`'s ('EEVEE' or 'CYCLES') Material Output of a baked
    material reaches, through the user's nodes and node groups, in the order first reached."""
    found, seen = [], set()
    output = material_output(material.node_tree, renderer)
    stack = [output] if output is not None else []
    while stack:
        node = stack.pop()
        if node.as_pointer() in seen:
            continue
        seen.add(node.as_pointer())
        if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
            if is_bake_group(node.node_tree):
                found.append(node.node_tree)
                continue
            stack += [n for n in node.node_tree.nodes if n.bl_idname == "NodeGroupOutput"]
        stack += [link.from_node for socket in node.inputs for link in socket.links if not link.is_muted]
    return list(dict.fromkeys(found))


def baked_group(material, renderer: str = "EEVEE"):
    """The first of baked_groups (the one a single-BSDF material shades with), or None."""
    groups = baked_groups(material, renderer)
    return groups[0] if groups else None


def apply_stage(scene, plan, out_dir, *, pack_images: bool = True, progress=None) -> dict:
    """Write the bake into the scene's materials. Returns what was done (also merged into report.json)."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    with active_scene(scene) as depsgraph:
        targets = bake_targets(scene, plan.baked_objects, depsgraph)
    layout, path, measured, env_sgs, detail_path = build_packed_image(out_dir, plan)
    image = _load_image(path, pack_images)
    detail_image = _load_image(detail_path, pack_images, DETAIL_IMAGE_NAME) if detail_path else None
    groups = {}  # SG count (None: irradiance only) -> the node group evaluating the packed image

    def evaluated_count(planned: int) -> int:
        # Textures with another SG count than the plan's (the fixed-SG baseline) are evaluated whole everywhere.
        return min(planned, layout.sg_count) if layout.sg_count == plan.max_sg_count else layout.sg_count

    def group_for(planned: int):
        """One group per SG count, EEVEE's graph (it fits EEVEE's uniform block), shading both renderers. A Cycles-only
        graph beside it (Vector Math nodes, constants as socket values: 20-33 % faster Cycles renders) made EEVEE
        spend 80 s (spheres) to 5 CPU-minutes (courtyard) per material compiling, against 5 s without it
        (docs/design-additions.md §18-19). A planned count of 0 (an irradiance lightmap) reads only the irradiance
        tile, whatever the encoder."""
        count = evaluated_count(planned) if planned else None
        if count not in groups:
            if count is None:
                fewer, name = SGTextureLayout(0, 0, True, layout.atlas_size, tiles=layout.tiles,
                                              irradiance_detail=layout.irradiance_detail), f"{GROUP_NAME} (irradiance)"
            elif layout.sh_count:
                fewer, name = layout, f"{GROUP_NAME} (SH L2)"
            else:
                fewer = SGTextureLayout(count, min(count, layout.iwev_count), layout.has_irradiance, layout.atlas_size,
                                        tiles=layout.tiles,  # the same tiles: only the first `count` SGs are read
                                        irradiance_detail=layout.irradiance_detail)
                name = GROUP_NAME if count == layout.sg_count else f"{GROUP_NAME} ({count} SGs)"
            groups[count] = build_node_group(image, fewer, env_sgs, name, irradiance_image=detail_image)
        return groups[count]

    record = json.loads(scene.get(BAKE_RECORD_KEY, "{}"))
    baked_materials, switched = set(), set()
    for object_plan, target in zip(plan.baked_objects, targets):
        obj = target.obj
        holder = target.instancer or obj  # where its tile is
        if OFFSET_KEY not in holder and BLOCK_KEY not in holder and lightmap_modifier.instance_tiles_of(holder) is None:
            raise BakeInputError(f"'{object_plan.name}': not captured (no lightmap tile); run the capture stage first")
        if obj.name in switched:  # another instance of the same object: its slots are switched already
            continue
        switched.add(obj.name)
        baked_counts = {m.name: m.sg_count if m.glossy else 0 for m in object_plan.materials if m.baked}
        slots = record.setdefault(obj.name, {})
        for index, slot in enumerate(obj.material_slots):
            current = slot.material
            if current is None:
                continue
            original = bpy.data.materials.get(current.get(COPY_KEY, current.name))
            if original is None or original.name not in baked_counts:
                continue
            if not original.use_fake_user:
                original.use_fake_user = True
                original[FAKE_USER_KEY] = True
            copy = _baked_material(original, group_for(baked_counts[original.name]), lambda: group_for(0))
            slot.material = copy
            slots[str(index)] = original.name
            scene[BAKE_RECORD_KEY] = json.dumps(record)  # recorded at once: an interrupted apply can be undone
            baked_materials.add(copy.name)
    scene[BAKE_RECORD_KEY] = json.dumps(record)
    remove_unused_group_copies()  # of an earlier apply's copies
    _remove_unused_groups()  # of an earlier bake with other SG counts
    stale = bpy.data.images.get(DETAIL_IMAGE_NAME) if detail_image is None else None
    if stale is not None and stale.users == 0:  # an earlier apply's, now that the irradiance is a tile again
        bpy.data.images.remove(stale)
    uniform_bytes = {name: eevee_uniform_bytes(bpy.data.materials[name])["bytes"] for name in sorted(baked_materials)}
    warnings = [f"'{name}' needs {size} bytes of EEVEE uniforms, more than the {UNIFORM_BLOCK_LIMIT} EEVEE allows: "
                f"EEVEE will draw it magenta (Cycles is unaffected); bake with fewer SGs"
                for name, size in uniform_bytes.items() if size > UNIFORM_BLOCK_LIMIT]
    seconds = time.perf_counter() - start
    sg_counts = {m.name: evaluated_count(m.sg_count) for o in plan.baked_objects for m in o.materials if m.glossy}
    most = groups.get(layout.sg_count, groups.get(None))
    info = {"materials": sorted(baked_materials), "node_group": most.name if most else None,
            "nodes": flattened_node_count(most) if most else 0,  # nested groups expanded, as renderers compile it
            "node_groups": {g.name: flattened_node_count(g) for g in groups.values()},
            "sg_counts": sg_counts, "irradiance_only": plan.irradiance_only_materials,
            "sg_evaluations_saved": None if layout.sh_count else
            round(1 - sum(sg_counts.values()) / max(layout.sg_count * len(sg_counts), 1), 3),
            "encoder": "sh_l2" if layout.sh_count else "sg",
            "image": image.name, "image_packed": bool(image.packed_file), "layout": layout.to_dict(),
            "irradiance_image": detail_image.name if detail_image else None,
            "eevee_uniform_bytes": uniform_bytes, "eevee_uniform_limit": UNIFORM_BLOCK_LIMIT, "warnings": warnings,
            **measured}
    update_report(out_dir, plan.stage_hash("capture"), timings_s={"apply": seconds}, apply=info)
    if progress is not None:
        progress(1.0, f"{len(baked_materials)} materials baked")
    return info


def _remove_unused_groups():
    """Remove the bake's node groups nothing uses; a nested group ('<group> / ...') is freed by removing its parent."""
    while True:
        unused = [g for g in bpy.data.node_groups if is_bake_group(g) and g.users == 0]
        if not unused:
            return
        for group in unused:
            bpy.data.node_groups.remove(group)


def baked_slots(scene):
    """(material slot, original material) of every slot the scene's bake switched and that still exists."""
    record = json.loads(scene.get(BAKE_RECORD_KEY, "{}"))
    for object_name, slots in record.items():
        obj = scene.objects.get(object_name) or bpy.data.objects.get(object_name)  # an instanced object may be in
        for index, original_name in slots.items():  # a collection no scene links
            original = bpy.data.materials.get(original_name)
            if obj is not None and original is not None and int(index) < len(obj.material_slots):
                yield obj.material_slots[int(index)], original


def remove_bake(scene) -> int:
    """Restore the original materials of every slot the bake changed and delete what the bake made.
    Returns the number of slots restored."""
    record = json.loads(scene.get(BAKE_RECORD_KEY, "{}"))
    originals = {name for slots in record.values() for name in slots.values()}  # incl. of deleted objects
    restored = 0
    for slot, original in list(baked_slots(scene)):
        slot.material = original
        restored += 1
    for material in [m for m in bpy.data.materials if COPY_KEY in m and m.users == 0]:
        bpy.data.materials.remove(material)
    remove_unused_group_copies()
    for name in originals:
        original = bpy.data.materials.get(name)
        if original is not None and original.get(FAKE_USER_KEY):
            original.use_fake_user = False
            del original[FAKE_USER_KEY]
    if BAKE_RECORD_KEY in scene:
        del scene[BAKE_RECORD_KEY]
    still_baked = any(BAKE_RECORD_KEY in s for s in bpy.data.scenes)
    if not still_baked:
        _remove_unused_groups()
        for name in (IMAGE_NAME, DETAIL_IMAGE_NAME):
            image = bpy.data.images.get(name)
            if image is not None and image.users == 0:
                bpy.data.images.remove(image)
    remove_lightmap_uvs(scene)
    return restored
