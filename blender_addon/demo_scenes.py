"""Embedded demo scenes, built by code (bpy.data + bmesh, no downloads; operators only for the NURBS sphere).

Selectable everywhere as ``demo:NAME``: ``build_demo_scene("room")`` returns a new bpy Scene.
  spheres    Paper I Table 2: GGX roughness 0.2 / 0.3 / 0.4 / 0.5 in a row on a rough plane, lit only
             by emissive arcs behind them, black world.
  room       closed room, coloured walls, glossy floor, a glossy and a rough object, an emissive
             ceiling panel and one point lamp.
  courtyard  objects that occlude each other under Blender's shipped courtyard HDRI.
  materials  the materials real scenes have: a checker floor with a noise roughness through Map Range and a bump
             map, an image-textured metal sphere, a Mix Shader of Diffuse and Glossy with a textured factor, a
             Principled BSDF inside a node group behind reroutes, a glossy sign with textured emission, a box
             under a clear coat (baked below the coat), an alpha cut-out leaf card (baked, its alpha kept); and
             what the bake leaves to the renderer, a glass sphere; an area lamp and Blender's shipped interior HDRI.
  geometry   what real scenes are built from, each glossy: a smooth monkey primitive, a live Bevel + Array +
             Subdivision stack, extruded text, a bevelled curve, geometry-node instances, two collection instances,
             a metaball, a NURBS sphere and particle-scattered pebbles, on a counter.
  hair       a head-like mesh with a groom made by Blender's shipped procedural hair node assets;
             ``hair-straight``, ``hair-wavy`` (= ``hair``), ``hair-curly`` and ``hair-clumped`` pick the style.
"""
from __future__ import annotations

import math
import os

import bmesh
import bpy
from mathutils import Matrix, Vector

from ..bake_directory.bake_plan import BakeInputError
from .scene_analysis import empty_node_material, enable_nodes

DEMO_SCENES = ("spheres", "room", "courtyard", "materials", "geometry", "hair")
HAIR_STYLES = ("straight", "wavy", "curly", "clumped")
DEMO_PREFIX = "demo:"


def shipped_hdri(name: str) -> str:
    """Path of one of the CC0 HDRIs that ship inside Blender (city, courtyard, forest, ...)."""
    path = os.path.join(bpy.utils.system_resource("DATAFILES"), "studiolights", "world", f"{name}.exr")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"Blender's shipped HDRI '{name}' not found at {path}")
    return path


def shipped_hair_node_group(name: str):
    """A node group from Blender's shipped procedural hair assets (appended once, reused afterwards)."""
    existing = bpy.data.node_groups.get(name)
    if existing is not None and existing.library is None and existing.get("sglf_shipped_asset"):
        return existing
    path = os.path.join(bpy.utils.system_resource("DATAFILES"), "assets", "nodes", "procedural_hair_node_assets.blend")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"Blender's procedural hair node assets not found at {path}")
    with bpy.data.libraries.load(path) as (source, target):
        if name not in source.node_groups:
            raise KeyError(f"node group {name!r} is not among Blender's procedural hair assets")
        target.node_groups = [name]
    group = target.node_groups[0]
    group["sglf_shipped_asset"] = True
    return group


def _principled(name, color=(0.8, 0.8, 0.8), roughness=0.5, metallic=0.0, emission=None, strength=0.0):
    mat = bpy.data.materials.new(name)
    enable_nodes(mat)
    bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    if emission is not None:
        bsdf.inputs["Emission Color"].default_value = (*emission, 1.0)
        bsdf.inputs["Emission Strength"].default_value = strength
    return mat


def _mesh_object(scene, name, build, material, matrix=Matrix.Identity(4)):
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bm.loops.layers.uv.new("UVMap")  # the user's own UV map (bmesh fills it where calc_uvs is asked for)
    build(bm)
    _to_mesh_in_fixed_order(bm, mesh)
    bm.free()
    mesh.materials.append(material)
    for poly in mesh.polygons:
        poly.use_smooth = len(mesh.polygons) > 64  # spheres and tori smooth, boxes and planes flat
    obj = bpy.data.objects.new(name, mesh)
    obj.matrix_world = matrix
    scene.collection.objects.link(obj)
    return obj


def _to_mesh_in_fixed_order(bm, mesh):
    """bm into mesh with its vertices (by position), faces and each face's first loop in one fixed order.
    bmesh.ops.create_uvsphere orders faces and loops differently in every process (Blender 5.0.1, measured), and
    xatlas's lightmap layout follows that order: a demo bake resumed, or split over machines with --tile, would
    pair the light fields of one process's texels with another's surface points."""
    bm.verts.index_update()
    rank = {v.index: i for i, v in enumerate(sorted(bm.verts, key=lambda v: tuple(round(c, 6) for c in v.co)))}
    uv_layer = bm.loops.layers.uv.active
    faces = []
    for face in bm.faces:
        loops = list(face.loops)
        first = min(range(len(loops)), key=lambda k: rank[loops[k].vert.index])
        loops = loops[first:] + loops[:first]  # same winding, the lowest-ranked vertex first
        faces.append(([rank[loop.vert.index] for loop in loops],
                      [tuple(loop[uv_layer].uv) for loop in loops] if uv_layer is not None else []))
    faces.sort(key=lambda face: face[0])
    positions = [None] * len(rank)
    for v in bm.verts:
        positions[rank[v.index]] = tuple(v.co)
    mesh.from_pydata(positions, [], [indices for indices, _ in faces])
    if uv_layer is not None:
        mesh.uv_layers.new(name=uv_layer.name).uv.foreach_set("vector", [c for _, uvs in faces for uv in uvs
                                                                          for c in uv])
    mesh.validate()


def _sphere(radius, segments=32, rings=16):
    return lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=radius,
                                                calc_uvs=True)


def _box(sx, sy, sz):
    def build(bm):
        bmesh.ops.create_cube(bm, size=1.0, calc_uvs=True)
        bmesh.ops.scale(bm, vec=Vector((sx, sy, sz)), verts=bm.verts)
    return build


def _plane(sx, sy):
    def build(bm):
        bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5, calc_uvs=True)
        bmesh.ops.scale(bm, vec=Vector((sx, sy, 1.0)), verts=bm.verts)
    return build


def _arc(radius, thickness, start, end, segments=48):
    """A thin tube bent along a circular arc in the XZ plane (an 'emissive arc')."""
    def build(bm):
        rings = []
        for i in range(segments + 1):
            a = start + (end - start) * i / segments
            centre = Vector((radius * math.cos(a), 0.0, radius * math.sin(a)))
            tangent = Vector((-math.sin(a), 0.0, math.cos(a)))
            side = Vector((0.0, 1.0, 0.0))
            normal = tangent.cross(side)
            ring = [bm.verts.new(centre + thickness * (math.cos(b) * normal + math.sin(b) * side))
                    for b in (2 * math.pi * k / 8 for k in range(8))]
            rings.append(ring)
        for r0, r1 in zip(rings, rings[1:]):
            for k in range(8):
                bm.faces.new((r0[k], r0[(k + 1) % 8], r1[(k + 1) % 8], r1[k]))
    return build


def _camera(scene, location, target, lens=35.0):
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.lens = lens
    cam = bpy.data.objects.new("Camera", cam_data)
    cam.location = location
    direction = Vector(target) - Vector(location)
    cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


def _world(scene, color=(0.0, 0.0, 0.0), strength=1.0, hdri=None):
    world = bpy.data.worlds.new(f"{scene.name} World")
    enable_nodes(world)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    background = next(n for n in nodes if n.type == "BACKGROUND")
    background.inputs["Color"].default_value = (*color, 1.0)
    background.inputs["Strength"].default_value = strength
    if hdri:
        env = nodes.new("ShaderNodeTexEnvironment")
        env.image = bpy.data.images.load(shipped_hdri(hdri), check_existing=True)
        links.new(env.outputs["Color"], background.inputs["Color"])
    scene.world = world
    return world


def _new_scene(name):
    scene = bpy.data.scenes.new(name)
    scene.render.engine = "CYCLES"
    scene.render.resolution_x, scene.render.resolution_y = 640, 360
    return scene


def build_spheres(scene):
    floor = _principled("Floor", color=(0.5, 0.5, 0.5), roughness=0.8)
    _mesh_object(scene, "Floor", _plane(10.0, 6.0), floor)
    for i, rough in enumerate((0.2, 0.3, 0.4, 0.5)):
        mat = _principled(f"Glossy (roughness {rough:.1f})", color=(0.8, 0.8, 0.8), roughness=rough, metallic=1.0)
        _mesh_object(scene, f"Sphere (roughness {rough:.1f})", _sphere(0.6), mat,
                     Matrix.Translation((-2.4 + 1.6 * i, 0.0, 0.6)))
    for i, (color, radius) in enumerate((((1.0, 0.3, 0.2), 3.0), ((0.3, 1.0, 0.4), 3.6), ((0.3, 0.5, 1.0), 4.2))):
        mat = _principled(f"Arc {i}", color=(0, 0, 0), roughness=1.0, emission=color, strength=6.0)
        _mesh_object(scene, f"Arc {i}", _arc(radius, 0.06, math.radians(15), math.radians(165)), mat,
                     Matrix.Translation((0.0, 2.5 + 0.4 * i, 0.0)))
    _world(scene, color=(0, 0, 0), strength=0.0)
    _camera(scene, (0.0, -7.0, 2.2), (0.0, 0.0, 0.6))


def build_room(scene):
    w, d, h = 6.0, 6.0, 3.0
    white = _principled("White Wall", (0.8, 0.8, 0.8), roughness=0.9)
    walls = {
        "Floor": (_plane(w, d), Matrix.Identity(4), _principled("Glossy Floor", (0.6, 0.6, 0.6), roughness=0.25)),
        "Ceiling": (_plane(w, d), Matrix.Translation((0, 0, h)) @ Matrix.Rotation(math.pi, 4, "X"), white),
        "Wall Left": (_plane(h, d), Matrix.Translation((-w / 2, 0, h / 2)) @ Matrix.Rotation(math.pi / 2, 4, "Y"),
                      _principled("Red Wall", (0.8, 0.1, 0.1), roughness=0.9)),
        "Wall Right": (_plane(h, d), Matrix.Translation((w / 2, 0, h / 2)) @ Matrix.Rotation(-math.pi / 2, 4, "Y"),
                       _principled("Green Wall", (0.1, 0.7, 0.1), roughness=0.9)),
        "Wall Back": (_plane(w, h), Matrix.Translation((0, d / 2, h / 2)) @ Matrix.Rotation(math.pi / 2, 4, "X"),
                      white),
        "Wall Front": (_plane(w, h), Matrix.Translation((0, -d / 2, h / 2)) @ Matrix.Rotation(-math.pi / 2, 4, "X"),
                       white),
    }
    for name, (build, matrix, mat) in walls.items():
        _mesh_object(scene, name, build, mat, matrix)
    _mesh_object(scene, "Glossy Sphere", _sphere(0.7), _principled("Gold", (1.0, 0.75, 0.3), 0.2, metallic=1.0),
                 Matrix.Translation((-1.0, 0.5, 0.7)))
    _mesh_object(scene, "Rough Box", _box(1.0, 1.0, 1.4), _principled("Rough Blue", (0.2, 0.3, 0.8), 0.85),
                 Matrix.Translation((1.3, 1.0, 0.7)) @ Matrix.Rotation(0.4, 4, "Z"))
    panel = _principled("Ceiling Light", (0, 0, 0), 1.0, emission=(1.0, 0.95, 0.85), strength=12.0)
    _mesh_object(scene, "Light Panel", _plane(1.5, 1.5), panel,
                 Matrix.Translation((0, 0, h - 0.01)) @ Matrix.Rotation(math.pi, 4, "X"))
    lamp_data = bpy.data.lights.new("Lamp", type="POINT")
    lamp_data.energy = 150.0
    lamp_data.color = (1.0, 0.85, 0.7)
    lamp_data.shadow_soft_size = 0.1
    lamp = bpy.data.objects.new("Lamp", lamp_data)
    lamp.location = (2.0, -1.5, 2.2)
    scene.collection.objects.link(lamp)
    _world(scene, color=(0, 0, 0), strength=0.0)
    _camera(scene, (0.0, -2.9, 1.6), (0.0, 0.5, 0.7), lens=20.0)


def build_courtyard(scene):
    _mesh_object(scene, "Ground", _plane(12.0, 12.0), _principled("Glossy Ground", (0.4, 0.4, 0.4), roughness=0.3))
    stone = _principled("Stone", (0.7, 0.65, 0.6), roughness=0.6)  # one material on both stone objects
    _mesh_object(scene, "Tall Block", _box(1.0, 1.0, 3.0), stone, Matrix.Translation((0.0, 1.0, 1.5)))
    _mesh_object(scene, "Chrome Sphere", _sphere(0.6), _principled("Chrome", (0.9, 0.9, 0.9), 0.15, metallic=1.0),
                 Matrix.Translation((0.9, 0.0, 0.6)))
    _mesh_object(scene, "Arch Roof", _box(2.5, 1.0, 0.2), stone, Matrix.Translation((-1.5, -0.5, 1.6)))
    _mesh_object(scene, "Glossy Box", _box(0.8, 0.8, 0.8), _principled("Glossy Red", (0.7, 0.1, 0.1), roughness=0.3),
                 Matrix.Translation((-1.5, -0.5, 0.4)))
    _world(scene, hdri="courtyard")
    _camera(scene, (3.5, -5.5, 2.5), (-0.3, 0.0, 0.8), lens=30.0)


def _node(tree, kind, location=(0, 0), **props):
    node = tree.nodes.new(kind)
    for key, value in props.items():
        setattr(node, key, value)
    node.location = location
    return node


def _textured_floor():
    """Checker base colour, noise roughness through Map Range, a bump map from the same noise."""
    mat = _principled("Checker Floor", roughness=0.3)
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    checker = _node(tree, "ShaderNodeTexChecker", (-700, 300))
    checker.inputs["Scale"].default_value = 8.0
    checker.inputs["Color1"].default_value = (0.75, 0.72, 0.65, 1.0)
    checker.inputs["Color2"].default_value = (0.12, 0.12, 0.14, 1.0)
    noise = _node(tree, "ShaderNodeTexNoise", (-900, -100))
    noise.inputs["Scale"].default_value = 3.0
    remap = _node(tree, "ShaderNodeMapRange", (-600, -100))
    remap.inputs["From Min"].default_value, remap.inputs["From Max"].default_value = 0.35, 0.65
    remap.inputs["To Min"].default_value, remap.inputs["To Max"].default_value = 0.12, 0.5
    bump = _node(tree, "ShaderNodeBump", (-400, -350))
    bump.inputs["Strength"].default_value = 0.25
    tree.links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    tree.links.new(noise.outputs["Fac"], remap.inputs["Value"])
    tree.links.new(remap.outputs["Result"], bsdf.inputs["Roughness"])
    tree.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    tree.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def _image_metal():
    """A metal whose base colour is an image through the UV map (Blender's generated colour grid: no file)."""
    mat = _principled("Painted Metal", roughness=0.25, metallic=1.0)
    tree = mat.node_tree
    image = bpy.data.images.get("Painted Metal Grid") or bpy.data.images.new("Painted Metal Grid", 256, 256)
    image.generated_type = "COLOR_GRID"
    texture = _node(tree, "ShaderNodeTexImage", (-500, 300), image=image)
    tree.links.new(texture.outputs["Color"], tree.nodes["Principled BSDF"].inputs["Base Color"])
    return mat


def _mixed_diffuse_glossy():
    """Mix Shader of a Diffuse and a Glossy BSDF, its factor a wave texture."""
    mat = bpy.data.materials.new("Diffuse Glossy Mix")
    enable_nodes(mat)
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    diffuse = _node(tree, "ShaderNodeBsdfDiffuse", (-300, 200))
    diffuse.inputs["Color"].default_value = (0.8, 0.35, 0.1, 1.0)
    glossy = _node(tree, "ShaderNodeBsdfGlossy", (-300, -50))
    glossy.inputs["Color"].default_value = (0.9, 0.9, 0.9, 1.0)
    glossy.inputs["Roughness"].default_value = 0.3
    wave = _node(tree, "ShaderNodeTexWave", (-600, 400))
    wave.inputs["Scale"].default_value = 3.0
    mix = _node(tree, "ShaderNodeMixShader", (0, 100))
    tree.links.new(wave.outputs["Fac"], mix.inputs["Fac"])
    tree.links.new(diffuse.outputs[0], mix.inputs[1])
    tree.links.new(glossy.outputs[0], mix.inputs[2])
    tree.links.new(mix.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return mat


def _grouped_gold():
    """A Principled BSDF inside a node group ('Brushed Gold'), reached through reroutes."""
    group = bpy.data.node_groups.new("Brushed Gold", "ShaderNodeTree")
    group.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    group.interface.new_socket("Roughness", in_out="INPUT", socket_type="NodeSocketFloat").default_value = 0.35
    inputs = _node(group, "NodeGroupInput", (-500, 0))
    outputs = _node(group, "NodeGroupOutput", (400, 0))
    bsdf = _node(group, "ShaderNodeBsdfPrincipled", (0, 0))
    bsdf.inputs["Base Color"].default_value = (1.0, 0.72, 0.3, 1.0)
    bsdf.inputs["Metallic"].default_value = 1.0
    reroute = _node(group, "NodeReroute", (250, 0))
    group.links.new(inputs.outputs["Roughness"], bsdf.inputs["Roughness"])
    group.links.new(bsdf.outputs[0], reroute.inputs[0])
    group.links.new(reroute.outputs[0], outputs.inputs["Shader"])
    mat = bpy.data.materials.new("Grouped Gold")
    enable_nodes(mat)
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    node = _node(tree, "ShaderNodeGroup", (-200, 0), node_tree=group)
    node.inputs["Roughness"].default_value = 0.35
    reroute = _node(tree, "NodeReroute", (100, 0))
    tree.links.new(node.outputs[0], reroute.inputs[0])
    tree.links.new(reroute.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return mat


def _glowing_sign():
    """A glossy dielectric whose emission is a brick texture: emission on a baked surface, kept."""
    mat = _principled("Glowing Sign", (0.1, 0.1, 0.1), roughness=0.3)
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    brick = _node(tree, "ShaderNodeTexBrick", (-500, -200))
    brick.inputs["Color1"].default_value = (1.0, 0.5, 0.1, 1.0)
    brick.inputs["Color2"].default_value = (0.2, 0.6, 1.0, 1.0)
    brick.inputs["Mortar"].default_value = (0.0, 0.0, 0.0, 1.0)
    tree.links.new(brick.outputs["Color"], bsdf.inputs["Emission Color"])
    bsdf.inputs["Emission Strength"].default_value = 1.5
    return mat


def _area_lamp(scene, energy, location, tilt_y_degrees):
    """A 1 m area lamp tilted 30 degrees about X and `tilt_y_degrees` about Y."""
    lamp = bpy.data.objects.new("Area Lamp", bpy.data.lights.new("Area Lamp", type="AREA"))
    lamp.data.energy, lamp.data.size = energy, 1.0
    lamp.location = location
    lamp.rotation_euler = (math.radians(30), math.radians(tilt_y_degrees), 0.0)
    scene.collection.objects.link(lamp)
    return lamp


def build_materials(scene):
    _mesh_object(scene, "Floor", _plane(6.0, 6.0), _textured_floor())
    _mesh_object(scene, "Painted Sphere", _sphere(0.55), _image_metal(), Matrix.Translation((-1.3, 0.3, 0.55)))
    glass = _principled("Glass", (1.0, 1.0, 1.0), roughness=0.05)
    glass.node_tree.nodes["Principled BSDF"].inputs["Transmission Weight"].default_value = 1.0
    _mesh_object(scene, "Glass Sphere", _sphere(0.4), glass, Matrix.Translation((0.9, -0.8, 0.4)))
    _mesh_object(scene, "Mixed Cube", _box(0.8, 0.8, 0.8), _mixed_diffuse_glossy(),
                 Matrix.Translation((0.4, 0.9, 0.4)) @ Matrix.Rotation(0.5, 4, "Z"))
    _mesh_object(scene, "Gold Ball", _sphere(0.35), _grouped_gold(), Matrix.Translation((-0.2, -0.6, 0.35)))
    _mesh_object(scene, "Sign", _box(1.6, 0.1, 0.8), _glowing_sign(), Matrix.Translation((0.0, 2.2, 0.6)))
    leaf = _principled("Leaf Cut-out", (0.2, 0.5, 0.1), roughness=0.5)
    checker = _node(leaf.node_tree, "ShaderNodeTexChecker", (-400, 0))
    checker.inputs["Color1"].default_value, checker.inputs["Color2"].default_value = (1, 1, 1, 1), (0, 0, 0, 1)
    leaf.node_tree.links.new(checker.outputs["Fac"], leaf.node_tree.nodes["Principled BSDF"].inputs["Alpha"])
    _mesh_object(scene, "Leaf Card", _plane(0.8, 0.8), leaf,
                 Matrix.Translation((1.8, 0.6, 0.5)) @ Matrix.Rotation(math.pi / 2, 4, "X"))
    coated = _principled("Car Paint", (0.5, 0.02, 0.02), roughness=0.4)
    coated.node_tree.nodes["Principled BSDF"].inputs["Coat Weight"].default_value = 1.0
    _mesh_object(scene, "Coated Box", _box(0.5, 0.5, 0.5), coated, Matrix.Translation((-2.0, -1.0, 0.25)))
    _area_lamp(scene, 250.0, (1.5, -1.5, 3.0), 20.0)
    _world(scene, hdri="interior", strength=0.6)
    _camera(scene, (2.6, -4.4, 2.3), (-0.2, 0.3, 0.4), lens=30.0)


def bevel_array_subdivision(obj, bevel_width, spacing, count=4):
    """A procedural stack real files have: Bevel (2 segments), an Array of `count` copies along X `spacing` object
    widths apart, Subdivision at level 1 in the viewport and 2 in renders. Returns the modifiers."""
    bevel = obj.modifiers.new("Bevel", "BEVEL")
    bevel.width, bevel.segments = bevel_width, 2
    array = obj.modifiers.new("Array", "ARRAY")
    array.count, array.relative_offset_displace = count, (spacing, 0.0, 0.0)
    subdivision = obj.modifiers.new("Subdivision", "SUBSURF")
    subdivision.levels, subdivision.render_levels = 1, 2
    return bevel, array, subdivision


def instance_on_grid(name, size, instance_socket):
    """A Geometry Nodes tree instancing what `instance_socket(tree)` returns on a 3 x 2 grid of points `size` (x, y)
    across: the scatter setups real files have."""
    tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    points = tree.nodes.new("GeometryNodeMeshGrid")
    points.inputs["Vertices X"].default_value, points.inputs["Vertices Y"].default_value = 3, 2
    points.inputs["Size X"].default_value, points.inputs["Size Y"].default_value = size
    instance = tree.nodes.new("GeometryNodeInstanceOnPoints")
    tree.links.new(points.outputs["Mesh"], instance.inputs["Points"])
    tree.links.new(instance_socket(tree), instance.inputs["Instance"])
    tree.links.new(instance.outputs["Instances"], tree.nodes.new("NodeGroupOutput").inputs[0])
    return tree


def _monkey(bm):
    bmesh.ops.create_monkey(bm)


def build_geometry(scene):
    """What real scenes are built from, each glossy: a smooth-shaded monkey primitive (its quads split across
    lightmap charts), a bar whose Bevel + Array + Subdivision stack stays live, an extruded text, a bevelled curve
    spheres instanced on a grid by Geometry Nodes, two instances of a collection of a cup and saucer, a metaball of
    two merging elements, a NURBS sphere and pebbles scattered by a particle system, on a counter under an area lamp
    and a shipped HDRI."""
    _mesh_object(scene, "Counter", _box(5.0, 3.0, 0.2), _principled("Counter Top", (0.55, 0.5, 0.45), roughness=0.35),
                 Matrix.Translation((0.0, 0.0, -0.1)))
    monkey = _mesh_object(scene, "Suzanne", _monkey, _principled("Red Plastic", (0.6, 0.05, 0.04), roughness=0.25),
                          Matrix.Translation((-1.3, 0.2, 0.45)) @ Matrix.Rotation(-0.4, 4, "Z") @ Matrix.Scale(0.5, 4))
    for poly in monkey.data.polygons:
        poly.use_smooth = True
    bar = _mesh_object(scene, "Bar", _box(0.3, 0.3, 0.3), _principled("Steel", (0.7, 0.72, 0.75), roughness=0.2,
                                                                      metallic=1.0),
                       Matrix.Translation((0.2, 0.9, 0.15)))
    bevel_array_subdivision(bar, bevel_width=0.03, spacing=1.3)
    text_data = bpy.data.curves.new("SG Text", "FONT")
    text_data.body, text_data.extrude, text_data.size = "SG", 0.06, 0.8
    text_data.materials.append(_principled("Gold", (1.0, 0.77, 0.34), roughness=0.25, metallic=1.0))
    text = bpy.data.objects.new("Text", text_data)
    text.matrix_world = Matrix.Translation((0.3, -0.4, 0.0))
    scene.collection.objects.link(text)
    curve_data = bpy.data.curves.new("Pipe", "CURVE")
    curve_data.dimensions, curve_data.bevel_depth, curve_data.bevel_resolution = "3D", 0.04, 3
    spline = curve_data.splines.new("BEZIER")
    spline.bezier_points.add(2)
    for point, (x, y, z) in zip(spline.bezier_points, ((-2.0, -1.0, 0.05), (-1.2, -0.6, 0.5), (-0.3, -1.1, 0.05))):
        point.co = (x, y, z)
        point.handle_left_type = point.handle_right_type = "AUTO"
    curve_data.materials.append(_principled("Copper", (0.95, 0.64, 0.54), roughness=0.3, metallic=1.0))
    pipe = bpy.data.objects.new("Pipe", curve_data)
    scene.collection.objects.link(pipe)
    marble = _mesh_object(scene, "Marble", _sphere(0.12, 16, 8), _principled("Chrome", (0.9, 0.9, 0.9), roughness=0.15,
                                                                             metallic=1.0))
    marble.hide_render = True  # shown only through its instances
    marble.hide_viewport = True

    def marble_instance(tree):
        source = tree.nodes.new("GeometryNodeObjectInfo")
        source.inputs["Object"].default_value, source.inputs["As Instance"].default_value = marble, True
        return source.outputs["Geometry"]
    scatter = instance_on_grid("Marbles on a grid", (0.8, 0.4), marble_instance)
    grid = bpy.data.objects.new("Marble Grid", bpy.data.meshes.new("Marble Grid"))
    grid.location = (1.4, -0.9, 0.12)
    grid.modifiers.new("Scatter", "NODES").node_group = scatter
    scene.collection.objects.link(grid)
    cups = bpy.data.collections.new("Cup and Saucer")  # linked to no scene: seen only through its instances
    glaze = _principled("Blue Glaze", (0.1, 0.2, 0.7), roughness=0.2)
    for name, build, height in (("Cup", _box(0.25, 0.25, 0.35), 0.205), ("Saucer", _box(0.45, 0.45, 0.03), 0.015)):
        part = _mesh_object(scene, name, build, glaze, Matrix.Translation((0.0, 0.0, height)))
        scene.collection.objects.unlink(part)
        cups.objects.link(part)
    for k, location in enumerate(((-0.6, 0.9, 0.0), (-1.9, 0.6, 0.0))):
        cup_instance = bpy.data.objects.new(f"Cup Instance {k + 1}", None)
        cup_instance.instance_type, cup_instance.instance_collection = "COLLECTION", cups
        cup_instance.location = location
        scene.collection.objects.link(cup_instance)
    blob = bpy.data.objects.new("Blob", bpy.data.metaballs.new("Blob"))  # two merging elements
    for co, radius in (((0.0, 0.0, 0.0), 0.3), ((-0.3, 0.1, 0.05), 0.22)):
        element = blob.data.elements.new()
        element.co, element.radius = co, radius
    blob.data.resolution, blob.data.render_resolution = 0.08, 0.04
    blob.data.materials.append(_principled("Pearl", (0.85, 0.83, 0.78), roughness=0.2))
    blob.location = (1.55, 0.4, 0.25)
    scene.collection.objects.link(blob)
    pebble = _mesh_object(scene, "Pebble", _sphere(0.07, 12, 6), _principled("Obsidian", (0.04, 0.04, 0.05),
                                                                             roughness=0.15))
    pebble.hide_render = pebble.hide_viewport = True  # shown only through the particles
    scatter = _mesh_object(scene, "Pebble Scatter", _box(0.5, 0.35, 0.01), None,
                           Matrix.Translation((-0.45, -0.05, 0.07)))
    scatter.show_instancer_for_render = False
    scatter.modifiers.new("Pebbles", "PARTICLE_SYSTEM")
    particles = scatter.particle_systems[0].settings
    particles.count, particles.frame_start, particles.frame_end, particles.physics_type = 12, 1, 1, "NO"
    particles.render_type, particles.instance_object, particles.size_random = "OBJECT", pebble, 0.3
    particles.use_rotations, particles.rotation_factor_random = True, 1.0
    particles.particle_size = 1.0  # the instances' scale (its default, 0.05, is for particles drawn as points)
    dome = nurbs_sphere(scene, "Dome", 0.3, (-2.1, -0.15, 0.3))
    dome.data.materials.append(_principled("Brass", (0.9, 0.7, 0.35), roughness=0.3, metallic=1.0))
    _area_lamp(scene, 200.0, (1.0, -1.5, 2.5), 15.0)
    _world(scene, hdri="interior", strength=0.6)
    _camera(scene, (1.9, -3.0, 1.7), (-0.2, 0.0, 0.25), lens=32.0)


def nurbs_sphere(scene, name, radius, location):
    """Blender's NURBS sphere primitive in `scene` (the Python API cannot give a spline a second row of points, so the
    primitive's operator makes it)."""
    with bpy.context.temp_override(scene=scene, view_layer=scene.view_layers[0], collection=scene.collection):
        bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=radius, location=location, enter_editmode=False)
    sphere = scene.view_layers[0].objects.active  # the operator's new object
    sphere.name = sphere.data.name = name
    return sphere


# Modifier stacks per style: (asset node group, {input name: value}) after Generate Hair Curves.
_HAIR_STYLE_STACKS = {
    "straight": [("Hair Curves Noise", {"Distance": 0.002, "Scale": 4.0})],
    "wavy": [("Hair Curves Noise", {"Distance": 0.02, "Scale": 2.0, "Shape": 0.8})],
    "curly": [("Curl Hair Curves", {"Radius": 0.012, "Frequency": 6.0, "Curl Start": 0.05,
                                    "Existing Guide Map": False})],
    "clumped": [("Clump Hair Curves", {"Shape": 0.7, "Guide Distance": 0.04, "Existing Guide Map": False}),
                ("Hair Curves Noise", {"Distance": 0.005, "Scale": 6.0})],
}


def _set_modifier_inputs(modifier, values: dict, attributes: dict = ()):
    sockets = {item.name: item.identifier for item in modifier.node_group.interface.items_tree
               if item.item_type == "SOCKET" and item.in_out == "INPUT"}
    for name, value in values.items():
        modifier[sockets[name]] = value
    for name, attribute in dict(attributes).items():
        modifier[sockets[name] + "_use_attribute"] = True
        modifier[sockets[name] + "_attribute_name"] = attribute


def build_hair(scene, style="wavy"):
    if style not in HAIR_STYLES:
        raise BakeInputError(f"unknown hair style {style!r}; choose one of {', '.join(HAIR_STYLES)}")
    skin = _principled("Skin", (0.8, 0.55, 0.45), roughness=0.45)
    head = _mesh_object(scene, "Head", _sphere(0.1, 48, 24), skin,
                        Matrix.Translation((0, 0, 1.6)) @ Matrix.Diagonal((0.85, 1.0, 1.1, 1.0)))

    def scalp(bm):  # the upper back of the head, where hair grows
        _sphere(0.1, 48, 24)(bm)
        doomed = [v for v in bm.verts if v.co.z < -0.01 - 0.04 * max(0.0, -v.co.y / 0.1) and v.co.y < 0.06
                  or v.co.y < -0.06 and v.co.z < 0.05]
        bmesh.ops.delete(bm, geom=doomed, context="VERTS")

    surface = _mesh_object(scene, "Scalp", scalp, skin, head.matrix_world.copy())
    surface.hide_render = True  # only the surface the groom grows from; the head renders
    surface.parent = head
    surface.matrix_parent_inverse = head.matrix_world.inverted()
    hair_material = empty_node_material("Hair")
    nodes = hair_material.node_tree.nodes
    bsdf = nodes.new("ShaderNodeBsdfHairPrincipled")
    bsdf.parametrization = "COLOR"
    bsdf.inputs["Color"].default_value = (0.32, 0.17, 0.08, 1.0)  # light brown (the filter reads this colour)
    hair_material.node_tree.links.new(bsdf.outputs[0], nodes["Material Output"].inputs["Surface"])
    curves = bpy.data.hair_curves.new(f"Hair {style}")
    curves.materials.append(hair_material)
    curves.surface = surface
    curves.surface_uv_map = surface.data.uv_layers[0].name
    hair = bpy.data.objects.new(f"Hair {style}", curves)
    hair.matrix_world = surface.matrix_world.copy()
    scene.collection.objects.link(hair)
    generate = hair.modifiers.new("Generate Hair Curves", "NODES")
    generate.node_group = shipped_hair_node_group("Generate Hair Curves")
    _set_modifier_inputs(generate, {"Surface": surface, "Hair Length": 0.12, "Density": 30000.0, "Seed": 7,
                                    "Hair Material": hair_material},
                         {"Surface UV Map": curves.surface_uv_map})
    for group_name, values in _HAIR_STYLE_STACKS[style]:
        modifier = hair.modifiers.new(group_name, "NODES")
        modifier.node_group = shipped_hair_node_group(group_name)
        _set_modifier_inputs(modifier, values)
    profile = hair.modifiers.new("Set Hair Curve Profile", "NODES")
    profile.node_group = shipped_hair_node_group("Set Hair Curve Profile")
    _set_modifier_inputs(profile, {"Radius": 0.0004})
    key = bpy.data.lights.new("Key", type="AREA")
    key.energy, key.size = 40.0, 0.5
    key_obj = bpy.data.objects.new("Key", key)
    key_obj.matrix_world = Matrix.Translation((0.6, -0.8, 2.2)) @ Matrix.Rotation(math.radians(50), 4, "X")
    scene.collection.objects.link(key_obj)
    _world(scene, color=(0.05, 0.05, 0.06), strength=1.0)
    _camera(scene, (0.0, -0.75, 1.65), (0.0, 0.0, 1.62), lens=60.0)


_BUILDERS = {"spheres": build_spheres, "room": build_room, "courtyard": build_courtyard, "materials": build_materials,
             "geometry": build_geometry, "hair": build_hair}


def build_demo_scene(name: str):
    """A new scene holding the demo `name` (with or without the 'demo:' prefix); returns the scene."""
    key = name[len(DEMO_PREFIX):] if name.startswith(DEMO_PREFIX) else name
    base, _, variant = key.partition("-")
    if base not in _BUILDERS or (variant and (base != "hair" or variant not in HAIR_STYLES)):
        raise BakeInputError(f"unknown demo scene {name!r}; choose one of: "
                             + ", ".join(DEMO_PREFIX + n for n in DEMO_SCENES)
                             + " (hair styles: " + ", ".join(f"hair-{s}" for s in HAIR_STYLES) + ")")
    scene = _new_scene(f"SG demo {key}")
    if variant:
        _BUILDERS[base](scene, variant)
    else:
        _BUILDERS[base](scene)
    return scene


STABILITY_VARIANTS = ("roughness_min", "roughness_one", "hdr_sun", "all_black", "scale_1e4", "scale_1e-3")


def build_stability_variant(variant: str):
    """`spheres` pushed to an extreme (DESIGN section 7): every sphere at roughness 0 (the floor ROUGHNESS_MIN
    applies), two spheres at roughness 1, one arc emitting 1e5, no light at all, or the scene scaled by 1e4 / 1e-3.
    Returns (scene, scale factor)."""
    if variant not in STABILITY_VARIANTS:
        raise BakeInputError(f"unknown stability variant {variant!r}; choose one of {', '.join(STABILITY_VARIANTS)}")
    scene = build_demo_scene("spheres")

    def bsdfs(prefix):
        return [o.material_slots[0].material.node_tree.nodes["Principled BSDF"] for o in scene.objects
                if o.name.startswith(prefix)]

    scale = 1.0
    if variant == "roughness_min":
        for bsdf in bsdfs("Sphere"):
            bsdf.inputs["Roughness"].default_value = 0.0
    elif variant == "roughness_one":
        for bsdf in bsdfs("Sphere")[:2]:
            bsdf.inputs["Roughness"].default_value = 1.0
    elif variant == "hdr_sun":
        bsdfs("Arc")[0].inputs["Emission Strength"].default_value = 1e5
    elif variant == "all_black":
        for bsdf in bsdfs("Arc"):
            bsdf.inputs["Emission Strength"].default_value = 0.0
    else:
        scale = float(variant.split("_")[1])
        for obj in scene.objects:
            if obj.parent is None:  # matrix_basis: matrix_world of a camera placed by location is not yet evaluated
                obj.matrix_basis = Matrix.Scale(scale, 4) @ obj.matrix_basis
            if obj.type == "CAMERA":  # the camera must still see the scaled scene
                obj.data.clip_start, obj.data.clip_end = obj.data.clip_start * scale, obj.data.clip_end * scale
    return scene, scale
