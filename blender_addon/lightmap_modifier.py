"""Lightmap UVs on evaluated geometry: a last, removable Geometry Nodes modifier (DESIGN section 10).

Objects whose rendered surface is not their mesh data (modifier stacks, text, curves with geometry) or whose mesh
cannot hold one UV per corner for xatlas's charts (a quad split across two charts) get their lightmap UV here:

  1. the modifier ``SG Lightmap UV`` is added last; it triangulates the evaluated geometry (the same split Blender
     renders with: quads along 0-2, n-gons by ear clipping) and stores the corner attribute ``SGLightmap``;
  2. xatlas charts that triangulated mesh; the UVs go into a *carrier*: a mesh copy of it that no scene holds,
     named ``SG Lightmap carrier: OBJECT``, referenced only by the modifier;
  3. at every evaluation the modifier copies the carrier's UVs by corner index (Sample Index), so the user's stack
     stays live. Should the stack change topology afterwards (a new level of subdivision, another array count), the
     copy falls back to the carrier's nearest surface point, nudged towards the face centre so a corner on a chart
     seam reads its own face's chart; the next capture lays it out again.

Instances: on an object whose Geometry Nodes make instances of other objects, the same modifier gives each top-level
instance its atlas tile as the instance attributes ``sglf_lightmap_offset`` and ``sglf_lightmap_scale`` (copied from
the vertex of a second helper mesh, ``SG Lightmap instance tiles: OBJECT``, nearest to the instance's position); the
baked material reads them through Instancer attributes, which fall back to the object's own properties elsewhere. The
instances' own geometry passes through untouched (Separate Components: only the mesh is triangulated).

Why a modifier and not a UV layer on the mesh data: a layer on the original mesh is what Array, Mirror, Bevel and
Subdivision copy or interpolate, so their copies share texels; the user would have to apply the stack. Remove SG Bake
takes the modifier, its carrier and the node group away, and the object's modifier list is what it was.
"""
from __future__ import annotations

import bpy
import numpy as np

MODIFIER_NAME = "SG Lightmap UV"
NODE_GROUP_NAME = "SG Lightmap UV"
CARRIER_PREFIX = "SG Lightmap carrier: "
OWNED_KEY = "sglf_lightmap_modifier"  # on our modifier's node group and carriers: made by SG Lightfield
CARRIER_INPUT = "Carrier"
INSTANCE_TILES_INPUT = "Instance tiles"
INSTANCE_TILES_PREFIX = "SG Lightmap instance tiles: "
# Per-instance atlas tiles, as instance attributes (read by the baked material's Instancer attributes); the names
# are the object properties of an object's own tile (capture.OFFSET_KEY, SCALE_KEY).
INSTANCE_ATTRIBUTES = ("sglf_lightmap_offset", "sglf_lightmap_scale")
MODIFIER_TYPES = {"MESH", "CURVE", "FONT"}  # object types a Geometry Nodes modifier can be added to


def lightmap_modifier(obj):
    """The object's SG Lightmap UV modifier, or None."""
    modifiers = getattr(obj, "modifiers", None)
    if modifiers is None:
        return None
    return next((m for m in modifiers if m.type == "NODES" and m.node_group is not None
                 and m.node_group.get(OWNED_KEY) and m.name.startswith(MODIFIER_NAME)), None)


# On the node group of the modifier that takes a Geometry Nodes instancer's instances away while object copies render
# in their place (stand_ins.copy_instances).
INSTANCES_OFF_KEY = "sglf_instances_off"


def user_modifiers(obj) -> list:
    """The object's own modifiers that change what renders (the bake's excluded)."""
    ours = lightmap_modifier(obj)
    return [m for m in getattr(obj, "modifiers", ()) if m != ours and (m.show_render or m.show_viewport)
            and not (m.type == "NODES" and m.node_group is not None and m.node_group.get(INSTANCES_OFF_KEY))]


def _node(tree, kind, **props):
    node = tree.nodes.new(kind)
    for key, value in props.items():
        setattr(node, key, value)
    return node


def geometry_node_group(key, name, object_inputs=()) -> tuple:
    """(the file's Geometry Nodes group marked with the property `key`, False), or (a new one named `name` with a
    Geometry input and output and an Object input per name in `object_inputs`, True) for the caller to fill."""
    existing = next((g for g in bpy.data.node_groups if g.get(key) and g.bl_idname == "GeometryNodeTree"), None)
    if existing is not None:
        return existing, False
    tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
    tree[key] = True
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for input_name in object_inputs:
        tree.interface.new_socket(input_name, in_out="INPUT", socket_type="NodeSocketObject")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    return tree, True


def lightmap_node_group():
    """The shared Geometry Nodes group of the modifier (made once per file). Its mesh gets the lightmap UV; its
    top-level instances get their atlas tiles as instance attributes; the instances' own geometry is left alone."""
    tree, made = geometry_node_group(OWNED_KEY, NODE_GROUP_NAME, (CARRIER_INPUT, INSTANCE_TILES_INPUT))
    if not made:
        return tree
    link = tree.links.new
    group_in, group_out = _node(tree, "NodeGroupInput"), _node(tree, "NodeGroupOutput")
    parts = _node(tree, "GeometryNodeSeparateComponents")
    link(group_in.outputs["Geometry"], parts.inputs[0])
    join = _node(tree, "GeometryNodeJoinGeometry")
    link(_lightmap_uv_nodes(tree, parts.outputs["Mesh"], group_in.outputs[CARRIER_INPUT]), join.inputs[0])
    for name in ("Curve", "Point Cloud", "Volume", "Grease Pencil"):
        if name in parts.outputs:
            link(parts.outputs[name], join.inputs[0])
    link(_instance_tile_nodes(tree, parts.outputs["Instances"], group_in.outputs[INSTANCE_TILES_INPUT]), join.inputs[0])
    link(join.outputs[0], group_out.inputs["Geometry"])
    return tree


def _lightmap_uv_nodes(tree, mesh_socket, carrier_socket):
    """Triangulate the mesh and store the carrier's UVs as SGLightmap; returns the output socket."""
    link = tree.links.new
    triangulate = _node(tree, "GeometryNodeTriangulate")
    _set_enum_input(triangulate, "Quad Method", "quad_method", "FIXED")
    _set_enum_input(triangulate, "N-gon Method", "ngon_method", "CLIP")
    link(mesh_socket, triangulate.inputs["Mesh"])
    carrier = _node(tree, "GeometryNodeObjectInfo", transform_space="ORIGINAL")
    link(carrier_socket, carrier.inputs["Object"])
    stored_uv = _node(tree, "GeometryNodeInputNamedAttribute", data_type="FLOAT_VECTOR")
    stored_uv.inputs["Name"].default_value = "SGLightmap"
    by_index = _node(tree, "GeometryNodeSampleIndex", data_type="FLOAT_VECTOR", domain="CORNER")
    link(carrier.outputs["Geometry"], by_index.inputs["Geometry"])
    link(stored_uv.outputs["Attribute"], by_index.inputs["Value"])
    link(_node(tree, "GeometryNodeInputIndex").outputs[0], by_index.inputs["Index"])
    # Topology changed since the capture: the nearest carrier point to a spot just inside the corner's face.
    position = _node(tree, "GeometryNodeInputPosition")
    face_centre = _node(tree, "GeometryNodeFieldOnDomain", data_type="FLOAT_VECTOR", domain="FACE")
    link(position.outputs[0], face_centre.inputs[0])
    nudge = _node(tree, "ShaderNodeMix", data_type="VECTOR")
    nudge.inputs["Factor"].default_value = 1e-3
    link(position.outputs[0], nudge.inputs["A"])
    link(face_centre.outputs[0], nudge.inputs["B"])
    nearest = _node(tree, "GeometryNodeSampleNearestSurface", data_type="FLOAT_VECTOR")
    link(carrier.outputs["Geometry"], nearest.inputs["Mesh"])
    link(stored_uv.outputs["Attribute"], nearest.inputs["Value"])
    link(nudge.outputs["Result"], nearest.inputs["Sample Position"])
    carrier_size = _node(tree, "GeometryNodeAttributeDomainSize", component="MESH")
    link(carrier.outputs["Geometry"], carrier_size.inputs[0])
    own_size = _node(tree, "GeometryNodeAttributeDomainSize", component="MESH")
    link(triangulate.outputs[0], own_size.inputs[0])
    same = _node(tree, "FunctionNodeCompare", data_type="INT", operation="EQUAL")
    link(carrier_size.outputs["Face Corner Count"], same.inputs["A"])
    link(own_size.outputs["Face Corner Count"], same.inputs["B"])
    choose = _node(tree, "GeometryNodeSwitch", input_type="VECTOR")
    link(same.outputs[0], choose.inputs["Switch"])
    link(nearest.outputs[0], choose.inputs["False"])
    link(by_index.outputs[0], choose.inputs["True"])
    store = _node(tree, "GeometryNodeStoreNamedAttribute", data_type="FLOAT2", domain="CORNER")
    store.inputs["Name"].default_value = "SGLightmap"
    link(triangulate.outputs[0], store.inputs["Geometry"])
    link(choose.outputs[0], store.inputs["Value"])
    return store.outputs[0]


def _instance_tile_nodes(tree, instances_socket, tiles_socket):
    """Give each top-level instance the tile of the tiles object's vertex nearest to its position (the instancer's
    space); without tiles the instances pass unchanged. Returns the output socket."""
    link = tree.links.new
    tiles = _node(tree, "GeometryNodeObjectInfo", transform_space="ORIGINAL")
    link(tiles_socket, tiles.inputs["Object"])
    nearest = _node(tree, "GeometryNodeSampleNearest", domain="POINT")
    link(tiles.outputs["Geometry"], nearest.inputs["Geometry"])
    link(_node(tree, "GeometryNodeInputPosition").outputs[0], nearest.inputs["Sample Position"])
    count = _node(tree, "GeometryNodeAttributeDomainSize", component="MESH")
    link(tiles.outputs["Geometry"], count.inputs[0])
    any_tiles = _node(tree, "FunctionNodeCompare", data_type="INT", operation="GREATER_THAN")
    link(count.outputs["Point Count"], any_tiles.inputs["A"])
    any_tiles.inputs["B"].default_value = 0
    socket = instances_socket
    for name in INSTANCE_ATTRIBUTES:
        value = _node(tree, "GeometryNodeInputNamedAttribute", data_type="FLOAT_VECTOR")
        value.inputs["Name"].default_value = name
        sample = _node(tree, "GeometryNodeSampleIndex", data_type="FLOAT_VECTOR", domain="POINT")
        link(tiles.outputs["Geometry"], sample.inputs["Geometry"])
        link(value.outputs["Attribute"], sample.inputs["Value"])
        link(nearest.outputs["Index"], sample.inputs["Index"])
        store = _node(tree, "GeometryNodeStoreNamedAttribute", data_type="FLOAT_VECTOR", domain="INSTANCE")
        store.inputs["Name"].default_value = name
        link(socket, store.inputs["Geometry"])
        link(any_tiles.outputs[0], store.inputs["Selection"])
        link(sample.outputs[0], store.inputs["Value"])
        socket = store.outputs[0]
    return socket


def _set_enum_input(node, socket_name, property_name, value):
    """Blender 5 turned some node enums into menu sockets; older versions keep them as properties."""
    socket = node.inputs.get(socket_name)
    if socket is not None:
        socket.default_value = {"FIXED": "Fixed", "CLIP": "Clip"}.get(value, value)
    else:
        setattr(node, property_name, value)


def _input_identifier(modifier, name):
    return next(i.identifier for i in modifier.node_group.interface.items_tree
                if i.item_type == "SOCKET" and i.in_out == "INPUT" and i.name == name)


def carrier_of(obj):
    modifier = lightmap_modifier(obj)
    return None if modifier is None else modifier[_input_identifier(modifier, CARRIER_INPUT)]


def instance_tiles_of(obj):
    modifier = lightmap_modifier(obj)
    return None if modifier is None else modifier[_input_identifier(modifier, INSTANCE_TILES_INPUT)]


def swap_instance_tiles(obj, tiles):
    """Give `obj`'s modifier another instance-tiles object (None: its instances read their object's own tile);
    returns the one it had."""
    modifier = lightmap_modifier(obj)
    identifier = _input_identifier(modifier, INSTANCE_TILES_INPUT)
    previous, modifier[identifier] = modifier[identifier], tiles
    _reevaluate(obj, modifier)
    return previous


def set_instance_tiles(obj, positions, offsets, scales) -> None:
    """Give `obj`'s modifier the atlas tiles of its top-level instances: one vertex per instance at its position in
    `obj`'s space, with the tile's offset and scale (atlas_uv = offset + uv * scale) as vertex attributes."""
    modifier = lightmap_modifier(obj)
    mesh = bpy.data.meshes.new(f"{INSTANCE_TILES_PREFIX}{obj.name}")
    mesh[OWNED_KEY] = True
    mesh.vertices.add(len(positions))
    mesh.vertices.foreach_set("co", np.asarray(positions, np.float32).ravel())
    for name, values in zip(INSTANCE_ATTRIBUTES, (offsets, scales)):
        mesh.attributes.new(name, "FLOAT_VECTOR", "POINT").data.foreach_set(
            "vector", np.asarray(values, np.float32).ravel())
    mesh.update()
    tiles = instance_tiles_of(obj)
    if tiles is None:
        tiles = bpy.data.objects.new(f"{INSTANCE_TILES_PREFIX}{obj.name}", mesh)
        tiles[OWNED_KEY] = True
        modifier[_input_identifier(modifier, INSTANCE_TILES_INPUT)] = tiles
    else:
        tiles.data = mesh  # the previous mesh is an orphan (remove_orphans) unless a cancel snapshot holds it
    _reevaluate(obj, modifier)


def attach(obj):
    """Add the modifier (last, no carrier yet: it only triangulates); returns it. An existing one is moved last."""
    modifier = lightmap_modifier(obj)
    if modifier is None:
        modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
        modifier.node_group = lightmap_node_group()
    else:
        while obj.modifiers[-1] != modifier:
            obj.modifiers.move(list(obj.modifiers).index(modifier), len(obj.modifiers) - 1)
    modifier.show_viewport = modifier.show_render = True
    return modifier


def set_carrier(obj, evaluated_mesh, loop_uv):
    """Give `obj`'s modifier a carrier: a copy of `evaluated_mesh` (its triangulated output) with `loop_uv` as
    SGLightmap. The carrier object is reused; its previous mesh is returned (the caller may keep it to restore)."""
    modifier = lightmap_modifier(obj)
    mesh = bpy.data.meshes.new(f"{CARRIER_PREFIX}{obj.name}")
    mesh[OWNED_KEY] = True
    count = len(evaluated_mesh.loops)
    positions = np.empty(len(evaluated_mesh.vertices) * 3, np.float32)
    evaluated_mesh.vertices.foreach_get("co", positions)
    corner_verts = np.empty(count, np.int32)
    evaluated_mesh.loops.foreach_get("vertex_index", corner_verts)
    starts = np.empty(len(evaluated_mesh.polygons), np.int32)
    evaluated_mesh.polygons.foreach_get("loop_start", starts)
    mesh.vertices.add(len(positions) // 3)
    mesh.vertices.foreach_set("co", positions)
    mesh.loops.add(count)
    mesh.loops.foreach_set("vertex_index", corner_verts)
    mesh.polygons.add(len(starts))
    mesh.polygons.foreach_set("loop_start", starts)
    mesh.update(calc_edges=True)
    layer = mesh.uv_layers.new(name="SGLightmap", do_init=False)
    layer.uv.foreach_set("vector", np.asarray(loop_uv, np.float32).ravel())
    carrier = carrier_of(obj)
    previous = None
    if carrier is None:
        carrier = bpy.data.objects.new(f"{CARRIER_PREFIX}{obj.name}", mesh)
        carrier[OWNED_KEY] = True
        modifier[_input_identifier(modifier, CARRIER_INPUT)] = carrier
    else:
        previous, carrier.data = carrier.data, mesh
    _reevaluate(obj, modifier)
    return previous


def _reevaluate(obj, modifier) -> None:
    """A modifier input set as an ID property does not rebuild the depsgraph's relations; an RNA update does."""
    modifier.node_group = modifier.node_group
    obj.update_tag()


def restore_helpers(obj, carrier_mesh, tiles_mesh) -> None:
    """Put back the carrier and instance-tiles meshes an earlier capture gave `obj`'s modifier (None: keep)."""
    for helper, mesh in ((carrier_of(obj), carrier_mesh), (instance_tiles_of(obj), tiles_mesh)):
        if helper is not None and mesh is not None:
            replaced, helper.data = helper.data, mesh
            if replaced.users == 0:
                bpy.data.meshes.remove(replaced)
    _reevaluate(obj, lightmap_modifier(obj))


def detach(obj) -> bool:
    """Remove the object's modifier and carrier; the shared node group goes when nothing uses it. True if removed."""
    modifier = lightmap_modifier(obj)
    if modifier is None:
        return False
    helpers = [o for o in (carrier_of(obj), instance_tiles_of(obj)) if o is not None]
    obj.modifiers.remove(modifier)
    for helper in helpers:
        mesh = helper.data
        bpy.data.objects.remove(helper)
        if mesh is not None and mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    remove_orphans()
    return True


def remove_orphans() -> None:
    """Carrier meshes and node groups of ours that nothing uses any more (an earlier capture's)."""
    for mesh in [m for m in bpy.data.meshes if m.get(OWNED_KEY) and m.users == 0]:
        bpy.data.meshes.remove(mesh)
    for group in [g for g in bpy.data.node_groups if g.get(OWNED_KEY) and g.bl_idname == "GeometryNodeTree"
                  and g.users == 0]:
        bpy.data.node_groups.remove(group)
