"""Capture stage: lightmap UVs (xatlas) and per-texel maps of every baked object (DESIGN section 2).

What it changes in the scene (``remove_lightmap_uvs`` takes all of it away again):
- a plain mesh (no modifiers) gets one UV layer ``SGLightmap`` on its mesh data, made by xatlas, never one of the
  user's layers; linked duplicates share it;
- an object with modifiers, a text or a curve, or a mesh whose quads xatlas would split across charts, gets the
  same layer from a last, removable ``SG Lightmap UV`` modifier (lightmap_modifier), so its stack stays live;
- every baked object gets its tile of the shared atlas as two custom properties (sglf_lightmap_offset and
  sglf_lightmap_scale: atlas_uv = offset + uv * scale), so duplicates get texels of their own;
- a metaball or NURBS surface (no modifiers) is baked through a mesh stand-in that follows its surface
  (stand_ins); the original is invisible to rays and probes and drawn as wire meanwhile; with the setting
  instance_copies, particle, vertex, face, nested and node-made instances are replaced by object copies
  (stand_ins), which bake as objects;
- every instance gets a tile of its own too: a collection's objects are packed once into a block of tiles that
  each instancing empty gets a copy of (``sglf_lightmap_block`` on the empty: where its block is); a geometry-node
  instance's tile is a pair of instance attributes that the SG Lightmap UV modifier on its instancer writes.
Geometry is captured as a render evaluates it (modifiers shown for rendering, subdivision at render levels).

What it writes to the bake directory:
  texels.exr    float32 atlas maps (channels in TEXEL_CHANNELS), row 0 = top = v near 1
  texels.json   atlas size, object and material tables, counts, the plan hash
  capture_position.png / capture_normal.png / capture_validity.png   pictures for the report

Normals: both are stored. ``Ng`` (geometric, from the triangle, outward even under negative scale)
decides the hemisphere the light field covers and the ray-origin offset: light cannot arrive from
below the real surface, and rays leaving along a smoothed normal would start inside the mesh. ``N``
(interpolated shading normal) is what the material shades with, so apply and evaluate use it.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector
from mathutils.bvhtree import BVHTree

from ..bake_directory.bake_plan import (IRRADIANCE_DETAIL_SAMPLES, BakeCancelled, BakeInputError,
                                        write_json_atomic)
from ..bake_directory.bake_report import update_report
from ..bake_directory.exr_io import ExrError, read_exr_metadata, write_exr
from ..bake_directory.texel_maps import (CAPTURE_PICTURES, CHANNEL, FLAG_BURIED, FLAG_CENTRE_INSIDE, FLAG_COVERED,
                                  FLAG_GUTTER, FLAG_PUSHED_OUT, TEXEL_CHANNELS, TEXELS_FILE, TEXELS_JSON,
                                  save_capture_pictures)
from ..bake_directory.texel_raster import centre_overlap_count, dilate, rasterize, shelf_pack, signed_areas
from .scene_analysis import (active_scene, bake_targets, instance_targets, instances_by_instancer, loop_triangle_arrays,
                             principled_surface, render_evaluation, transform_points, triangle_areas, unbaked)
from . import lightmap_modifier
from .lightmap_modifier import user_modifiers
from .irradiance_detail import DETAIL_FILE, bake_irradiance_detail, filled
from .stand_ins import (STAND_IN_TYPES, copied, copy_instances, ensure_stand_in, has_stand_in, is_stand_in,
                        remove_stand_ins)
from .surface_probe import measure_surfaces

LIGHTMAP_LAYER = "SGLightmap"
OWNER_KEY = "sglf_lightmap_layer"  # on a mesh: the name of the UV layer SG Lightfield made there
# On an object: its tile in the atlas as atlas_uv = offset + lightmap_uv * scale (two 3-float properties,
# so a shader's Object Attribute node reads each as a plain vector).
OFFSET_KEY, SCALE_KEY = "sglf_lightmap_offset", "sglf_lightmap_scale"
# On a collection-instancing empty: where its copy of the collection's block of tiles is, from the first block.
BLOCK_KEY = "sglf_lightmap_block"
TILE_KEYS = (OFFSET_KEY, SCALE_KEY, BLOCK_KEY)
TEXEL_SCALE_KEY = "sglf_texel_scale"  # on an object: multiplier of the scene's texel density
MAX_UV_LAYERS = 8  # Blender's limit per mesh
UV_PADDING = 2  # texels between charts (bilinear filtering needs >= 1 after instance scaling)
MAX_ATLAS_SIDE = 16384
MAX_OVERLAP_FRACTION = 0.002  # of a user-chosen layer's covered texel centres
PUSH_OUT_DIRECTIONS = 8  # rays in the tangent plane per texel (Rakhteenko)
BURIED_DIRECTIONS = 5  # the normal and four tilted by 45 degrees; all must hit a back face ...
BURIED_REACH_TEXELS = 8  # ... within this many texels (or 1% of the scene's size): a closed shell
# around the whole scene (an emissive sky sphere, a room modelled as one outward-facing box) seen from
# inside must not bury every texel


@dataclass
class ObjectTile:
    id: int
    name: str
    mesh: str
    uv_layer: str
    rect: tuple  # (u0, v0, su, sv) in atlas UV
    pixel_rect: tuple  # (x, y, w, h) in atlas pixels, y from the top
    texels: int = 0
    pushed_out: int = 0
    buried: int = 0


@dataclass
class CaptureResult:
    atlas_width: int
    atlas_height: int
    texels: int
    coverage_percent: float
    pushed_out_texels: int
    buried_texels: int
    objects: list
    materials: list
    warnings: list = field(default_factory=list)
    surface_probe: dict = field(default_factory=dict)  # what measure_surfaces baked: objects, materials, seconds
    layout_hash: str = ""  # where every tile and texel is (layout_hash): the irradiance detail image records it
    seconds: float = 0.0


def _noop_progress(fraction, message):
    pass


def _texel_scale(obj) -> float:
    """The object's texel-density multiplier (a stand-in's is its source's, where the user set it)."""
    obj = obj.parent if is_stand_in(obj) and obj.parent is not None else obj
    value = obj.get(TEXEL_SCALE_KEY, 1.0)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise BakeInputError(f"'{obj.name}': custom property {TEXEL_SCALE_KEY} must be a number, got {value!r}")
    if not (1e-3 <= value <= 1e3):
        raise BakeInputError(f"'{obj.name}': {TEXEL_SCALE_KEY} {value} is outside 0.001..1000")
    return value


def _xatlas_layout(mesh, loops, verts, coords, texels_per_unit: float):
    """Chart and pack one mesh (object space, its loop_triangle_arrays) with xatlas; returns loop UVs (L, 2) in
    [0, 1], the layout size in texels and the count of triangles whose loops got conflicting UVs."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(coords.astype(np.float32), verts.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.texels_per_unit = float(texels_per_unit)
    pack.padding = UV_PADDING
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    _, indices, uvs = atlas[0]
    loop_uv = np.zeros((len(mesh.loops), 2), np.float64)
    loop_uv[loops.ravel()] = uvs[indices.ravel()]
    # An n-gon whose triangles xatlas put into different charts cannot have one UV per loop.
    conflicts = int(np.count_nonzero(np.abs(loop_uv[loops] - uvs[indices]).max(axis=(1, 2)) > 1e-6))
    return loop_uv, (int(atlas.width), int(atlas.height)), conflicts


def _layer_uvs(mesh, name):
    layer = mesh.uv_layers.get(name)
    uv = np.empty(len(mesh.loops) * 2, np.float64)
    layer.uv.foreach_get("vector", uv)
    return uv.reshape(-1, 2)


def ensure_lightmap_layer(mesh, loop_uv) -> None:
    """Write `loop_uv` into the mesh's SGLightmap layer, creating it; the user's layers and active flags stay."""
    layer = mesh.uv_layers.get(LIGHTMAP_LAYER)
    if layer is not None and mesh.get(OWNER_KEY) != LIGHTMAP_LAYER:
        raise BakeInputError(f"mesh '{mesh.name}' already has a UV layer named {LIGHTMAP_LAYER} that SG Lightfield "
                             "did not make; rename it, or choose it as the lightmap layer")
    if layer is None:
        if len(mesh.uv_layers) >= MAX_UV_LAYERS:
            raise BakeInputError(f"mesh '{mesh.name}' has {MAX_UV_LAYERS} UV layers, Blender's maximum; remove one "
                                 "or choose an existing valid layer as the lightmap layer")
        active_index = mesh.uv_layers.active_index
        render_layer = next((uv.name for uv in mesh.uv_layers if uv.active_render), None)
        layer = mesh.uv_layers.new(name=LIGHTMAP_LAYER, do_init=False)
        if render_layer is not None:
            mesh.uv_layers.active_index = active_index
            mesh.uv_layers[render_layer].active_render = True
        mesh[OWNER_KEY] = LIGHTMAP_LAYER
    layer.uv.foreach_set("vector", np.asarray(loop_uv, np.float32).ravel())
    mesh.update()


def lightmap_owners(scene) -> list:
    """Every object a capture of `scene` may have changed: the scene's objects and the objects its instances show
    (which may live in a collection no scene links)."""
    with active_scene(scene) as depsgraph:
        instanced = {i.object.original for i in depsgraph.object_instances if i.is_instance}
    return list(dict.fromkeys([*scene.objects, *sorted(instanced, key=lambda o: o.name)]))


def remove_lightmap_uvs(scene) -> int:
    """Undo capture's changes: drop the SGLightmap layers, SG Lightmap UV modifiers (with their carriers), tile
    rectangles, mesh stand-ins and instance copies it added. Returns the count of layers, modifiers, stand-ins and
    copies removed."""
    removed = 0
    for obj in lightmap_owners(scene):
        for key in TILE_KEYS:
            if key in obj:
                del obj[key]
        removed += lightmap_modifier.detach(obj)
        mesh = obj.data if obj.type == "MESH" else None
        if mesh is not None and mesh.get(OWNER_KEY) == LIGHTMAP_LAYER:
            layer = mesh.uv_layers.get(LIGHTMAP_LAYER)
            if layer is not None:
                mesh.uv_layers.remove(layer)
                removed += 1
            del mesh[OWNER_KEY]
    return removed + remove_stand_ins(scene)


def _validate_user_layer(obj, loops, layer_name, world_area, density):
    """A user-chosen lightmap layer must exist, stay inside [0, 1] and not overlap; returns its tile side.
    `loops` are the mesh's loop-triangle loops (loop_triangle_arrays)."""
    mesh = obj.data
    if mesh.uv_layers.get(layer_name) is None:
        raise BakeInputError(f"'{obj.name}': has no UV layer '{layer_name}' to use as the lightmap layer "
                             f"(it has: {', '.join(mesh.uv_layers.keys()) or 'none'})")
    uv = _layer_uvs(mesh, layer_name)[loops]
    if not np.all(np.isfinite(uv)) or uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        raise BakeInputError(f"'{obj.name}': UV layer '{layer_name}' leaves the [0, 1] square "
                             f"(range {uv.min():.3f}..{uv.max():.3f}); a lightmap layout must stay inside it")
    uv_area = float(np.abs(signed_areas(uv)).sum())
    if uv_area <= 1e-12:
        raise BakeInputError(f"'{obj.name}': UV layer '{layer_name}' has no area")
    side = int(np.clip(math.ceil(math.sqrt(world_area * density**2 / uv_area)), 4, MAX_ATLAS_SIDE))
    check = max(side, 64)
    px = np.stack([uv[..., 0] * check, (1 - uv[..., 1]) * check], axis=-1)
    count = centre_overlap_count(px, check, check)
    covered = np.count_nonzero(count)
    overlap = np.count_nonzero(count > 1) / max(covered, 1)
    if overlap > MAX_OVERLAP_FRACTION:
        raise BakeInputError(f"'{obj.name}': UV layer '{layer_name}' overlaps itself ({100 * overlap:.1f}% of its "
                             "texels are claimed twice); a lightmap layer needs a unique layout; leave the "
                             "lightmap layer empty to let xatlas make one")
    return side


def _material_table(objects, plan):
    names, table = [], []
    plans = {mp.name: mp for op in plan.objects for mp in op.materials}
    for obj in objects:
        for slot in obj.material_slots or [None]:
            material = unbaked(slot.material) if slot is not None else None
            name = material.name if material is not None else "(no material)"
            if name in names:
                continue
            names.append(name)
            surface = principled_surface(material)
            mp = plans.get(name)
            if mp is not None:
                surface["roughness"], surface["metallic"], surface["textured"] = mp.roughness, mp.metallic, mp.textured
            table.append({"id": len(names), "name": name, **surface})
    return table


def _object_material_ids(obj, materials):
    by_name = {m["name"]: m["id"] for m in materials}
    slots = [unbaked(s.material).name if s.material is not None else "(no material)" for s in obj.material_slots]
    return np.array([by_name[n] for n in slots] or [by_name["(no material)"]], np.int64)


def _needs_modifier(obj, lightmap_uv_layer) -> bool:
    """Objects whose rendered surface is not their mesh data take the lightmap UV from the modifier."""
    if obj.type != "MESH":
        return True
    return bool(user_modifiers(obj)) and not lightmap_uv_layer


def _layout_overlap(uv_triangles, width, height) -> float:
    """Share of a layout's covered texel centres (at width x height texels) that two triangles claim."""
    px = np.stack([uv_triangles[..., 0] * width, (1 - uv_triangles[..., 1]) * height], axis=-1)
    claimed = centre_overlap_count(px, width, height)
    return np.count_nonzero(claimed > 1) / max(np.count_nonzero(claimed), 1)


def _tile_sizes(uv_triangles, width, height, scales, name, warnings):
    """Tile sizes of the instances sharing one layout: `scales` of the reference layout (width x height texels),
    each grown until its charts keep texels of their own (small objects, small duplicates of a big one)."""
    sizes = []
    for scale in scales:
        while True:
            w, h = max(1, math.ceil(width * scale)), max(1, math.ceil(height * scale))
            if scale >= 1.0 or _layout_overlap(uv_triangles, w, h) <= MAX_OVERLAP_FRACTION:
                break
            scale = min(1.0, scale * 1.25)
        sizes.append((w, h))
    overlap = _layout_overlap(uv_triangles, width, height)
    if overlap > MAX_OVERLAP_FRACTION:
        warnings.append(f"'{name}': {100 * overlap:.1f}% of its lightmap texels are shared by two charts at "
                        f"{width} x {height} texels; raise its {TEXEL_SCALE_KEY} for a cleaner bake")
    return sizes


def _densities(targets, coords, verts, local_area, settings):
    """Texels per object-space unit of each target (world area over local area, times its object's texel scale)."""
    densities = []
    for target in targets:
        world_area = float(triangle_areas(transform_points(target.matrix, coords), verts).sum())
        densities.append(settings.texel_density * _texel_scale(target.obj) * math.sqrt(world_area / local_area))
    return densities


def _check_size(name, local_area, reference, settings):
    if local_area * reference**2 > MAX_ATLAS_SIDE**2:
        raise BakeInputError(f"'{name}' would need {local_area * reference**2:.3g} texels at "
                             f"{settings.texel_density:g} texels/m; lower the texel density or its {TEXEL_SCALE_KEY}")


def _plan_layout(targets, settings, lightmap_uv_layer, warnings):
    """Lightmap UVs and one atlas tile per target (an object, or one instance of an object); returns tiles. Plain
    meshes get the UV layer SGLightmap on their mesh data (linked duplicates and instances share it); everything else
    gets it from the SG Lightmap UV modifier. Every instance of an object shares the object's layout."""
    owners = list(dict.fromkeys(t.obj for t in targets))
    uses = {obj: [t for t in targets if t.obj == obj] for obj in owners}
    modified = [obj for obj in owners if _needs_modifier(obj, lightmap_uv_layer)]
    groups: dict = {}
    for obj in owners:
        if obj not in modified:
            groups.setdefault(obj.data.name, []).append(obj)
    layouts = {}  # target name -> (layer, (width, height))
    for mesh_name, objects in groups.items():
        mesh = objects[0].data
        users = [t for obj in objects for t in uses[obj]]
        loops, verts, _, coords = loop_triangle_arrays(mesh)
        local_area = float(triangle_areas(coords, verts).sum())
        if local_area <= 0:
            raise BakeInputError(f"'{users[0].name}': mesh '{mesh_name}' has no faces with area")
        densities = _densities(users, coords, verts, local_area, settings)
        if lightmap_uv_layer:
            for target, d in zip(users, densities):
                side = _validate_user_layer(target.obj, loops, lightmap_uv_layer,
                                            local_area * (d / settings.texel_density) ** 2, settings.texel_density)
                layouts[target.name] = (lightmap_uv_layer, (side, side))
            continue
        reference = max(densities)
        _check_size(users[0].name, local_area, reference, settings)
        loop_uv, (width, height), conflicts = _xatlas_layout(mesh, loops, verts, coords, reference)
        if conflicts:  # a quad or n-gon split across charts: only a triangulated copy can hold one UV per corner
            modified.extend(objects)
            continue
        for obj in objects:
            lightmap_modifier.detach(obj)  # an earlier bake's, now that the object renders its mesh data
        ensure_lightmap_layer(mesh, loop_uv)
        sizes = _tile_sizes(loop_uv[loops], width, height, [d / reference for d in densities], users[0].name, warnings)
        for target, size in zip(users, sizes):
            layouts[target.name] = (LIGHTMAP_LAYER, size)
    if modified:
        for obj in modified:
            lightmap_modifier.attach(obj)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        for obj in modified:
            users = uses[obj]
            evaluated = obj.evaluated_get(depsgraph)
            mesh = evaluated.to_mesh()
            try:
                loops, verts, _, coords = loop_triangle_arrays(mesh)
                local_area = float(triangle_areas(coords, verts).sum()) if len(verts) else 0.0
                if local_area <= 0:
                    raise BakeInputError(f"'{obj.name}': its evaluated {obj.type.lower()} has no faces with area")
                densities = _densities(users, coords, verts, local_area, settings)
                reference = max(densities)
                _check_size(obj.name, local_area, reference, settings)
                loop_uv, (width, height), _ = _xatlas_layout(mesh, loops, verts, coords, reference)
                lightmap_modifier.set_carrier(obj, mesh, loop_uv)
            finally:
                evaluated.to_mesh_clear()
            sizes = _tile_sizes(loop_uv[loops], width, height, [d / reference for d in densities], obj.name, warnings)
            for target, size in zip(users, sizes):
                layouts[target.name] = (LIGHTMAP_LAYER, size)
        lightmap_modifier.remove_orphans()
    pixel_rects, atlas_w, atlas_h, blocks = _pack(targets, {name: size for name, (_, size) in layouts.items()})
    tiles = []
    for i, target in enumerate(targets):
        x, y, w, h = pixel_rects[target.name]
        rect = (x / atlas_w, (atlas_h - y - h) / atlas_h, w / atlas_w, h / atlas_h)
        tiles.append(ObjectTile(i + 1, target.name, target.obj.data.name, layouts[target.name][0], rect, (x, y, w, h)))
    return tiles, atlas_w, atlas_h, blocks


def _pack(targets, sizes):
    """Atlas places of every target's tile. The members of a collection instance are packed once into a block, and
    each instancing empty gets a copy of that block, so one tile per member, relative to its block, serves every
    instance (the member's own properties hold it; the empty holds where its block is). The first block serves the
    members that the scene also shows directly. Returns ({target name: (x, y, w, h)}, atlas width, height,
    {empty name: (dx, dy) of its block from the first block, in texels})."""
    collections: dict = {}  # collection -> {"members": {object: tile size}, "empties": [empty]}
    for target in targets:
        if target.instancer is not None and target.instancer.type == "EMPTY":
            group = collections.setdefault(target.instancer.instance_collection, {"members": {}, "empties": []})
            w, h = sizes[target.name]
            old = group["members"].get(target.obj, (0, 0))
            group["members"][target.obj] = (max(old[0], w), max(old[1], h))
            if target.instancer not in group["empties"]:
                group["empties"].append(target.instancer)
    member_of = {obj: group for group in collections.values() for obj in group["members"]}
    for group in collections.values():
        members = list(group["members"])
        positions, bw, bh = shelf_pack([group["members"][m] for m in members], border=1, max_side=MAX_ATLAS_SIDE)
        group["relative"] = dict(zip(members, positions))
        group["size"] = (bw, bh)
    # a member shown directly lives in the first block
    items = [t.name for t in targets if t.obj not in member_of or t.instancer is not None and t.instancer.type != "EMPTY"]
    block_items = [(group_key, index) for group_key, group in enumerate(collections.values())
                   for index in range(len(group["empties"]))]
    groups = list(collections.values())
    pack_sizes = [sizes[name] for name in items] + [groups[g]["size"] for g, _ in block_items]
    try:
        positions, atlas_w, atlas_h = shelf_pack(pack_sizes, border=1, max_side=MAX_ATLAS_SIDE)
    except ValueError as exc:
        raise BakeInputError(f"the lightmap atlas is too large ({exc}); lower the texel density") from exc
    rects = {name: (*positions[k], *sizes[name]) for k, name in enumerate(items)}
    block_at, blocks = {}, {}
    for (g, index), (x, y) in zip(block_items, positions[len(items):]):
        empty = groups[g]["empties"][index]
        block_at[empty.name] = (x, y)
        first = block_at.setdefault(("first", g), (x, y))
        blocks[empty.name] = (x - first[0], y - first[1])
    group_index = {id(group): g for g, group in enumerate(groups)}
    for target in targets:
        group = member_of.get(target.obj)
        if target.name in rects or group is None:
            continue
        g = group_index[id(group)]
        bx, by = block_at[target.instancer.name] if target.instancer is not None else block_at[("first", g)]
        rx, ry = group["relative"][target.obj]
        rects[target.name] = (bx + rx, by + ry, *group["members"][target.obj])
    return rects, atlas_w, atlas_h, blocks


def _store_tiles(targets, tiles, blocks, atlas_w, atlas_h) -> None:
    """Each target's atlas tile where its baked material finds it (Instancer attributes, which fall back to the
    object's own): an object's custom properties; a collection member's properties (its tile in its collection's
    first block) plus the empty's block offset; a geometry-node instance's instance attributes, written by the SG
    Lightmap UV modifier on its instancer."""
    by_instancer: dict = {}
    for target, tile in zip(targets, tiles):
        u0, v0, su, sv = tile.rect
        offset, scale = [u0, v0, 0.0], [su, sv, 1.0]
        if target.instancer is None or target.instancer.type == "EMPTY":
            if target.instancer is not None:  # the member's tile in the first block
                dx, dy = blocks[target.instancer.name]
                offset = [u0 - dx / atlas_w, v0 + dy / atlas_h, 0.0]
                target.instancer[BLOCK_KEY] = [dx / atlas_w, -dy / atlas_h, 0.0]
            target.obj[OFFSET_KEY], target.obj[SCALE_KEY] = offset, scale
        else:
            local = target.instancer.matrix_world.inverted() @ target.matrix.translation
            by_instancer.setdefault(target.instancer, []).append((tuple(local), offset, scale))
    for instancer, rows in by_instancer.items():
        lightmap_modifier.attach(instancer)
        lightmap_modifier.set_instance_tiles(instancer, *zip(*rows))


def scene_bvh(scene, depsgraph):
    """World-space BVH of everything that renders a surface (meshes, curves, text, instances; winding made outward
    for negative scale) and the length of the scene's bounding-box diagonal."""
    vertices, polygons, offset = [], [], 0
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type not in ("MESH", "CURVE", "FONT", "SURFACE", "META") or obj.original.hide_render \
                or has_stand_in(obj.original):  # its stand-in, at the same place, is in the BVH
            continue
        mesh = obj.to_mesh()
        try:
            if mesh is None or len(mesh.polygons) == 0:
                continue
            _, verts, _, coords = loop_triangle_arrays(mesh)
            matrix = instance.matrix_world
            world = transform_points(matrix, coords)
            if np.linalg.det(np.array(matrix)[:3, :3]) < 0:
                verts = verts[:, ::-1]
            vertices.append(world)
            polygons.append(verts + offset)
            offset += len(world)
        finally:
            obj.to_mesh_clear()
    if not vertices:
        return None, 0.0
    points = np.concatenate(vertices)
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return BVHTree.FromPolygons(points.tolist(), np.concatenate(polygons).tolist(), all_triangles=True), size


def _tangent_frame(n):
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(helper, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def push_out(bvh, position, normal, texel_size, offset, scene_size=0.0):
    """Rakhteenko's fix for texels whose sample lies inside other geometry, and detection of buried ones.

    Rays in the tangent plane as long as the texel footprint's half diagonal: the nearest back-face hit
    means the sample is inside something; it moves just outside that face. Afterwards a sample whose
    normal ray and four rays tilted 45 degrees all hit back faces nearby is enclosed (buried): nothing
    can see it.
    Returns new positions and boolean masks (pushed, buried)."""
    position = position.copy()
    pushed = np.zeros(len(position), bool)
    buried = np.zeros(len(position), bool)
    if bvh is None or len(position) == 0:
        return position, pushed, buried
    t, b = _tangent_frame(normal)
    angles = 2 * np.pi * np.arange(PUSH_OUT_DIRECTIONS) / PUSH_OUT_DIRECTIONS
    reach = texel_size * math.sqrt(0.5)
    for i in range(len(position)):
        lifted = position[i] + normal[i] * offset[i]
        best = None
        for a in angles:
            direction = math.cos(a) * t[i] + math.sin(a) * b[i]
            # Start one offset behind the sample so a surface passing exactly through it is seen from
            # its far side too: a sample lying on a wall's base is then moved to the wall's front.
            origin = Vector(lifted - direction * offset[i])
            direction = Vector(direction)
            hit, hit_normal, _, distance = bvh.ray_cast(origin, direction, float(reach[i] + offset[i]))
            if hit is not None and hit_normal.dot(direction) > 0 and (best is None or distance < best[0]):
                best = (distance, hit, hit_normal)
        if best is not None:
            position[i] = np.array(best[1] + best[2] * float(offset[i])) - normal[i] * offset[i]
            pushed[i] = True
        origin = Vector(position[i] + normal[i] * offset[i])
        enclosed = True
        for k in range(BURIED_DIRECTIONS):
            if k == 0:
                direction = normal[i]
            else:
                a = 2 * np.pi * (k - 1) / (BURIED_DIRECTIONS - 1)
                direction = (normal[i] + math.cos(a) * t[i] + math.sin(a) * b[i]) / math.sqrt(2)
            direction = Vector(direction)
            reach_buried = max(BURIED_REACH_TEXELS * float(texel_size[i]), 0.01 * scene_size)
            hit, hit_normal, _, _ = bvh.ray_cast(origin, direction, reach_buried)
            if hit is None or hit_normal.dot(direction) <= 0:
                enclosed = False
                break
        buried[i] = enclosed
    return position, pushed, buried


def ray_offset(position, texel_size):
    """Scene-scale-aware origin offset: a thousandth of the texel, never below float32 resolution."""
    magnitude = np.abs(position).max(axis=-1)
    return np.maximum(1e-3 * texel_size, 64 * np.finfo(np.float32).eps * np.maximum(magnitude, 1.0))


def _rasterize_object(target, tile, depsgraph, material_ids, atlas_w, atlas_h, maps):
    obj = target.obj
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        if mesh.uv_layers.get(tile.uv_layer) is None:
            raise BakeInputError(f"'{obj.name}': a modifier removed the lightmap UV layer '{tile.uv_layer}'")
        loops, verts, mat_index, coords = loop_triangle_arrays(mesh)
        uv = _layer_uvs(mesh, tile.uv_layer)[loops]
        normals = np.empty(len(mesh.loops) * 3, np.float64)
        mesh.corner_normals.foreach_get("vector", normals)
        corner_normals = normals.reshape(-1, 3)[loops]
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array(target.matrix, dtype=np.float64)
    world = transform_points(matrix, coords)[verts]  # (T, 3, 3)
    flip = -1.0 if np.linalg.det(matrix[:3, :3]) < 0 else 1.0
    face = flip * np.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
    world_area = 0.5 * np.linalg.norm(face, axis=1)
    x, y, w, h = tile.pixel_rect
    px = np.stack([x + uv[..., 0] * w, y + (1 - uv[..., 1]) * h], axis=-1)
    px_area = np.abs(signed_areas(px))
    usable = (world_area > 1e-20) & (px_area > 1e-12)
    degenerate = np.where(~usable[:, None, None], np.nan, 0.0)
    claimed = centre_overlap_count(px[usable], atlas_w, atlas_h)
    overlap = np.count_nonzero(claimed > 1) / max(np.count_nonzero(claimed), 1)
    if overlap > MAX_OVERLAP_FRACTION and tile.uv_layer != LIGHTMAP_LAYER:  # a user-chosen layer
        modifiers = ", ".join(m.name for m in user_modifiers(obj) if m.show_render)
        raise BakeInputError(f"'{obj.name}': its UV layer '{tile.uv_layer}' overlaps itself "
                             + (f"after its modifiers ({modifiers}) " if modifiers else "")
                             + f"({100 * overlap:.1f}% of its texels are claimed twice); a lightmap layer needs a "
                             "unique layout; leave the lightmap layer empty to let SG Lightfield lay one out")
    raster = rasterize(px + degenerate, atlas_w, atlas_h)  # NaN corners: skipped by the rasteriser
    rows, cols = np.nonzero(raster.covered)
    inside_tile = (cols >= x) & (cols < x + w) & (rows >= y) & (rows < y + h)
    rows, cols = rows[inside_tile], cols[inside_tile]
    if len(rows) == 0:
        return 0
    tri = raster.triangle[rows, cols]
    bary = raster.barycentric[rows, cols]
    position = np.einsum("nk,nkc->nc", bary, world[tri])
    geometric = face[tri] / np.maximum(np.linalg.norm(face[tri], axis=1, keepdims=True), 1e-300)
    normal_matrix = np.linalg.inv(matrix[:3, :3]).T
    shading = np.einsum("nk,nkc->nc", bary, corner_normals[tri]) @ normal_matrix.T
    length = np.linalg.norm(shading, axis=1, keepdims=True)
    shading = np.where(length > 1e-12, shading / np.maximum(length, 1e-300), geometric)
    texel_size = np.sqrt(world_area[tri] / px_area[tri])
    flags = FLAG_COVERED | np.where(raster.centre_inside[rows, cols], FLAG_CENTRE_INSIDE, 0)
    maps["P"][rows, cols] = position
    maps["Ng"][rows, cols] = geometric
    maps["N"][rows, cols] = shading
    maps["object_id"][rows, cols] = tile.id
    maps["material_id"][rows, cols] = material_ids[np.clip(mat_index[tri], 0, len(material_ids) - 1)]
    maps["texel_size"][rows, cols] = texel_size
    maps["flags"][rows, cols] = flags
    return len(rows)


def _add_stand_ins(scene, plan) -> None:
    """Make the mesh stand-ins and instance copies the plan bakes through (an earlier capture's are kept)."""
    for object_plan in plan.baked_objects:
        obj = scene.objects.get(object_plan.name)
        if not object_plan.instancer and obj is not None and obj.type in STAND_IN_TYPES:
            ensure_stand_in(obj)
    names = dict.fromkeys(o.instancer for o in plan.baked_objects if o.instancer)
    instancers = [scene.objects[n] for n in names if n in scene.objects and not copied(scene.objects[n])]
    if not plan.settings.instance_copies or not instancers:
        return
    with active_scene(scene), render_evaluation(instancers):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        found = instances_by_instancer(depsgraph, keep_meshes={o.name for o in instancers})
    for instancer in instancers:
        instanced = found.get(instancer.name)
        if instanced is not None and instanced.copyable:
            copy_instances(scene, instancer, instanced.how, instanced.nested, instanced.entries,
                           instance_targets(instancer.name, instanced), instanced.meshes)
        elif instanced is not None:
            for mesh in instanced.meshes.values():
                bpy.data.meshes.remove(mesh)


def capture(scene, plan, out_dir, *, lightmap_uv_layer: str = "", progress=_noop_progress,
            should_cancel=lambda: False) -> CaptureResult:
    """Run the capture stage for `plan` on `scene`, writing texel maps into `out_dir`."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    warnings: list[str] = []
    progress(0.0, "lightmap UVs")
    _add_stand_ins(scene, plan)
    with active_scene(scene) as depsgraph:
        depsgraph.update()
        targets = bake_targets(scene, plan.baked_objects, depsgraph)
    objects = list(dict.fromkeys(t.obj for t in targets))
    with active_scene(scene), render_evaluation(objects):
        tiles, atlas_w, atlas_h, blocks = _plan_layout(targets, plan.settings, lightmap_uv_layer, warnings)
        _store_tiles(targets, tiles, blocks, atlas_w, atlas_h)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        materials = _material_table(objects, plan)
        maps = {
            "P": np.zeros((atlas_h, atlas_w, 3)), "Ng": np.zeros((atlas_h, atlas_w, 3)),
            "N": np.zeros((atlas_h, atlas_w, 3)), "object_id": np.zeros((atlas_h, atlas_w), np.int64),
            "material_id": np.zeros((atlas_h, atlas_w), np.int64), "texel_size": np.zeros((atlas_h, atlas_w)),
            "flags": np.zeros((atlas_h, atlas_w), np.int64),
        }
        for k, (target, tile) in enumerate(zip(targets, tiles)):
            if should_cancel():
                raise BakeCancelled("capture cancelled")
            progress(0.1 + 0.4 * k / len(targets), f"texels of '{target.name}'")
            tile.texels = _rasterize_object(target, tile, depsgraph, _object_material_ids(target.obj, materials),
                                            atlas_w, atlas_h, maps)
            if tile.texels == 0:
                warnings.append(f"'{target.name}': no texel at {plan.settings.texel_density:g} texels/m")
        covered = (maps["flags"] & FLAG_COVERED) > 0
        if not np.any(covered):
            raise BakeInputError(f"no texel was produced at {plan.settings.texel_density:g} texels/m; "
                                 "raise the texel density")
        textured = {m.name for o in plan.objects for m in o.materials if m.baked and m.textured}
        progress(0.45, "material values of textured surfaces")
        maps["surface"], measured, probe_info = measure_surfaces(
            scene, targets, tiles, (atlas_h, atlas_w), maps["object_id"], lambda material: material.name in textured)
        maps["measured"] = measured & covered
        layout = layout_hash(tiles, maps)
        detail = _irradiance_detail(scene, plan, out_dir, targets, tiles, (atlas_h, atlas_w), layout, progress,
                                    should_cancel)
        progress(0.5, "push-out of texels inside geometry")
        bvh, scene_size = scene_bvh(scene, bpy.context.evaluated_depsgraph_get())  # the probes changed the scene
    rows, cols = np.nonzero(covered)
    offset = ray_offset(maps["P"][rows, cols], maps["texel_size"][rows, cols])
    if should_cancel():
        raise BakeCancelled("capture cancelled")
    position, pushed, buried = push_out(bvh, maps["P"][rows, cols], maps["Ng"][rows, cols],
                                        maps["texel_size"][rows, cols], offset, scene_size)
    maps["P"][rows, cols] = position
    maps["flags"][rows, cols] |= np.where(pushed, FLAG_PUSHED_OUT, 0) | np.where(buried, FLAG_BURIED, 0)
    valid = np.zeros((atlas_h, atlas_w), bool)
    valid[rows[~buried], cols[~buried]] = True
    ray_offsets = np.zeros((atlas_h, atlas_w))
    ray_offsets[rows, cols] = offset
    for tile in tiles:
        in_tile = maps["object_id"][rows, cols] == tile.id
        tile.pushed_out, tile.buried = int(np.count_nonzero(pushed & in_tile)), int(np.count_nonzero(buried & in_tile))
    progress(0.8, "gutters and files")
    filled, reached = dilate({**maps, "ray_offset": ray_offsets}, covered, UV_PADDING + 1)
    gutter = reached & ~covered
    filled["flags"][gutter] = FLAG_GUTTER
    atlas = _texel_atlas(filled, valid, materials)
    _measured_statistics(materials, atlas, probe_info)
    result = CaptureResult(atlas_w, atlas_h, int(np.count_nonzero(valid)),
                           round(100.0 * np.count_nonzero(valid) / (atlas_w * atlas_h), 3),
                           int(np.count_nonzero(pushed)), int(np.count_nonzero(buried)),
                           [asdict(t) for t in tiles], materials, warnings, probe_info, layout)
    _write_outputs(out_dir, plan, atlas, result)
    result.seconds = time.perf_counter() - start
    update_report(out_dir, plan.stage_hash("capture"), timings_s={"capture": result.seconds}, texels=result.texels,
                  coverage_percent=result.coverage_percent, pushed_out_texels=result.pushed_out_texels,
                  buried_texels=result.buried_texels, atlas=[atlas_w, atlas_h], sg_count=plan.max_sg_count,
                  capture_pictures=list(CAPTURE_PICTURES), surface_probe=probe_info, irradiance_detail=detail)
    progress(1.0, f"{result.texels} texels")
    return result


def layout_hash(tiles, maps) -> str:
    """What a capture's outputs depend on beyond the plan: where each tile is and where its texels and their normals
    are (an object's texel scale, or its geometry under an unchanged plan, moves them)."""
    digest = hashlib.sha256(json.dumps([(t.name, list(t.pixel_rect)) for t in tiles]).encode())
    for key in ("P", "N"):
        digest.update(np.round(maps[key], 5).astype(np.float32).tobytes())
    return digest.hexdigest()[:16]


def _irradiance_detail(scene, plan, out_dir, targets, tiles, atlas_shape, layout, progress, should_cancel) -> dict:
    """Bake DIR/irradiance_detail.exr when the settings ask for a detail above 1 (else remove a stale one): the diffuse
    light of the baked surfaces at `irradiance_detail` pixels per texel. Its metadata records the capture's plan hash,
    the lightmap layout (layout_hash) and the detail, which the apply stage checks; a file that matches them is kept
    (a capture run again, as a farm's last task does, or a resumed bake), as finished light-field tiles are."""
    path = Path(out_dir) / DETAIL_FILE
    detail = plan.settings.irradiance_detail
    if detail <= 1 or not targets:
        path.unlink(missing_ok=True)
        return {"detail": 1}
    wanted = {"plan_hash": plan.stage_hash("capture"), "detail": str(detail), "samples": str(IRRADIANCE_DETAIL_SAMPLES),
              "passes": "direct and indirect in one", "bounces": "the scene's, own colours",
              "kind": "irradiance_detail", "layout": layout}
    if path.is_file():
        try:
            found = read_exr_metadata(path)
        except ExrError:  # unreadable: baked again
            found = {}
        if all(found.get(k) == v for k, v in wanted.items()):
            return {"detail": detail, "samples": IRRADIANCE_DETAIL_SAMPLES, "file": DETAIL_FILE, "kept": True}
    irradiance, written, info = bake_irradiance_detail(
        scene, targets, tiles, atlas_shape, detail,
        progress=lambda fraction, message: progress(0.45 + 0.05 * fraction, message), should_cancel=should_cancel)
    write_exr(path, filled(irradiance, written, 2 * detail), precision="half", channels=["R", "G", "B"],
              metadata=wanted)
    return {**info, "file": DETAIL_FILE, "pixels_written": int(np.count_nonzero(written))}


def _texel_atlas(maps, valid, materials):
    h, w = valid.shape
    by_id = np.zeros((len(materials) + 1, 8))
    for m in materials:
        by_id[m["id"]] = [m["roughness"], m["metallic"], *m["base_color"], *m["f0"]]
    surface = by_id[maps["material_id"]]
    measured = maps["measured"]
    surface[measured] = maps["surface"][measured]  # textured materials: the values Cycles measured per texel
    columns = [maps["P"], maps["Ng"], maps["N"], surface, valid[..., None].astype(np.float64),
               maps["flags"][..., None], maps["object_id"][..., None], maps["material_id"][..., None],
               maps["texel_size"][..., None], maps["ray_offset"][..., None]]
    atlas = np.concatenate(columns, axis=-1).astype(np.float32)
    assert atlas.shape == (h, w, len(TEXEL_CHANNELS))
    return atlas


def _measured_statistics(materials, atlas, probe_info):
    """Add what was measured per textured material to its entry of the material table: the 5th, 50th and 95th
    percentiles of its texels' roughness and metallic and the mean base colour; the probe's record lists them."""
    rows, cols = np.nonzero(atlas[..., CHANNEL["valid"]] > 0)
    ids = atlas[rows, cols, CHANNEL["material_id"]].astype(np.int64)
    for material in materials:
        mine = ids == material["id"]
        if not material.get("textured") or not np.any(mine):
            continue
        texels = atlas[rows[mine], cols[mine]]

        def percentiles(channel):
            return [round(float(v), 4) for v in np.percentile(texels[:, CHANNEL[channel]], (5, 50, 95))]

        material["measured"] = {"texels": int(np.count_nonzero(mine)),
                                "roughness_p5_p50_p95": percentiles("roughness"),
                                "metallic_p5_p50_p95": percentiles("metallic"),
                                "base_color_mean": [round(float(texels[:, CHANNEL[c]].mean()), 4)
                                                    for c in ("base.R", "base.G", "base.B")]}
    probe_info["materials"] = [m["name"] for m in materials if "measured" in m]


def _write_outputs(out_dir, plan, atlas, result):
    plan_hash = plan.stage_hash("capture")
    write_exr(out_dir / TEXELS_FILE, atlas, precision="float", channels=TEXEL_CHANNELS,
              metadata={"plan_hash": plan_hash, "stage": "capture"})
    info = {k: v for k, v in asdict(result).items() if k != "seconds"}
    write_json_atomic(out_dir / TEXELS_JSON, {"plan_hash": plan_hash, "channels": TEXEL_CHANNELS,
                                              "rows": "row 0 = top of the atlas (v near 1)",
                                              "lightmap_layer": LIGHTMAP_LAYER, "tile_properties": list(TILE_KEYS), **info})
    save_capture_pictures(out_dir, atlas)
