"""What the bake adds to render in place of what it cannot give a lightmap: mesh stand-ins for metaballs and NURBS
surfaces, object copies for particle, vertex and face instances (DESIGN section 10).

The lightmap UV lives on the evaluated surface, written by a last Geometry Nodes modifier (lightmap_modifier);
Blender gives metaballs and NURBS surfaces no modifiers at all. The capture therefore gives each baked one a
*stand-in*: a mesh object named ``SG Lightfield stand-in: NAME``, parented to it with no offset, whose own Geometry
Nodes modifier reads the source's evaluated surface through Object Info (Relative). The stand-in stays live: move
the source, edit its elements or control points, and the stand-in follows; only the lighting waits for a new bake.
Its material slots are linked to the object and hold the source's materials, so the bake switches them without
touching the source's data. The source stays in the render but invisible to every ray and probe (a metaball hidden
in renders is not polygonised there, so its stand-in would be empty: verified in bpy 5.0.1) and is drawn as wire in
the viewport, so renders and the rendered viewport show the stand-in, not both. Its own settings are kept on it and
put back by Remove SG Bake, which deletes the stand-in with its mesh.

Particle, vertex and face instances carry no attribute a material can find its tile by (Particle Info is Cycles
only), instances nested in other instances share the top level's, and geometry made inside a node tree has no
object whose slots the bake could switch. Where the settings ask for it (``instance_copies``), the capture gives
each such instance an *object copy*: a linked duplicate of the instanced object (its data shared; for node-made
geometry, a mesh of its own) at the instance's world matrix, in a collection ``SG Lightfield copies: INSTANCER``,
which gets its tile as any object does. The instancer stops instancing (its particle-system modifiers that render
objects are turned off in renders and the viewport; vertex, face or collection instancing is set to none; a
Geometry Nodes instancer gets a last modifier, ``SG Lightfield instances off``, that drops its instances and keeps
the rest), so the copies render instead; the copies are a snapshot of the instances at capture time. Remove SG Bake
deletes the copies and puts the instancer's settings back.
"""
from __future__ import annotations

import json

import bpy
from mathutils import Matrix

from .lightmap_modifier import INSTANCES_OFF_KEY, geometry_node_group, lightmap_modifier
from .temporary_settings import temporarily

STAND_IN_TYPES = {"SURFACE", "META"}  # object types Blender gives no modifiers
STAND_IN_PREFIX = "SG Lightfield stand-in: "
SOURCE_KEY = "sglf_stand_in_of"  # on a stand-in: its source object's name
SOURCE_STATE_KEY = "sglf_stand_in_state"  # on a source: its own settings of SOURCE_HIDDEN, as JSON
# What makes a source invisible in renders while it stays evaluated there (its stand-in reads its surface).
SOURCE_HIDDEN = {"visible_camera": False, "visible_diffuse": False, "visible_glossy": False,
                 "visible_transmission": False, "visible_volume_scatter": False, "visible_shadow": False,
                 "hide_probe_volume": True, "hide_probe_sphere": True, "hide_probe_plane": True, "display_type": "WIRE"}
GROUP_KEY = "sglf_stand_in_group"  # on the stand-ins' shared Geometry Nodes group
GROUP_NAME = "SG Lightfield stand-in"
SOURCE_INPUT = "Source"


def is_stand_in(obj) -> bool:
    return SOURCE_KEY in obj


def has_stand_in(obj) -> bool:
    """A source the bake made invisible behind a stand-in (it renders through the stand-in)."""
    return SOURCE_STATE_KEY in obj


def stand_in_of(source):
    """The stand-in of `source`, or None."""
    return next((child for child in source.children if SOURCE_KEY in child), None)


def _group():
    tree, made = geometry_node_group(GROUP_KEY, GROUP_NAME, (SOURCE_INPUT,))
    if not made:
        return tree
    group_in = tree.nodes.new("NodeGroupInput")
    source = tree.nodes.new("GeometryNodeObjectInfo")
    source.transform_space = "RELATIVE"
    tree.links.new(group_in.outputs[SOURCE_INPUT], source.inputs["Object"])
    tree.links.new(source.outputs["Geometry"], tree.nodes.new("NodeGroupOutput").inputs["Geometry"])
    return tree


def ensure_stand_in(source):
    """The stand-in of `source`, made (and the source made invisible behind it) where it has none yet."""
    stand_in = stand_in_of(source)
    if stand_in is not None:
        return stand_in
    name = f"{STAND_IN_PREFIX}{source.name}"
    stand_in = bpy.data.objects.new(name, bpy.data.meshes.new(name))
    stand_in[SOURCE_KEY] = source.name
    for collection in source.users_collection:
        collection.objects.link(stand_in)
    stand_in.parent = source  # the source's world matrix, with no offset: Relative geometry lands where it renders
    stand_in.matrix_parent_inverse.identity()
    stand_in.hide_select = True  # clicks select the source, which the user edits
    for slot in source.material_slots:
        stand_in.data.materials.append(None)
        own = stand_in.material_slots[-1]
        own.link = "OBJECT"
        own.material = slot.material
    modifier = stand_in.modifiers.new(GROUP_NAME, "NODES")
    modifier.node_group = _group()
    identifier = next(i.identifier for i in modifier.node_group.interface.items_tree
                      if i.item_type == "SOCKET" and i.in_out == "INPUT" and i.name == SOURCE_INPUT)
    modifier[identifier] = source
    modifier.node_group = modifier.node_group  # an ID input set as a property needs an RNA update for the depsgraph
    source[SOURCE_STATE_KEY] = json.dumps({name: getattr(source, name) for name in SOURCE_HIDDEN})
    for name, value in SOURCE_HIDDEN.items():
        setattr(source, name, value)
    return stand_in


COPYABLE = ("particle", "vertex", "face")  # instancers whose instances carry no attribute of their own (nested and
# node-made instances of any instancer bake as copies too: scene_analysis.Instanced.copyable)
COPIES_PREFIX = "SG Lightfield copies: "
COPIES_OF_KEY = "sglf_copies_of"  # on a collection of copies: its instancer's name when it was made
COPIES_COLLECTION_KEY = "sglf_copies"  # on an instancer whose instances were copied: the collection of its copies
# On a copy: {"source": the instanced object's name, "index": among the instancer's instances, "generated": whether it
# holds node-made geometry in a mesh of its own}
INSTANCE_COPY_KEY = "sglf_instance_copy"
INSTANCER_STATE_KEY = "sglf_instance_copies"  # on an instancer whose instances were copied: its own settings, JSON
OWN_KEYS_PREFIX = "sglf_"  # the bake's properties, which a copy must not inherit from its source ...
USER_KEYS = ("sglf_texel_scale",)  # ... but for the user's own setting among them (capture.TEXEL_SCALE_KEY)


def is_copy(obj) -> bool:
    return INSTANCE_COPY_KEY in obj


def copied(instancer) -> bool:
    """An instancer whose instances the bake replaced by object copies."""
    return INSTANCER_STATE_KEY in instancer


def copied_state(instancer) -> dict:
    """What the copies changed on `instancer`: {"how", "nested", and for particles "modifiers" ({name: [show_render,
    show_viewport]}), for vertex, face and collection instancing "instance_type" and "hide_render"}, its own values
    (a Geometry Nodes instancer got a modifier instead); {} where nothing was copied."""
    return json.loads(instancer[INSTANCER_STATE_KEY]) if copied(instancer) else {}


def modifiers_turned_off(instancer) -> set:
    """The names of the particle-system modifiers the copies turned off (they render in the user's setup)."""
    return set(copied_state(instancer).get("modifiers", {}))


INSTANCES_OFF_NAME = "SG Lightfield instances off"


def _instances_off_group():
    """The shared Geometry Nodes group that passes every component of a geometry but its instances."""
    tree, made = geometry_node_group(INSTANCES_OFF_KEY, INSTANCES_OFF_NAME)
    if not made:
        return tree
    parts, join = tree.nodes.new("GeometryNodeSeparateComponents"), tree.nodes.new("GeometryNodeJoinGeometry")
    tree.links.new(tree.nodes.new("NodeGroupInput").outputs[0], parts.inputs[0])
    for output in parts.outputs:
        if output.name != "Instances":
            tree.links.new(output, join.inputs[0])
    tree.links.new(join.outputs[0], tree.nodes.new("NodeGroupOutput").inputs[0])
    return tree


def _instances_off(instancer):
    """The modifier that takes `instancer`'s instances away, or None."""
    return next((m for m in instancer.modifiers if m.type == "NODES" and m.node_group is not None
                 and m.node_group.get(INSTANCES_OFF_KEY)), None)


def _instancing_settings(instancer, state, on: bool) -> list:
    """(owner, setting, value) that turn `instancer`'s instancing on (its own values, from `state`) or off."""
    if state["how"] == "geometry nodes":  # the bake's modifier after the user's stack drops the instances
        off = _instances_off(instancer)
        return [] if off is None else [(off, "show_render", not on), (off, "show_viewport", not on)]
    if state["how"] == "particle":
        return [(instancer.modifiers[name], setting, value if on else False)
                for name, values in state["modifiers"].items() if name in instancer.modifiers
                for setting, value in zip(("show_render", "show_viewport"), values)]
    # Vertex, face or collection instancing set to none; a mesh that hid itself as an instancer would render then.
    return [(instancer, "instance_type", state["instance_type"] if on else "NONE"),
            (instancer, "hide_render", state["hide_render"] if on else
             state["hide_render"] or (instancer.type == "MESH" and not instancer.show_instancer_for_render))]


def _copies_collection(instancer):
    """The collection of `instancer`'s copies (held by reference: renaming either keeps them together), or None."""
    collection = instancer.get(COPIES_COLLECTION_KEY)
    return collection if isinstance(collection, bpy.types.Collection) else None


def copies_of(instancer) -> list:
    """The copies of an instancer's instances, in the instancer's order; [] where it has none."""
    collection = _copies_collection(instancer)
    copies = [o for o in collection.objects if is_copy(o)] if collection is not None else []
    return sorted(copies, key=lambda o: int(o[INSTANCE_COPY_KEY]["index"]))


def copy_instances(scene, instancer, how, nested, entries, names, meshes=None) -> list:
    """Replace `instancer`'s instances (`how`: one of COPYABLE, "collection" or "geometry nodes"; `entries`: (source
    object name, world matrix) each, in its order; `names`: the plan's name of each; `meshes`: entry index -> a mesh
    of its own for geometry made inside a node tree) by object copies; returns them."""
    meshes = meshes or {}
    collection = bpy.data.collections.new(f"{COPIES_PREFIX}{instancer.name}")
    collection[COPIES_OF_KEY] = instancer.name
    scene.collection.children.link(collection)
    copies = []
    for k, ((source, matrix), name) in enumerate(zip(entries, names)):
        if k in meshes:  # node-made geometry: an object of its own for its mesh
            copy = bpy.data.objects.new(name, meshes[k])
        else:
            copy = bpy.data.objects[source].copy()  # a linked duplicate: the source's data, modifiers and slots
        for key in [key for key in copy.keys() if key.startswith(OWN_KEYS_PREFIX) and key not in USER_KEYS]:
            del copy[key]
        for modifier in [m for m in copy.modifiers if m.type == "PARTICLE_SYSTEM" or m == lightmap_modifier(copy)]:
            copy.modifiers.remove(modifier)  # no second generation of particles; the source's lightmap modifier
        copy.name = name
        copy[INSTANCE_COPY_KEY] = {"source": source, "index": k, "generated": k in meshes}
        copy.parent = None
        copy.matrix_world = Matrix(matrix)
        copy.hide_render = copy.hide_viewport = False
        copy.hide_select = True  # clicks select the instancer, which the user edits
        collection.objects.link(copy)
        copies.append(copy)
    state = {"how": how, "nested": bool(nested)}
    if how == "geometry nodes":
        off = instancer.modifiers.new(INSTANCES_OFF_NAME, "NODES")
        off.node_group = _instances_off_group()
    elif how == "particle":
        state["modifiers"] = {m.name: [m.show_render, m.show_viewport] for m in instancer.modifiers
                              if m.type == "PARTICLE_SYSTEM"
                              and m.particle_system.settings.render_type in ("OBJECT", "COLLECTION")}
    else:
        state.update(instance_type=instancer.instance_type, hide_render=instancer.hide_render)
    for owner, setting, value in _instancing_settings(instancer, state, on=False):
        setattr(owner, setting, value)
    instancer[INSTANCER_STATE_KEY] = json.dumps(state)
    instancer[COPIES_COLLECTION_KEY] = collection
    return copies


def original_instancing(scene):
    """For the block: every copied instancer of `scene` instances again as the user set it up and its copies are
    hidden in renders (the bench's frame time of the instances against the copies)."""
    return temporarily([change for instancer in scene.objects if copied(instancer)
                        for change in [(copy, "hide_render", True) for copy in copies_of(instancer)]
                        + _instancing_settings(instancer, copied_state(instancer), on=True)])


def _uncopy(instancer) -> None:
    collection = _copies_collection(instancer)
    if collection is not None:
        for copy in list(collection.objects):
            data = copy.data
            bpy.data.objects.remove(copy)
            if isinstance(data, bpy.types.Mesh) and data.users == 0:  # node-made geometry's own (a source's stays)
                bpy.data.meshes.remove(data)
        bpy.data.collections.remove(collection)
    for owner, setting, value in _instancing_settings(instancer, copied_state(instancer), on=True):
        setattr(owner, setting, value)
    off = _instances_off(instancer)
    if off is not None:
        instancer.modifiers.remove(off)
    if COPIES_COLLECTION_KEY in instancer:
        del instancer[COPIES_COLLECTION_KEY]
    for group in [g for g in bpy.data.node_groups if g.get(INSTANCES_OFF_KEY) and g.users == 0]:
        bpy.data.node_groups.remove(group)
    del instancer[INSTANCER_STATE_KEY]


def remove_stand_ins(scene, keep=()) -> int:
    """Delete the stand-ins and instance copies of `scene`'s objects (but the stand-ins and instancers named in
    `keep`) and give their sources and instancers back their own settings; returns how many stand-ins and copies
    went. The stand-ins' shared node group goes with the last."""
    removed = 0
    for instancer in [o for o in scene.objects if copied(o) and o.name not in keep]:
        removed += len(copies_of(instancer))
        _uncopy(instancer)
    for source in [o for o in scene.objects if has_stand_in(o)]:
        stand_in = stand_in_of(source)
        if stand_in is not None and stand_in.name in keep:
            continue
        if stand_in is not None:
            mesh = stand_in.data
            bpy.data.objects.remove(stand_in)
            if mesh.users == 0:
                bpy.data.meshes.remove(mesh)
            removed += 1
        for name, value in json.loads(source[SOURCE_STATE_KEY]).items():
            setattr(source, name, value)
        del source[SOURCE_STATE_KEY]
    for group in [g for g in bpy.data.node_groups if g.get(GROUP_KEY) and g.users == 0]:
        bpy.data.node_groups.remove(group)
    return removed
