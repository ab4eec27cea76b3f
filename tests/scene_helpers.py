"""Small real scenes for tests (bpy as a module): meshes from bmesh, Principled materials, hashes."""
import hashlib
import re

import bpy  # noqa: I001  (bmesh exists only once bpy is imported)
import bmesh
import numpy as np

from sg_lightfield.blender_addon.scene_analysis import enable_nodes


def base_name(name: str) -> str:
    """'Floor.002' -> 'Floor': demo scenes built twice in one session get Blender's numeric suffixes."""
    return re.sub(r"\.\d{3}$", "", name)


def material(name, roughness, metallic=0.0):
    mat = bpy.data.materials.new(name)
    enable_nodes(mat)
    bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    return mat


def mesh_object(name, build, mat=None, uv_map=None, mesh=None):
    """A new object; `build(bm)` fills a fresh mesh unless an existing `mesh` is shared."""
    if mesh is None:
        mesh = bpy.data.meshes.new(name)
        bm = bmesh.new()
        if uv_map:
            bm.loops.layers.uv.new(uv_map)
        build(bm)
        bm.to_mesh(mesh)
        bm.free()
        if mat is not None:
            mesh.materials.append(mat)
    return bpy.data.objects.new(name, mesh)


def scene_with(*objects, name="test scene"):
    scene = bpy.data.scenes.new(name)
    for obj in objects:
        scene.collection.objects.link(obj)
    return scene


def uniform_world(scene, color, name="test world"):
    """Give `scene` a new world of one background colour (RGB)."""
    world = bpy.data.worlds.new(name)
    enable_nodes(world)
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*color, 1)
    scene.world = world
    return world


def lit_ortho_scene(*objects, name, lamp_energy, lamp_size, lamp_location, world_color, ortho_scale, camera_height,
                    resolution):
    """`objects` under one square area lamp and a one-colour world, seen from above by an orthographic camera at
    (0, 0, camera_height) rendering resolution x resolution 32-bit EXRs with Cycles, no denoising."""
    scene = scene_with(*objects, name=name)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "AREA"))
    lamp.data.energy, lamp.data.size = lamp_energy, lamp_size
    lamp.location = lamp_location
    scene.collection.objects.link(lamp)
    world = bpy.data.worlds.new(f"{name} world")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*world_color, 1.0)
    scene.world = world
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", ortho_scale
    camera.location = (0, 0, camera_height)
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.render.resolution_x = scene.render.resolution_y = resolution
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    scene.cycles.use_denoising = False
    return scene


def cube(size=1.0):
    return lambda bm: bmesh.ops.create_cube(bm, size=size, calc_uvs=True)


def uv_sphere(radius=1.0, segments=24, rings=12):
    return lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=radius,
                                                calc_uvs=True)


def mesh_fingerprint(mesh) -> str:
    """Hash of what a user owns in a mesh: vertices, faces, every UV layer and the active flags."""
    h = hashlib.sha256()
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    h.update(co.tobytes())
    loops = np.empty(len(mesh.loops), np.int64)
    mesh.loops.foreach_get("vertex_index", loops)
    h.update(loops.tobytes())
    for layer in mesh.uv_layers:
        uv = np.empty(len(mesh.loops) * 2, np.float32)
        layer.uv.foreach_get("vector", uv)
        h.update(layer.name.encode() + bytes([layer.active, layer.active_render]) + uv.tobytes())
    h.update(str(sorted(mesh.keys())).encode())
    return h.hexdigest()


def object_fingerprint(obj) -> str:
    """Hash of what a user owns in an object: its modifiers (type, order and every setting), custom properties,
    material slots, visibility, display and children, and its data (mesh_fingerprint for meshes; curve, surface,
    text and metaball settings otherwise)."""
    h = hashlib.sha256()
    h.update(repr((obj.hide_render, obj.hide_viewport, obj.hide_select, obj.display_type,
                   sorted(child.name for child in obj.children))).encode())
    for modifier in obj.modifiers:
        settings = {p.identifier: getattr(modifier, p.identifier) for p in modifier.bl_rna.properties
                    if not p.is_readonly and p.type in {"BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"}}
        h.update(repr((modifier.name, modifier.type, sorted((k, repr(v)) for k, v in settings.items()))).encode())
    h.update(str(sorted(obj.keys())).encode())
    h.update(repr([(s.link, s.material.name if s.material else None) for s in obj.material_slots]).encode())
    if obj.type == "MESH":
        h.update(mesh_fingerprint(obj.data).encode())
    elif obj.data is not None:
        h.update(repr(sorted((p.identifier, repr(getattr(obj.data, p.identifier))) for p in obj.data.bl_rna.properties
                             if not p.is_readonly and p.type in {"BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"})).encode())
        h.update(str(sorted(obj.data.keys())).encode())
    return h.hexdigest()
