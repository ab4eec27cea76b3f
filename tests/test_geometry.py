"""Real geometry (bpy as a module): modifier stacks stay live, text and curves bake as their evaluated meshes,
metaballs and NURBS surfaces through mesh stand-ins, small objects and every instance get texels of their own
(particle, vertex, face, nested and node-made instances as object copies when asked), and what is not baked is named
with a reason."""
import json
import math
import re

import bpy  # noqa: I001  (bmesh exists only once bpy is imported)
import bmesh
import numpy as np
import pytest

from sg_lightfield.blender_addon import lightmap_modifier
from sg_lightfield.blender_addon.apply import remove_bake
from sg_lightfield.blender_addon.capture import LIGHTMAP_LAYER, capture, remove_lightmap_uvs
from sg_lightfield.blender_addon.demo_scenes import bevel_array_subdivision, instance_on_grid, nurbs_sphere
from sg_lightfield.blender_addon.scene_analysis import active_scene, build_plan, loop_triangle_arrays
from sg_lightfield.headless.bake import stage_summary
from sg_lightfield.bake_directory.bake_plan import BakeInputError, BakeSettings
from sg_lightfield.bake_directory.texel_maps import channels, read_texel_maps
from tests.scene_helpers import base_name, cube, material, mesh_object, object_fingerprint, scene_with, uv_sphere

DRAFT = BakeSettings.from_preset("draft")


def _texels_of(atlas, info, name):
    object_id = next(o["id"] for o in info["objects"] if base_name(o["name"]) == name)
    return (channels(atlas, "object_id") == object_id) & (channels(atlas, "valid") > 0)


def _evaluated_uv(obj):
    with active_scene(obj.users_scene[0]) as depsgraph:
        depsgraph.update()
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            loops, _, _, coords = loop_triangle_arrays(mesh)
            uv = np.empty(len(mesh.loops) * 2, np.float32)
            mesh.uv_layers[LIGHTMAP_LAYER].uv.foreach_get("vector", uv)
            corner_vertex = np.empty(len(mesh.loops), np.int64)
            mesh.loops.foreach_get("vertex_index", corner_vertex)
            return uv.reshape(-1, 2)[loops], coords[corner_vertex[loops]]
        finally:
            evaluated.to_mesh_clear()


def _own_texels_overlap(uv_triangles, width, height):
    from sg_lightfield.bake_directory.texel_raster import centre_overlap_count

    px = np.stack([uv_triangles[..., 0] * width, (1 - uv_triangles[..., 1]) * height], axis=-1)
    claimed = centre_overlap_count(px, width, height)
    return np.count_nonzero(claimed > 1), np.count_nonzero(claimed)


def test_a_small_smooth_monkey_at_low_density_gets_texels_of_its_own(tmp_path):
    """Suzanne (no modifiers) at Draft's 4 texels/m: xatlas splits some of her quads across charts, which one UV per
    corner of her mesh cannot hold; the SG Lightmap UV modifier gives her triangulated surface the layout, every
    chart keeps its own texels and her mesh data is not touched."""
    def monkey(bm):
        bmesh.ops.create_monkey(bm)
    suzanne = mesh_object("Suzanne", monkey, material("red plastic", 0.25))
    for polygon in suzanne.data.polygons:
        polygon.use_smooth = True
    suzanne.scale = (0.4, 0.4, 0.4)
    scene = scene_with(suzanne)
    before = object_fingerprint(suzanne)
    ours = {kind: {b.name for b in getattr(bpy.data, kind) if b.get(lightmap_modifier.OWNED_KEY)}
            for kind in ("objects", "meshes", "node_groups")}  # other tests' scenes may still hold theirs
    plan = build_plan(scene, DRAFT)
    result = capture(scene, plan, tmp_path)
    assert not result.warnings, result.warnings
    tile = next(o for o in result.objects if base_name(o["name"]) == "Suzanne")
    assert tile["texels"] > 0
    assert LIGHTMAP_LAYER not in suzanne.data.uv_layers  # the layout lives on the evaluated geometry only
    uv, _ = _evaluated_uv(suzanne)
    shared, covered = _own_texels_overlap(uv, tile["pixel_rect"][2], tile["pixel_rect"][3])
    assert covered > 0 and shared / covered <= 0.002, (shared, covered)
    remove_lightmap_uvs(scene)
    assert object_fingerprint(suzanne) == before
    assert {kind: {b.name for b in getattr(bpy.data, kind) if b.get(lightmap_modifier.OWNED_KEY)}
            for kind in ours} == ours


def test_the_layout_follows_a_live_modifier_stack_and_a_textured_material_is_measured_on_it(tmp_path):
    """A bar with Bevel + Array + Subdivision (viewport level 1, render level 2) and a Noise-textured roughness: each
    array copy gets texels; the evaluated UV equals the carrier's layout at render levels and, at the viewport's
    other topology, stays within a texel of it (the modifier's nearest-surface fallback); the probe bakes the textured
    roughness through a temporary mesh of the evaluated surface; Remove leaves the object as it was."""
    steel = material("steel", 0.3, metallic=1.0)
    tree = steel.node_tree
    noise = tree.nodes.new("ShaderNodeTexNoise")
    ramp = tree.nodes.new("ShaderNodeMapRange")
    ramp.inputs["To Min"].default_value, ramp.inputs["To Max"].default_value = 0.1, 0.4
    tree.links.new(noise.outputs["Fac"], ramp.inputs["Value"])
    tree.links.new(ramp.outputs["Result"], tree.nodes["Principled BSDF"].inputs["Roughness"])
    bar = mesh_object("Bar", cube(0.5), steel)
    _, _, subdivision = bevel_array_subdivision(bar, bevel_width=0.05, spacing=1.5)
    scene = scene_with(bar)
    before = object_fingerprint(bar)
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=16.0))
    bar_plan = next(o for o in plan.objects if base_name(o.name) == "Bar")
    assert bar_plan.bake_lightfield and bar_plan.geometry == "mesh + Bevel, Array, Subdivision"
    result = capture(scene, plan, tmp_path)
    assert subdivision.levels == 1
    atlas, info = read_texel_maps(tmp_path)
    mine = _texels_of(atlas, info, "Bar")
    x = channels(atlas, "P.X")[mine]
    copies = np.bincount(np.clip(np.round(x / 0.75).astype(int), 0, 3), minlength=4)  # array copies 0.75 m apart
    assert np.all(copies > 0.15 * copies.sum()), copies
    roughness = channels(atlas, "roughness")[mine]
    assert 0.09 <= roughness.min() and roughness.max() <= 0.41 and roughness.std() > 0.01
    measured = next(m for m in info["materials"] if base_name(m["name"]) == "steel")["measured"]
    assert measured["texels"] == int(mine.sum())
    assert result.surface_probe["objects"] == [bar.name]

    subdivision.levels = 2  # the render topology: UVs by corner index, exactly the carrier's
    carrier = lightmap_modifier.carrier_of(bar).data
    exact = np.empty(len(carrier.loops) * 2, np.float32)
    carrier.uv_layers[LIGHTMAP_LAYER].uv.foreach_get("vector", exact)
    uv, _ = _evaluated_uv(bar)
    loops, _, _, _ = loop_triangle_arrays(carrier)
    np.testing.assert_allclose(uv, exact.reshape(-1, 2)[loops], atol=1e-6)
    subdivision.levels = 1  # the viewport's coarser topology: every triangle's UV lies on the layout
    coarse_uv, _ = _evaluated_uv(bar)
    width, height = next(o for o in result.objects if base_name(o["name"]) == "Bar")["pixel_rect"][2:]
    texel = 1.0 / min(width, height)
    charts = exact.reshape(-1, 2)[loops]
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(charts.reshape(-1, 2)).query(coarse_uv.reshape(-1, 2))
    assert np.median(distance) < texel, (np.median(distance), texel)
    remove_lightmap_uvs(scene)
    assert object_fingerprint(bar) == before


def _instances_scene():
    """A floor; glossy spheres instanced by Geometry Nodes on a grid (their object hidden); two instances of a
    collection of a glossy rock and stone that no scene links."""
    chrome = material("chrome", 0.1, metallic=1.0)
    floor = mesh_object("Floor", cube(4.0), material("tiles", 0.3))
    floor.scale.z = 0.01
    floor.location.z = -0.5
    sphere = mesh_object("Sphere Source", uv_sphere(0.3), chrome)
    sphere.hide_render = True

    def object_info(tree):
        info = tree.nodes.new("GeometryNodeObjectInfo")
        info.inputs["Object"].default_value, info.inputs["As Instance"].default_value = sphere, True
        return info.outputs["Geometry"]
    grid = bpy.data.objects.new("Grid", bpy.data.meshes.new("Grid"))
    grid.modifiers.new("Scatter", "NODES").node_group = instance_on_grid("Scatter spheres", (3.0, 2.0), object_info)
    rocks = bpy.data.collections.new("Rocks")  # two objects, instanced twice
    rock, stone = mesh_object("Rock", cube(0.4), chrome), mesh_object("Stone", uv_sphere(0.2), chrome)
    stone.location = (0.5, 0.0, 0.0)
    rocks.objects.link(rock)
    rocks.objects.link(stone)
    empties = []
    for k, x in enumerate((-1.0, 0.8)):
        empty = bpy.data.objects.new(f"Rock Instance {k + 1}", None)
        empty.instance_type, empty.instance_collection = "COLLECTION", rocks
        empty.location = (x, 1.6, 0.0)
        empties.append(empty)
    return scene_with(floor, sphere, grid, *empties, name="instances test"), sphere, grid, empties, (rock, stone)


def test_every_instance_gets_texels_of_its_own_and_its_shading_finds_them(tmp_path):
    """Six geometry-node instances and two instances of a collection of two objects: each instance is in the plan with
    its texels, gets its own atlas tile whose texels lie on it, and a material reading the atlas UV as the baked copy
    does (lightmap layer, Instancer attributes) lands inside that instance's tile in Cycles and in EEVEE. Remove SG
    Bake leaves the instancers, the instanced objects and their meshes as they were."""
    from sg_lightfield.blender_addon.apply import _lightmap_uv

    scene, sphere, grid, empties, members = _instances_scene()
    owners = [grid, sphere, *empties, *members]
    before = [object_fingerprint(o) for o in owners]
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=8.0))
    instances = [o for o in plan.objects if o.instancer]
    assert [o.name for o in instances if o.instancer == grid.name] == [f"{grid.name}: {sphere.name} #{k}"
                                                                       for k in range(1, 7)]
    for empty in empties:
        mine = [o for o in instances if o.instancer == empty.name]
        assert sorted(o.source for o in mine) == sorted(m.name for m in members), mine
    assert all(o.bake_lightfield and o.texels > 0 for o in instances)
    assert "each baked with texels of its own" in next(o for o in plan.objects if o.name == grid.name).reason
    assert not any("not baked" in w for w in plan.warnings), plan.warnings
    result = capture(scene, plan, tmp_path)
    atlas, info = read_texel_maps(tmp_path)
    tiles = {o["name"]: o for o in info["objects"]}
    centres = []
    for entry in instances:
        mine = _texels_of(atlas, info, entry.name)
        p = channels(atlas, "P.X", 3)[mine]
        assert mine.sum() > 0 and np.ptp(p, axis=0).max() < 0.9  # one sphere or rock, not several
        centres.append(p.mean(axis=0))
    assert len({tuple(np.round(c, 1)) for c in centres}) == len(instances)  # each at a place of its own

    emit = bpy.data.materials.new("atlas uv")
    tree = emit.node_tree
    emission = tree.nodes.new("ShaderNodeEmission")
    tree.links.new(_lightmap_uv(tree), emission.inputs["Color"])
    tree.links.new(emission.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    chrome = sphere.material_slots[0].material
    for obj in (sphere, *members):
        obj.material_slots[0].material = emit
    camera = bpy.data.objects.new("Top", bpy.data.cameras.new("Top"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 5.0
    camera.location = (0.0, 0.3, 5.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.resolution_x = scene.render.resolution_y = 100
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    scene.view_settings.view_transform = "Standard"
    scene.cycles.samples, scene.cycles.use_denoising = 4, False
    next(o for o in scene.objects if base_name(o.name) == "Floor").hide_render = True
    from sg_lightfield.bake_directory.exr_io import read_exr

    for engine in ("CYCLES", "BLENDER_EEVEE"):
        scene.render.engine = engine
        scene.render.filepath = str(tmp_path / f"atlas_uv_{engine}.exr")
        with active_scene(scene):
            bpy.ops.render.render(write_still=True, scene=scene.name)
        image = read_exr(scene.render.filepath, channels=["R", "G", "B"])[0].astype(np.float64)
        for entry, centre in zip(instances, centres):
            column = int(round(50 + 20 * centre[0]))
            row = int(round(50 - 20 * (centre[1] - 0.3)))
            u, v = image[row, column, :2]
            x, y, w, h = tiles[entry.name]["pixel_rect"]
            tile_u0, tile_v1 = x / result.atlas_width, 1 - y / result.atlas_height
            assert tile_u0 <= u <= tile_u0 + w / result.atlas_width, (engine, entry.name, u, x, w)
            assert tile_v1 - h / result.atlas_height <= v <= tile_v1, (engine, entry.name, v, y, h)
    remove_lightmap_uvs(scene)
    for obj in (sphere, *members):
        obj.material_slots[0].material = chrome
    next(o for o in scene.objects if base_name(o.name) == "Floor").hide_render = False
    assert [object_fingerprint(o) for o in owners] == before


def _unsupported_scene():
    """Instances of node-made geometry, particle instances and a curve with no bevel beside a floor; a metaball and a
    NURBS surface, which bake through stand-ins."""
    chrome = material("chrome", 0.1, metallic=1.0)
    floor = mesh_object("Floor", cube(4.0), material("tiles", 0.3))
    floor.scale.z = 0.01

    def node_sphere(tree):
        sphere = tree.nodes.new("GeometryNodeMeshUVSphere")
        tree.links.new(sphere.outputs["Mesh"], (setter := tree.nodes.new("GeometryNodeSetMaterial")).inputs[0])
        setter.inputs["Material"].default_value = chrome
        return setter.outputs[0]
    grid = bpy.data.objects.new("Node Spheres", bpy.data.meshes.new("Node Spheres"))
    grid.modifiers.new("Scatter", "NODES").node_group = instance_on_grid("Scatter node spheres", (3.0, 2.0), node_sphere)
    pebble = mesh_object("Pebble", uv_sphere(0.05), chrome)
    pebble.hide_render = True
    emitter = mesh_object("Emitter", cube(1.0))
    emitter.location = (0.0, 0.0, 2.0)
    blob = bpy.data.objects.new("Blob", bpy.data.metaballs.new("Blob"))
    blob.data.elements.new()
    blob.data.materials.append(chrome)
    wire = bpy.data.objects.new("Wire", bpy.data.curves.new("Wire", "CURVE"))
    wire.data.splines.new("POLY").points.add(2)
    wire.data.materials.append(chrome)
    scene = scene_with(floor, grid, pebble, emitter, blob, wire, name="unsupported test")
    emitter.modifiers.new("Pebbles", "PARTICLE_SYSTEM")
    particles = emitter.particle_systems[0].settings
    particles.count, particles.render_type, particles.instance_object = 20, "OBJECT", pebble
    particles.frame_start = particles.frame_end = 1  # all born on the first frame
    nurbs_sphere(scene, "Dome", 0.4, (1.5, 1.5, 0.5)).data.materials.append(chrome)
    return scene


def test_what_cannot_be_baked_is_named_with_its_reason():
    scene = _unsupported_scene()
    plan = build_plan(scene, DRAFT)
    by_name = {base_name(o.name): o for o in plan.objects}
    assert by_name["Floor"].bake_lightfield and by_name["Floor"].texels > 0
    nodes = by_name["Node Spheres"]
    assert not nodes.bake_lightfield and "6 geometry nodes instances of generated geometry" in nodes.reason
    assert "left to the renderer" in nodes.reason and "made inside the node tree" in nodes.reason
    emitter = by_name["Emitter"]
    assert "20 particle instances of Pebble" in emitter.geometry and "left to the renderer" in emitter.reason
    for blob_or_nurbs in (by_name["Blob"], next(o for o in plan.objects if scene.objects[o.name].type == "SURFACE")):
        assert blob_or_nurbs.bake_lightfield and blob_or_nurbs.texels > 0, blob_or_nurbs
        assert "through a mesh stand-in" in blob_or_nurbs.reason
    assert "no surface: a curve without bevel" in by_name["Wire"].reason
    assert any("instances of glossy objects are not baked" in w and "Pebble" in w for w in plan.warnings)
    assert "Emitter" not in {base_name(o.name) for o in plan.baked_objects}  # no material: left alone
    assert not any(o.instancer for o in plan.objects)
    decisions = "\n".join(plan.decisions())
    for name in ("Node Spheres", "Emitter", "Blob", "Wire"):
        assert any(line.startswith(name) for line in decisions.splitlines()), name
    matte = material("matte", 0.9)
    for name in ("Floor", "Blob", "Dome"):
        next(o for o in scene.objects if base_name(o.name) == name).material_slots[0].material = matte
    with pytest.raises(BakeInputError, match="instances of glossy objects are not baked.*Pebble"):
        build_plan(scene, BakeSettings.from_preset("draft", rough_materials="renderer"))


def test_a_bake_without_glossy_materials_says_so_instead_of_a_loss():
    plan = build_plan(scene_with(mesh_object("Rough", cube(1.0), material("rough", 0.9))), DRAFT)
    line, _ = stage_summary("train", {"metrics": {}}, plan)
    assert "no glossy material" in line and "nan" not in line.lower()


@pytest.mark.slow
def test_the_geometry_demo_bakes_every_class_and_remove_restores_every_object(tmp_path):
    """demo:geometry end to end at small settings: the monkey, the modifier stack, the text, the curve, the metaball,
    the NURBS surface and the particles (as object copies) are each in the plan with texels, the bake finishes,
    EEVEE's FLIP per material is finite and in the report, and Remove SG Bake leaves every object (modifiers, mesh,
    UV layers, slots, visibility) and the file's datablocks as they were."""
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.evaluate import evaluate_stage
    from sg_lightfield.blender_addon.pipeline import BakeJob

    scene = build_demo_scene("geometry")
    owners = [*scene.objects, *(o for o in bpy.data.objects if base_name(o.name) in ("Cup", "Saucer"))]
    before = {o.name: object_fingerprint(o) for o in owners}
    datablocks = {kind: set(getattr(bpy.data, kind).keys()) for kind in ("objects", "meshes", "node_groups",
                                                                          "collections")}
    settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=8, sg_count=4, training_budget_s=4.0,
                                        lobe_refit_steps=20, instance_copies=True)
    job = BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train", "apply"))

    def plain(name):  # earlier tests' objects of the same names give these numeric suffixes
        return re.sub(r"\.\d{3}", "", name)
    by_name = {plain(o.name): o for o in job.plan.objects}
    expected = {"Suzanne": "mesh", "Bar": "mesh + Bevel, Array, Subdivision", "Text": "text", "Pipe": "curve",
                "Marble Grid: Marble #1": "geometry nodes instance 1 of 6, of 'Marble' on 'Marble Grid'",
                "Blob": "metaball", "Dome": "NURBS surface",
                "Pebble Scatter: Pebble #1": "particle instance 1 of 12, of 'Pebble' on 'Pebble Scatter', as an object "
                                             "copy"}
    cups = [o for o in job.plan.objects if base_name(o.instancer).startswith("Cup Instance")]
    assert sorted(base_name(o.source) for o in cups) == ["Cup", "Cup", "Saucer", "Saucer"]
    assert all(o.bake_lightfield and o.texels > 0 for o in cups)
    for name, geometry in expected.items():
        assert by_name[name].bake_lightfield and by_name[name].texels > 0 and plain(by_name[name].geometry) == geometry
    job.run()
    tiles = {plain(o["name"]): o["texels"] for o in job.results["capture"].objects}
    assert all(tiles[name] > 0 for name in expected), tiles
    errors = evaluate_stage(scene, job.plan, tmp_path, views=1, resolution=(96, 54), reference_samples=16,
                            eevee_without_bake=False)  # EEVEE alone: the materials tests compare with it
    eevee = errors["eevee"]
    assert "error" not in eevee and math.isfinite(errors["flip"]) and 0 < eevee["flip"] < 1
    flips = {base_name(k): v["flip"] for k, v in eevee["flip_by_material"].items()}
    for name in ("Red Plastic", "Steel", "Gold", "Copper", "Chrome", "Blue Glaze", "Pearl", "Brass", "Obsidian"):
        assert math.isfinite(flips[name]) and 0 <= flips[name] < 1, flips
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["errors"]["eevee"]["flip"] == eevee["flip"]
    remove_bake(scene)
    assert {o.name: object_fingerprint(o) for o in owners} == before
    for kind, before_names in datablocks.items():
        after_names = set(getattr(bpy.data, kind).keys())
        assert after_names - before_names == set(), (kind, after_names - before_names)  # nothing of the bake stays
        # what went is only the bake's own (earlier tests' unused copies, cleaned up on the way), never the user's
        assert all(name.startswith("SG ") for name in before_names - after_names), (kind, before_names - after_names)


def _solidify(obj):
    obj.modifiers.new("Solidify", "SOLIDIFY").thickness = 0.2


def _boolean(obj):
    cutter = mesh_object("Cutter", uv_sphere(0.6))
    cutter.location = (0.5, 0.5, 0.5)
    cutter.hide_render = cutter.hide_viewport = True
    obj.users_scene[0].collection.objects.link(cutter)
    boolean = obj.modifiers.new("Boolean", "BOOLEAN")
    boolean.operation, boolean.object = "DIFFERENCE", cutter


def _geometry_nodes(obj):
    tree = bpy.data.node_groups.new("Subdivide and twist", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    subdivide = tree.nodes.new("GeometryNodeSubdivideMesh")
    subdivide.inputs["Level"].default_value = 2
    tree.links.new(tree.nodes.new("NodeGroupInput").outputs[0], subdivide.inputs["Mesh"])
    offset = tree.nodes.new("GeometryNodeSetPosition")
    noise = tree.nodes.new("ShaderNodeTexNoise")
    scale = tree.nodes.new("ShaderNodeVectorMath")
    scale.operation, scale.inputs["Scale"].default_value = "SCALE", 0.1
    tree.links.new(noise.outputs["Color"], scale.inputs[0])
    tree.links.new(scale.outputs["Vector"], offset.inputs["Offset"])
    tree.links.new(subdivide.outputs[0], offset.inputs["Geometry"])
    tree.links.new(offset.outputs[0], tree.nodes.new("NodeGroupOutput").inputs[0])
    obj.modifiers.new("Twist", "NODES").node_group = tree


@pytest.mark.parametrize("stack", [_solidify, _boolean, _geometry_nodes], ids=["solidify", "boolean", "geometry nodes"])
def test_solidify_boolean_and_geometry_nodes_stacks_get_a_layout_of_their_own(tmp_path, stack):
    box = mesh_object("Box", cube(1.0), material("glossy", 0.2))
    scene = scene_with(box)
    stack(box)
    before = object_fingerprint(box)
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=16.0))
    result = capture(scene, plan, tmp_path)
    assert not result.warnings, result.warnings
    tile = next(o for o in result.objects if base_name(o["name"]) == "Box")
    area = next(o.area_m2 for o in plan.objects if base_name(o.name) == "Box")
    assert 0.5 * area * 16.0**2 <= tile["texels"] <= 3.0 * area * 16.0**2, (tile["texels"], area)
    uv, _ = _evaluated_uv(box)
    shared, covered = _own_texels_overlap(uv, tile["pixel_rect"][2], tile["pixel_rect"][3])
    assert shared / covered <= 0.002, (shared, covered)
    remove_lightmap_uvs(scene)
    assert object_fingerprint(box) == before


def _lightmap_state(scene) -> dict:
    """Per object a capture may change: its tile properties and the data of its modifier's carrier and instance
    tiles (positions, UVs, tile attributes)."""
    from sg_lightfield.blender_addon.capture import TILE_KEYS, lightmap_owners

    state = {}
    for obj in lightmap_owners(scene):
        entry = [repr({k: [round(v, 9) for v in obj[k]] for k in TILE_KEYS if k in obj})]
        for helper in (lightmap_modifier.carrier_of(obj), lightmap_modifier.instance_tiles_of(obj)):
            if helper is None:
                entry.append(None)
                continue
            values = []
            for attribute in helper.data.attributes:
                if attribute.data_type in ("FLOAT_VECTOR", "FLOAT2"):
                    data = np.empty(len(attribute.data) * (3 if attribute.data_type == "FLOAT_VECTOR" else 2), np.float32)
                    attribute.data.foreach_get("vector", data)
                    values.append((attribute.name, data.round(6).tobytes()))
            entry.append(sorted(values))
        state[obj.name] = entry
    return state


def test_cancelling_a_rebake_puts_back_the_carriers_and_instance_tiles(tmp_path):
    """A scene with a modifier stack and geometry-node and collection instances, captured at one density; a second
    job at another density is cancelled after its capture: every carrier, instance tile and tile property is back."""
    from sg_lightfield.blender_addon.pipeline import BakeJob

    scene, *_ = _instances_scene()
    bar = mesh_object("Bar", cube(0.5), material("steel", 0.3, metallic=1.0))
    bevel_array_subdivision(bar, bevel_width=0.05, spacing=1.5)
    bar.location = (0.0, -1.5, 0.0)
    scene.collection.objects.link(bar)
    small = dict(lightfield_resolution=8, samples=2, sg_count=2, training_budget_s=1.0)
    BakeJob(scene, BakeSettings.from_preset("draft", texel_density=4.0, **small), tmp_path / "a",
            stages=("capture",)).run()
    captured = _lightmap_state(scene)
    job = BakeJob(scene, BakeSettings.from_preset("draft", texel_density=9.0, **small), tmp_path / "b",
                  stages=("capture", "render"))
    while job.step()[0] != "render":
        pass
    assert _lightmap_state(scene) != captured
    job.cancel()
    assert _lightmap_state(scene) == captured
    remove_lightmap_uvs(scene)
    assert not any(lightmap_modifier.lightmap_modifier(o) for o in scene.objects)


def test_a_metaball_and_a_nurbs_surface_bake_through_live_stand_ins_that_remove_takes_away(tmp_path):
    """The capture gives a metaball and a NURBS surface each a mesh stand-in whose surface is theirs (area within
    2 %), with texels of its own, the source's materials in object-linked slots and the source hidden in renders and
    drawn as wire; moving an element moves the stand-in's surface (it stays live); Remove SG Bake deletes the
    stand-ins and gives each source its own settings back."""
    from sg_lightfield.blender_addon import stand_ins
    from sg_lightfield.blender_addon.scene_analysis import _world_area

    pearl, brass = material("pearl", 0.2), material("brass", 0.3, metallic=1.0)
    floor = mesh_object("Floor", cube(4.0), material("tiles", 0.3))
    floor.scale.z = 0.01
    blob = bpy.data.objects.new("Blob", bpy.data.metaballs.new("Blob"))
    for co in ((0.0, 0.0, 0.5), (0.4, 0.0, 0.5)):
        element = blob.data.elements.new()
        element.co, element.radius = co, 0.4
    blob.data.materials.append(pearl)
    blob.data.resolution = 0.1  # the viewport's polygons too (the test reads the viewport's evaluation)
    scene = scene_with(floor, blob, name="stand-in test")
    dome = nurbs_sphere(scene, "Dome", 0.4, (1.5, 1.0, 0.5))
    dome.data.materials.append(brass)
    owners = (floor, blob, dome)
    before = {o.name: object_fingerprint(o) for o in owners}
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=16.0))
    with active_scene(scene) as depsgraph:
        source_areas = {o.name: _world_area(o, depsgraph) for o in (blob, dome)}
    assert min(source_areas.values()) > 1.0, source_areas
    result = capture(scene, plan, tmp_path)
    atlas, info = read_texel_maps(tmp_path)
    for source, mat in ((blob, pearl), (dome, brass)):
        stand_in = stand_ins.stand_in_of(source)
        assert stand_in is not None and stand_in.type == "MESH" and stand_in.name in scene.objects
        assert not source.visible_camera and not source.visible_shadow and source.display_type == "WIRE"
        assert [(s.link, s.material) for s in stand_in.material_slots] == [("OBJECT", mat)]
        with active_scene(scene) as depsgraph:
            assert _world_area(stand_in, depsgraph) == pytest.approx(source_areas[source.name], rel=0.02)
        assert _texels_of(atlas, info, base_name(source.name)).sum() > 20
        assert next(o for o in result.objects if o["name"] == source.name)["texels"] > 20
    with active_scene(scene) as depsgraph:
        depsgraph.update()
        centre = np.mean(_evaluated_uv(stand_ins.stand_in_of(blob))[1].reshape(-1, 3), axis=0)
        blob.data.elements[1].co.x = 0.8  # the user edits the metaball: its stand-in follows
        depsgraph.update()
        moved = np.mean(_evaluated_uv(stand_ins.stand_in_of(blob))[1].reshape(-1, 3), axis=0)
    assert moved[0] - centre[0] > 0.1, (centre, moved)
    blob.data.elements[1].co.x = 0.4
    blob["sglf_texel_scale"] = 2.0  # the user's texel scale on the metaball reaches its stand-in's tile
    scaled = capture(scene, plan, tmp_path / "scaled")
    texels = {o["name"]: o["texels"] for o in scaled.objects}
    assert texels[blob.name] > 3 * next(o["texels"] for o in result.objects if o["name"] == blob.name), texels
    del blob["sglf_texel_scale"]
    remove_bake(scene)
    assert not any(stand_ins.is_stand_in(o) for o in bpy.data.objects)
    assert not any(g.get(stand_ins.GROUP_KEY) for g in bpy.data.node_groups)
    assert {o.name: object_fingerprint(o) for o in owners} == before

    from sg_lightfield.blender_addon.pipeline import BakeJob  # a bake cancelled after its capture: the same

    job = BakeJob(scene, BakeSettings.from_preset("draft", texel_density=16.0), tmp_path / "cancelled",
                  stages=("capture", "render"))
    while job.step()[0] == "capture":
        pass
    assert stand_ins.stand_in_of(blob) is not None
    job.cancel()
    assert not any(stand_ins.is_stand_in(o) for o in bpy.data.objects)
    assert {o.name: object_fingerprint(o) for o in owners} == before


def _copies_scene():
    """A floor; 20 glossy pebbles scattered by a particle system on a hidden emitter; a glossy stud on each of a
    holder mesh's 8 vertices (vertex instancing); a table set: a collection instance of a plate and of a collection
    instance of a cup and a point lamp (nested); six spheres made and instanced by Geometry Nodes."""
    chrome, brass = material("chrome", 0.1, metallic=1.0), material("brass", 0.3, metallic=1.0)
    floor = mesh_object("Floor", cube(4.0), material("tiles", 0.3))
    floor.scale.z = 0.01
    pebble = mesh_object("Pebble", uv_sphere(0.08), chrome)
    pebble.hide_render = True
    emitter = mesh_object("Emitter", cube(1.0))
    emitter.location = (0.0, 0.0, 1.0)
    emitter.show_instancer_for_render = False
    holder = mesh_object("Holder", cube(0.6))
    holder.location = (1.5, 1.5, 0.6)
    stud = mesh_object("Stud", cube(0.08), brass)
    stud.parent = holder
    holder.instance_type = "VERTS"
    cup = mesh_object("Cup", cube(0.2), brass)  # a table set: a collection instance inside a collection instance
    candle = bpy.data.objects.new("Candle", bpy.data.lights.new("Candle", "POINT"))
    candle.location = (0.0, 0.0, 0.3)
    inner, outer = bpy.data.collections.new("Cup Set"), bpy.data.collections.new("Table Set")
    for obj in (cup, candle):
        inner.objects.link(obj)
    cup_set = bpy.data.objects.new("Cup Set Instance", None)
    cup_set.instance_type, cup_set.instance_collection, cup_set.location = "COLLECTION", inner, (0.4, 0.0, 0.0)
    outer.objects.link(cup_set)
    outer.objects.link(mesh_object("Plate", cube(0.5), chrome))
    table_set = bpy.data.objects.new("Table Set Instance", None)
    table_set.instance_type, table_set.instance_collection = "COLLECTION", outer
    table_set.location = (-1.5, 1.5, 0.3)
    def node_sphere(tree):
        sphere = tree.nodes.new("GeometryNodeMeshUVSphere")
        sphere.inputs["Radius"].default_value = 0.15
        tree.links.new(sphere.outputs["Mesh"], (setter := tree.nodes.new("GeometryNodeSetMaterial")).inputs[0])
        setter.inputs["Material"].default_value = chrome
        return setter.outputs[0]
    node_spheres = bpy.data.objects.new("Node Spheres", bpy.data.meshes.new("Node Spheres"))
    node_spheres.modifiers.new("Scatter", "NODES").node_group = instance_on_grid("Scatter node spheres", (1.0, 0.6),
                                                                                 node_sphere)
    node_spheres.location = (1.5, -1.5, 0.2)
    scene = scene_with(floor, pebble, emitter, holder, stud, table_set, node_spheres, name="copies test")
    emitter.modifiers.new("Pebbles", "PARTICLE_SYSTEM")
    particles = emitter.particle_systems[0].settings
    particles.count, particles.render_type, particles.instance_object = 20, "OBJECT", pebble
    particles.frame_start = particles.frame_end = 1
    particles.physics_type, particles.display_percentage = "NO", 50  # the viewport shows half of them
    particles.particle_size = 1.0
    return scene


def test_particle_and_vertex_instances_bake_as_object_copies_that_remove_takes_away(tmp_path):
    """Without Instances as Copies the plan names particle, vertex and nested instances as left to the renderer and
    says what bakes them; with it, each of the 20 particles (all of them, though the viewport shows half), 8 vertex
    instances and the nested table set's plate and cup is a plan entry with texels, the capture replaces them by
    object copies with tiles of their own (the lamp inside the set is copied too, so it still lights), a plan made
    after the capture is the same plan, and Remove SG Bake gives the instancers back their settings."""
    from sg_lightfield.blender_addon import stand_ins
    from sg_lightfield.blender_addon.capture import OFFSET_KEY

    scene = _copies_scene()
    by_base = {base_name(o.name): o for o in scene.objects}
    owners = [by_base[n] for n in ("Floor", "Pebble", "Emitter", "Holder", "Stud", "Table Set Instance",
                                   "Node Spheres")]
    meshes_before = set(bpy.data.meshes.keys())
    before = {o.name: object_fingerprint(o) for o in owners}
    particles = by_base["Emitter"].particle_systems[0].settings
    by_base["Pebble"]["sglf_texel_scale"] = 2.0  # the user's setting, which every copy keeps
    before = {o.name: object_fingerprint(o) for o in owners}
    left = build_plan(scene, DRAFT)
    emitter_line = next(o for o in left.objects if base_name(o.name) == "Emitter")
    assert "left to the renderer" in emitter_line.reason and "Instances as Copies" in emitter_line.reason
    table_line = next(o for o in left.objects if base_name(o.name) == "Table Set Instance")
    assert "nested inside instances" in table_line.reason and "Instances as Copies" in table_line.reason
    assert not any(o.instancer for o in left.objects)
    settings = BakeSettings.from_preset("draft", texel_density=16.0, instance_copies=True)
    plan = build_plan(scene, settings)
    pebbles = [o for o in plan.baked_objects if base_name(o.instancer) == "Emitter"]
    studs = [o for o in plan.baked_objects if base_name(o.instancer) == "Holder"]
    table = [o for o in plan.baked_objects if base_name(o.instancer) == "Table Set Instance"]
    spheres = [o for o in plan.baked_objects if base_name(o.instancer) == "Node Spheres"]
    assert len(pebbles) == 20 and len(studs) == 8 and sorted(base_name(o.source) for o in table) == ["Cup", "Plate"]
    assert len(spheres) == 6 and all("generated geometry #" in o.name for o in spheres)
    assert all(o.texels > 0 and o.geometry.endswith("as an object copy") for o in pebbles + studs + table + spheres)
    assert particles.display_percentage == 50
    result = capture(scene, plan, tmp_path)
    copies = {o["name"]: o["texels"] for o in result.objects
              if o["name"] in {p.name for p in pebbles + studs + table + spheres}}
    assert len(copies) == 36 and min(copies.values()) > 0, copies
    made = stand_ins.copies_of(by_base["Node Spheres"])  # meshes of their own, the node tree's material on them
    assert len({c.data.name for c in made}) == 6 and all(base_name(c.data.materials[-1].name) == "chrome"
                                                         for c in made)
    assert all(c.get("sglf_texel_scale") == 2.0 for c in stand_ins.copies_of(by_base["Emitter"]))
    for instancer, count in (("Emitter", 20), ("Holder", 8)):
        made = stand_ins.copies_of(by_base[instancer])
        assert len(made) == count and len({tuple(c[OFFSET_KEY]) for c in made}) == count  # a tile each
        assert all(c.data == made[0].data for c in made)  # linked duplicates of the instanced object
    table_copies = {base_name(c[stand_ins.INSTANCE_COPY_KEY]["source"]): c
                    for c in stand_ins.copies_of(by_base["Table Set Instance"])}
    assert sorted(table_copies) == ["Candle", "Cup", "Plate"] and table_copies["Candle"].type == "LIGHT"
    np.testing.assert_allclose(table_copies["Candle"].matrix_world.translation, (-1.1, 1.5, 0.6), atol=1e-6)
    assert not by_base["Emitter"].modifiers["Pebbles"].show_render and by_base["Holder"].instance_type == "NONE"
    assert by_base["Table Set Instance"].instance_type == "NONE"
    with active_scene(scene) as depsgraph:
        depsgraph.update()
        assert not any(i.is_instance and i.parent and i.parent.original.name in (
            "Emitter", "Holder", "Table Set Instance", "Node Spheres") for i in depsgraph.object_instances)
    assert build_plan(scene, settings).content_hash() == plan.content_hash()
    emitter = by_base["Emitter"]
    emitter_name, emitter.name = emitter.name, "Renamed Emitter"  # the user renames it: Remove still finds its copies
    remove_bake(scene)
    emitter.name = emitter_name
    assert not any(stand_ins.is_copy(o) for o in bpy.data.objects)
    assert not any(c.get(stand_ins.COPIES_OF_KEY) for c in bpy.data.collections)
    assert {o.name: object_fingerprint(o) for o in owners} == before
    assert particles.display_percentage == 50
    assert set(bpy.data.meshes.keys()) == meshes_before  # the node-made spheres' meshes went with their copies
