"""Apply stage: the node group against its numpy reference in Cycles, write-back, Remove SG Bake, re-bake."""
import json
import re

import bpy  # noqa: I001
import bmesh
import numpy as np
import pytest
from mathutils import Vector

from sg_lightfield.blender_addon.apply import BAKE_RECORD_KEY, IMAGE_NAME, apply_stage, baked_group, remove_bake
from sg_lightfield.blender_addon.capture import capture
from sg_lightfield.blender_addon.render import quiet_stdout, render_stage
from sg_lightfield.blender_addon.scene_analysis import active_scene, build_plan
from sg_lightfield.shaders import sg_math as m
from sg_lightfield.bake_directory.bake_plan import BakeSettings
from sg_lightfield.bake_directory.exr_io import read_exr, write_exr
from sg_lightfield.shaders.node_group import GROUP_NAME, SGTextureLayout, build_node_group, flattened_node_count
from sg_lightfield.shaders.sg_shading import NumpyOps, encode_sharpness, shade
from sg_lightfield.bake_directory.sg_textures import pack_tiles
from tests.scene_helpers import material, mesh_fingerprint, mesh_object, scene_with, uniform_world, uv_sphere
from sg_lightfield.training.train_stage import ENV_SG_COUNT

pytestmark = pytest.mark.slow


def parity_scene(group, width, height):
    scene = bpy.data.scenes.new("parity")
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising = 1, False
    scene.cycles.pixel_filter_type, scene.cycles.filter_width = "BOX", 0.01  # one sample at each pixel centre
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    mesh = bpy.data.meshes.new("parity")
    bm = bmesh.new()
    bm.loops.layers.uv.new("UVMap")
    bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=1.0, calc_uvs=True)
    bm.to_mesh(mesh)
    mat = bpy.data.materials.new("parity")
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    tree.links.new(tree.nodes.new("ShaderNodeUVMap").outputs[0], node.inputs["UV"])
    emission = tree.nodes.new("ShaderNodeEmission")
    tree.links.new(node.outputs["Total"], emission.inputs["Color"])
    tree.links.new(emission.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    mesh.materials.append(mat)
    scene.collection.objects.link(bpy.data.objects.new("parity", mesh))
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 2.0
    camera.location = (0, 0, 5)
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.world = bpy.data.worlds.new("black")
    return scene, node


def parity_group(tmp_path, layout, cells, env_sgs, name):
    """The node group over a packed image of the parameter cells (h, w) of every tile, and lookup(kind, j) of the
    stored (half-float) cells for the numpy reference. Every cell spans 2 x 2 identical texels and each pixel centre
    of a (w, h) render hits the middle of a cell, so the node-side bilinear filter returns the cell's exact values
    despite Cycles' tiny pixel-filter jitter."""
    h, w = next(iter(cells.values())).shape[:2]
    tiles = {key: np.repeat(np.repeat(value, 2, axis=0), 2, axis=1) for key, value in cells.items()}
    path = write_exr(tmp_path / "packed.exr", pack_tiles(layout, tiles, (2 * h, 2 * w)), precision="half",
                     channels=["R", "G", "B", "A"])
    stored, _, _ = read_exr(path, channels=["R", "G", "B", "A"])
    image = bpy.data.images.load(str(path))
    image.colorspace_settings.name, image.alpha_mode = "Non-Color", "CHANNEL_PACKED"
    group = build_node_group(image, layout, env_sgs, name=name)
    columns, rows = layout.grid

    def lookup(kind, j):
        col, row_from_bottom = layout.tile_offset(kind, j)
        top = (rows - 1 - row_from_bottom) * 2 * h
        texel = stored[top:top + 2 * h:2, col * 2 * w:(col + 1) * 2 * w:2].astype(np.float64)
        return texel[..., :3], texel[..., 3]

    return group, lookup


PARITY_METALLIC = 0.3  # the Fresnel between the dielectric's shape and Schlick's


def _parity_worst(tmp_path, layout, cells, env_sgs, roughnesses, angles_deg) -> float:
    """Worst relative difference between a Cycles render of the node group and its numpy reference, over the
    parameter cells (h, w) of every tile and the given roughnesses and normal angles."""
    h, w = next(iter(cells.values())).shape[:2]
    group, lookup = parity_group(tmp_path, layout, cells, env_sgs,
                                 f"SG Lightfield parity {layout.sg_count} {layout.sh_count}")
    scene, node = parity_scene(group, w, h)
    worst = 0.0
    for roughness in roughnesses:
        for theta in angles_deg:
            normal = (np.sin(np.radians(theta)), 0.0, np.cos(np.radians(theta)))
            node.inputs["Normal"].default_value = normal
            node.inputs["Roughness"].default_value = roughness
            node.inputs["F0"].default_value = (0.04, 0.5, 0.9, 1.0)  # at 1 the layered diffuse is ~0
            node.inputs["Albedo"].default_value = (0.8, 0.5, 0.2, 1.0)
            node.inputs["Metallic"].default_value = PARITY_METALLIC
            scene.render.filepath = str(tmp_path / "parity.exr")
            with active_scene(scene), quiet_stdout():
                bpy.ops.render.render(write_still=True, scene=scene.name)
            rendered, _, _ = read_exr(tmp_path / "parity.exr", channels=["R", "G", "B"])
            reference = shade(NumpyOps(), lookup, np.broadcast_to(normal, (h, w, 3)),
                              np.broadcast_to((0.0, 0.0, 1.0), (h, w, 3)), np.full((h, w), roughness),
                              np.broadcast_to((0.04, 0.5, 0.9), (h, w, 3)), np.broadcast_to((0.8, 0.5, 0.2), (h, w, 3)),
                              layout.sg_count, layout.iwev_count, env_sgs, layout.has_irradiance,
                              layout.sh_count, PARITY_METALLIC)["total"]
            # relative, and absolute below 0.1: the renders carry an offset of ~5e-5 (the same in every channel)
            worst = max(worst, float((np.abs(rendered - reference) / np.maximum(np.abs(reference), 0.1)).max()))
    return worst


def test_node_group_matches_its_numpy_reference_in_cycles(tmp_path):
    """Over a grid that includes the extremes: sharpness 1e-4..1e4, amplitudes 0..1e4, roughness 0 (floored)
    to 1, grazing n.v, with the environment term (global env SGs x W_E from IWEV SGs, clipped to [0, 1]);
    the stored (half-float) parameters feed the numpy reference."""
    n, h, w = 3, 6, 6
    rng = np.random.default_rng(0)
    layout = SGTextureLayout(n, iwev_count=1, has_irradiance=True, atlas_size=(2 * w, 2 * h))
    env_sgs = [((0.3, -0.2, 0.9), 4.0, (2.0, 1.5, 1.0)), ((-0.5, 0.5, 0.2), 40.0, (30.0, 20.0, 10.0))]
    cells = {}
    for j in range(n):
        sharpness = np.exp(rng.uniform(np.log(1e-4), np.log(1e4), (h, w)))
        sharpness[0, 0], sharpness[0, 1] = 1e-4, 1e4
        cells[("sg", j)] = np.concatenate([rng.normal(size=(h, w, 3)), encode_sharpness(sharpness)[..., None]], -1)
        amplitude = rng.uniform(0, 20, (h, w, 3))
        amplitude[1, 0], amplitude[1, 1] = 0.0, 1e4
        cells[("amp", j)] = np.concatenate([amplitude, np.zeros((h, w, 1))], -1)
    cells[("irradiance", 0)] = np.concatenate([rng.uniform(0, 3, (h, w, 3)), np.ones((h, w, 1))], -1)
    cells[("iwev", 0)] = np.concatenate([rng.normal(size=(h, w, 3)), rng.uniform(0, 1, (h, w, 1))], -1)
    cells[("iwev_amp", 0)] = np.concatenate([rng.uniform(0, 1.2, (h, w, 3)), np.zeros((h, w, 1))], -1)
    assert _parity_worst(tmp_path, layout, cells, env_sgs, (0.0, 0.2, 0.6, 1.0), (0.0, 60.0, 89.0)) < 1e-3


def test_irradiance_lightmap_group_matches_its_numpy_reference_in_cycles(tmp_path):
    """The group of rough materials baked as an irradiance lightmap (no SGs): the split-sum specular of the
    irradiance and the diffuse layered under it, from roughness 0.6 to 1 and normal to grazing view."""
    h, w = 4, 4
    layout = SGTextureLayout(0, has_irradiance=True, atlas_size=(2 * w, 2 * h))
    irradiance = np.random.default_rng(3).uniform(0.01, 3, (h, w, 3))
    cells = {("irradiance", 0): np.concatenate([irradiance, np.ones((h, w, 1))], -1)}
    assert _parity_worst(tmp_path, layout, cells, [], (0.6, 0.8, 1.0), (0.0, 60.0, 89.0)) < 1e-3


def test_sixteen_sgs_with_environment_visibility_fit_in_cycles_svm_stack(tmp_path):
    """The largest group the presets make (16 SGs, 16 IWEV SGs, 16 environment SGs) compiles in Cycles' 255-slot SVM
    stack and still equals its numpy reference (without the lookup barriers: "out of SVM stack space", black)."""
    n, iwev, h, w = 16, 16, 4, 4
    rng = np.random.default_rng(2)
    layout = SGTextureLayout(n, iwev_count=iwev, has_irradiance=True, atlas_size=(2 * w, 2 * h))
    env_sgs = _random_env_sgs(rng)
    cells = _largest_groups_cells(n, iwev, h, w, rng)
    assert _parity_worst(tmp_path, layout, cells, env_sgs, (0.3,), (30.0,)) < 1e-3


def test_sh_node_group_matches_its_numpy_reference_in_cycles(tmp_path):
    """The SH L2 baseline's variant of the group: signed coefficients up to 1e3, roughness 0 to 1, grazing."""
    h, w = 4, 4
    rng = np.random.default_rng(1)
    layout = SGTextureLayout(0, has_irradiance=True, atlas_size=(2 * w, 2 * h), sh_count=9)
    cells = {("sh", j): np.concatenate([rng.normal(size=(h, w, 3)) * (10.0 if j else 20.0), np.zeros((h, w, 1))], -1)
             for j in range(9)}
    cells[("sh", 0)][0, 0, :3] = 1e3
    cells[("irradiance", 0)] = np.concatenate([rng.uniform(0, 3, (h, w, 3)), np.ones((h, w, 1))], -1)
    assert _parity_worst(tmp_path, layout, cells, (), (0.0, 0.5, 1.0), (0.0, 89.0)) < 1e-3


def _material_fingerprint(mat):
    tree = mat.node_tree
    nodes = sorted((n.name, n.bl_idname, tuple((i.name, str(getattr(i, "default_value", None)) if not hasattr(
        getattr(i, "default_value", None), "__len__") else tuple(i.default_value)) for i in n.inputs))
                   for n in tree.nodes)
    links = sorted((l.from_node.name, l.from_socket.identifier, l.to_node.name, l.to_socket.identifier)
                   for l in tree.links)
    return json.dumps([mat.name, nodes, links], default=str)


def test_layered_diffuse_and_split_sum_specular_match_principled_in_a_white_furnace(tmp_path):
    """Dielectric spheres under a uniform white sky, rendered by Cycles' Principled BSDF and shaded by `shade` from
    their irradiance (pi) without SGs: the specular's split-sum albedo and the diffuse layered under it, per n.v.
    A black base shows the specular alone (the dielectric's Fresnel); a grey one the layering, which leaving out costs
    0.8 A (2 % to 12 % here)."""
    from sg_lightfield.blender_addon.render import render_still
    from sg_lightfield.blender_addon.scene_analysis import principled_surface

    cases = [(roughness, base) for roughness in (0.25, 0.9) for base in (0.0, 0.8)]
    scene = bpy.data.scenes.new("white furnace")
    uniform_world(scene, (1, 1, 1), "white")
    for i, (roughness, base) in enumerate(cases):
        mat = material(f"Furnace {i}", roughness)
        mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (base, base, base, 1)
        ball = mesh_object(f"Furnace ball {i}", uv_sphere(1.0, 96, 48), mat)
        ball.data.shade_smooth()
        ball.location = (2.2 * (i % 2) - 1.1, 2.2 * (i // 2) - 1.1, 0)
        ball.visible_diffuse = ball.visible_glossy = ball.visible_transmission = ball.visible_shadow = False  # convex
        scene.collection.objects.link(ball)
    camera = bpy.data.objects.new("furnace camera", bpy.data.cameras.new("furnace camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 4.4
    camera.location = (0, 0, 10)
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising = 256, False
    scene.cycles.pixel_filter_type, scene.cycles.filter_width = "BOX", 0.01
    scene.render.resolution_x = scene.render.resolution_y = 96
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    pixels = render_still(scene, tmp_path / "furnace.exr")[::-1].mean(axis=-1)  # rows from the bottom, as y
    centres = (np.arange(96) + 0.5) / 96 * 4.4 - 2.2
    x, y = np.meshgrid(centres, centres)
    for i, (roughness, base) in enumerate(cases):
        dx, dy = x - (2.2 * (i % 2) - 1.1), y - (2.2 * (i // 2) - 1.1)
        ndotv = np.sqrt(np.clip(1 - dx**2 - dy**2, 0, 1))
        surface = principled_surface(scene.objects[f"Furnace ball {i}"].active_material)
        for low, high in ((0.25, 0.5), (0.5, 0.75), (0.75, 1.0)):
            ring = (ndotv > low) & (ndotv <= high) & (dx**2 + dy**2 < 0.98)
            n = np.stack([dx[ring], dy[ring], ndotv[ring]], -1)
            shaded = shade(NumpyOps(), lambda name, j: (np.full((len(n), 3), np.pi), None), n,
                           np.broadcast_to((0.0, 0.0, 1.0), n.shape), np.full(len(n), roughness),
                           np.asarray(surface["f0"]), np.full(3, base), sg_count=0, metallic=surface["metallic"])
            ours, cycles = shaded["total"].mean(), pixels[ring].mean()
            if base:  # 256 spp: the rings' means are within 0.4 % of ours; without layering 1.8 % to 12 % above
                assert ours == pytest.approx(cycles, rel=0.01), (roughness, low, ours, cycles)
                assert ours + base * shaded["glossy"].mean() > 1.012 * cycles
            else:  # the specular alone: 0.92-1.06 of Cycles' (with Schlick's Fresnel 0.77-1.03)
                assert ours == pytest.approx(cycles, rel=0.1), (roughness, low, ours, cycles)


def test_write_back_remove_restores_everything_and_rebake_does_not_pile_up(tmp_path):
    glossy = material("Glossy", 0.2, metallic=1.0)
    rough = material("Rough", 0.9)
    ball = mesh_object("Ball", uv_sphere(0.8, 16, 8), glossy)
    twin = mesh_object("Twin", None, mesh=ball.data)  # a linked duplicate
    twin.location = (2.0, 0.0, 0.0)
    floor = mesh_object("Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=3.0), rough)
    floor.location = (0, 0, -0.8)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.location = (1, -2, 3)
    scene = scene_with(ball, twin, floor, lamp)
    before = {m.name: _material_fingerprint(m) for m in (glossy, rough)}
    meshes_before = {m.name: mesh_fingerprint(m) for m in (ball.data, floor.data)}
    plan = build_plan(scene, BakeSettings.from_preset("draft", lightfield_resolution=8, samples=4, sg_count=2,
                                                      training_budget_s=1.0))
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    from sg_lightfield.training.train_stage import train_stage

    train_stage(tmp_path, plan)
    counts = []
    for _ in range(2):
        info = apply_stage(scene, plan, tmp_path)
        counts.append((len(bpy.data.images), len(bpy.data.node_groups), len(bpy.data.materials)))
    assert counts[0] == counts[1]  # a second bake replaces, never piles up
    assert f"{GROUP_NAME} / glossy SG" in bpy.data.node_groups  # built once, instanced per SG
    assert info["materials"] == ["Glossy (SG bake)", "Rough (SG bake)"]
    assert ball.material_slots[0].material.name == "Glossy (SG bake)"
    assert info["irradiance_only"] == ["Rough"]  # rough: an irradiance lightmap through its own small group
    assert baked_group(floor.material_slots[0].material).name == f"{GROUP_NAME} (irradiance)"
    for baked in (ball.material_slots[0].material, floor.material_slots[0].material):
        # One graph, one output for both renderers: a Cycles graph beside EEVEE's cost EEVEE 80 s of compiling per
        # material on the Draft spheres, against 5 s without (docs/design-additions.md §19).
        outputs = [n for n in baked.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
        groups = [n for n in baked.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"]
        assert [o.target for o in outputs] == ["ALL"] and len(groups) == 1
        assert baked_group(baked, "CYCLES") == baked_group(baked, "EEVEE") == groups[0].node_tree
    assert bpy.data.images[IMAGE_NAME].packed_file is not None
    assert _material_fingerprint(glossy) == before["Glossy"]  # the original is never edited
    with active_scene(scene), quiet_stdout():  # the baked scene renders in Cycles
        scene.render.resolution_x = scene.render.resolution_y = 32
        scene.render.filepath = str(tmp_path / "baked.png")
        scene.camera = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        scene.collection.objects.link(scene.camera)
        scene.camera.location = (1, -6, 0.5)
        scene.camera.rotation_euler = (1.5, 0, 0)
        bpy.ops.render.render(write_still=True, scene=scene.name)
    from sg_lightfield.blender_addon.evaluate import EEVEE_LEFT_OUT, evaluate_stage

    objects_before = set(bpy.data.objects.keys())
    errors = evaluate_stage(scene, plan, tmp_path, views=2, resolution=(32, 18), reference_samples=8,
                            eevee_without_bake=False)
    assert len(errors["views"]) == 2 and all(np.isfinite(errors[k]) for k in ("rmse", "psnr", "flip"))
    assert 0 <= errors["flip"] <= 1 and (tmp_path / "evaluate_view1.png").is_file()
    classes = errors["flip_by_roughness"]  # glossy 0.2 ball and its twin vs the rough 0.8 floor
    assert classes["roughness < 0.3"]["pixels"] > 0 and classes["roughness >= 0.6"]["pixels"] > 0
    assert sum(c["pixels"] for c in classes.values()) < 2 * 32 * 18  # the world's pixels belong to no class
    materials = errors["flip_by_material"]  # by name: the same pixels less the edges that mix two surfaces
    assert set(materials) == {glossy.name, rough.name}, materials
    for name, roughness_class in ((glossy.name, "roughness < 0.3"), (rough.name, "roughness >= 0.6")):
        whole, of_class = materials[name]["pixels"], classes[roughness_class]["pixels"]
        assert of_class / 2 < whole <= of_class and 0 <= materials[name]["flip"] <= 1
        assert 0 <= materials[name]["reference_noise_flip"] <= 1 and materials[name]["rmse"] >= 0
        assert 0 < materials[name]["reference_noise_rmse"] < 1  # 4 + 4 spp halves: some noise, finite
    noise_classes = errors["reference_noise_flip_by_roughness"]
    assert all(0 < noise_classes[c]["rmse"] < 1 for c in ("roughness < 0.3", "roughness >= 0.6"))
    eevee = errors["eevee"]  # EEVEE, the engine the bake is for, renders the same views
    assert "error" not in eevee, eevee
    assert len(eevee["views"]) == 2 and (tmp_path / "evaluate_view1_eevee.png").is_file()
    assert eevee["flip_vs_cycles_bake"] < eevee["flip"] + 0.05 and eevee["first_render_s"] > 0
    assert set(bpy.data.objects.keys()) == objects_before  # temporary cameras removed
    assert ball.material_slots[0].material.name == "Glossy (SG bake)"  # swaps for the reference undone
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["errors"]["flip"] == errors["flip"] and set(report["timings_s"]) >= {"capture", "render", "train",
                                                                                        "apply", "evaluate"}
    page = (tmp_path / "report.html").read_text()
    assert "data:image/png;base64" in page and "RMSE where roughness &lt; 0.3" in page
    assert "against the converged image" in page
    cache = {}  # the bench evaluates several trainings of one bake's scene against one set of references
    first = evaluate_stage(scene, plan, tmp_path, views=2, resolution=(32, 18), reference_samples=8,
                           with_eevee=False, reference_cache=cache)
    assert len(cache) == 2 and first["reference_noise_rmse"] > 0
    assert first["eevee"] == {"error": EEVEE_LEFT_OUT} and first["eevee_without_bake"] == {}  # named, not silent
    for key, (half_a, _, surfaces) in list(cache.items()):
        cache[key] = (half_a, half_a, surfaces)  # equal halves: a reference read from the cache has no noise
    again = evaluate_stage(scene, plan, tmp_path, views=2, resolution=(32, 18), reference_samples=8,
                           with_eevee=False, reference_cache=cache)
    assert again["reference_noise_rmse"] == 0 and len(cache) == 2
    assert again["flip_by_material"].keys() == first["flip_by_material"].keys()
    assert set(bpy.data.objects.keys()) == objects_before
    assert remove_bake(scene) == 3  # the floor's slot and the slot of each instance (they share the mesh and slot)
    assert ball.material_slots[0].material == glossy and twin.material_slots[0].material == glossy
    assert floor.material_slots[0].material == rough and "Rough (SG bake)" not in bpy.data.materials
    assert {m.name: _material_fingerprint(m) for m in (glossy, rough)} == before
    assert {m.name: mesh_fingerprint(m) for m in (ball.data, floor.data)} == meshes_before
    assert not glossy.use_fake_user and "Glossy (SG bake)" not in bpy.data.materials
    group_name = re.compile(re.escape(GROUP_NAME) + r"( \(.*\))?( / .*)?$")  # and its nested groups
    assert not [g.name for g in bpy.data.node_groups if group_name.match(g.name)]
    assert IMAGE_NAME not in bpy.data.images
    assert BAKE_RECORD_KEY not in scene


def test_eevee_renders_the_baked_scene_like_cycles_evaluates_it(tmp_path):
    """Every visible surface is either baked or a pure emitter, so both engines must show the same picture."""
    import subprocess
    import sys
    from pathlib import Path

    from sg_lightfield.blender_addon.pipeline import BakeJob
    from sg_lightfield.bake_directory.image_metrics import tonemap

    scene = bpy.data.scenes.new("eevee parity")
    for i, roughness in enumerate((0.2, 0.45)):
        ball = mesh_object(f"Ball {i}", uv_sphere(0.6, 24, 12), material(f"Metal {i}", roughness, metallic=1.0))
        ball.location = (-0.8 + 1.6 * i, 0, 0)
        scene.collection.objects.link(ball)
    panel = mesh_object("Panel", uv_sphere(0.4, 12, 6), None)
    light = bpy.data.materials.new("Panel light")
    nodes = light.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 8.0
    light.node_tree.links.new(emission.outputs[0], nodes["Material Output"].inputs["Surface"])
    panel.data.materials.append(light)
    panel.location = (0, -1.0, 1.6)
    scene.collection.objects.link(panel)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location, camera.rotation_euler = (0, -4.5, 0.3), (1.5, 0, 0)
    scene.collection.objects.link(camera)
    scene.camera, scene.world = camera, bpy.data.worlds.new("black")
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 40, 100
    settings = BakeSettings.from_preset("draft", texel_density=6.0, lightfield_resolution=8, samples=8, sg_count=4,
                                        training_budget_s=5.0)
    BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train", "apply")).run()
    blend = tmp_path / "baked.blend"
    with active_scene(scene), quiet_stdout():
        bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    script = Path(__file__).resolve().parent.parent / "blender_addon" / "eevee_worker.py"
    out = subprocess.run([sys.executable, str(script), str(blend), scene.name, str(tmp_path),
                          "--engines", "BLENDER_EEVEE,CYCLES"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    eevee, _, _ = read_exr(tmp_path / "BLENDER_EEVEE_0.exr", channels=["R", "G", "B"])
    cycles, _, _ = read_exr(tmp_path / "CYCLES_0.exr", channels=["R", "G", "B"])
    difference = np.abs(tonemap(eevee) - tonemap(cycles))
    assert tonemap(cycles).max() > 0.3  # the picture is not empty
    assert difference.mean() < 0.005, difference.mean()  # one graph in both engines (measured 4e-4)

    # the frame-time tool a GPU machine runs (headless/eevee_frame_time.py), on this bake at a tiny size
    tool = Path(__file__).resolve().parent.parent / "headless" / "eevee_frame_time.py"
    report = tmp_path / "frame_time.json"
    out = subprocess.run([sys.executable, str(tool), str(tmp_path), "--resolution", "32x20", "--samples", "1,3",
                          "--repeats", "1", "--report", str(report)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (row,) = json.loads(report.read_text())
    muted = row["evaluator_off"]["evaluator_nodes_muted"]  # the file holds the other tests' materials as well
    assert muted["Metal 0 (SG bake)"] == muted["Metal 1 (SG bake)"] == 1  # one evaluator in each metal's copy
    assert row["with_bake"]["evaluator_nodes_muted"] == row["without_bake"]["evaluator_nodes_muted"] == {}
    for setup in ("with_bake", "evaluator_off", "without_bake"):
        assert row[setup]["first_render_s"] > 0 and (row[setup]["frame_ms"] is None or row[setup]["frame_ms"] > 0)
        assert [len(v) for v in row[setup]["render_s"].values()] == [1, 1]
    assert row["gpu"] and "frame" in out.stdout
    bad = subprocess.run([sys.executable, str(tool), str(tmp_path / "nowhere")], capture_output=True, text=True,
                         timeout=300)
    assert bad.returncode == 1 and bad.stderr.strip().splitlines()[-1] == \
        f"error: {tmp_path / 'nowhere'}: no baked.blend (bake with the apply stage first)"
    remove_bake(scene)


def test_eevee_renders_the_baked_spheres_in_the_evaluate_stage(tmp_path):
    """The whole pipeline on `spheres` (small knobs): the evaluate stage renders EEVEE headless, writes the
    picture reference | EEVEE | FLIP into the bake directory, and on the baked surfaces EEVEE matches Cycles'
    evaluation of the same nodes (the rough floor is EEVEE's own lighting, which lacks the emissive arcs'
    light without its ray tracing)."""
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.evaluate import evaluate_stage
    from sg_lightfield.blender_addon.pipeline import BakeJob

    scene = build_demo_scene("demo:spheres")
    # 4 SGs: EEVEE compiles each baked material's group on this CPU (16 SGs: 7 of the suite's 20 minutes); the
    # largest group has its own test
    settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=8, training_epochs=30,
                                        sg_count=4)  # parity between renderers of one bake, whatever its training
    job = BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train", "apply"))
    job.run()
    # the stage the pipeline runs last, at one view of 160 x 90 (its Cycles renders were most of this test's time)
    evaluate_stage(scene, job.plan, tmp_path, views=1, resolution=(160, 90), eevee_without_bake=False)
    errors = json.loads((tmp_path / "report.json").read_text())["errors"]
    eevee = errors["eevee"]
    assert "error" not in eevee, eevee
    assert errors["eevee_without_bake"] == {}  # EEVEE alone left out: the materials tests compare with it
    assert (tmp_path / "evaluate_view0_eevee.png").is_file() and eevee["first_render_s"] > 0
    assert eevee["shader_errors"] == []  # every baked material compiled (a failed one renders magenta)
    parity = eevee["flip_vs_cycles_bake_by_roughness"]
    for name in ("roughness < 0.3", "0.3 <= roughness < 0.6"):
        assert parity[name]["pixels"] > 100 and parity[name]["flip"] < 0.1, parity
    remove_bake(scene)


def _render_small(scene, path, camera_location) -> np.ndarray:
    """A 32x18 Cycles render (2 spp) of the scene from a new camera looking along +Y; returns its RGB."""
    with active_scene(scene), quiet_stdout():
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 32, 18, 100
        scene.cycles.samples = 2
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.filepath = str(path)
        scene.camera = bpy.data.objects.new("small render", bpy.data.cameras.new("small render"))
        scene.collection.objects.link(scene.camera)
        scene.camera.location, scene.camera.rotation_euler = camera_location, (1.5708, 0, 0)
        bpy.ops.render.render(write_still=True, scene=scene.name)
    return read_exr(path, channels=["R", "G", "B"])[0]


def test_each_material_gets_the_sg_count_its_roughness_needs(tmp_path):
    """A smooth and a rougher glossy material: the rougher one is fitted and shaded with fewer SGs (its texels'
    extra SGs are zero after the amplitude and lobe refits too, its node group is smaller); --uniform-sg-count
    gives both the same."""
    from sg_lightfield.bake_directory.bake_plan import auto_sg_count
    from sg_lightfield.bake_directory.sg_textures import read_sg_texture
    from sg_lightfield.bake_directory.texel_maps import channels, read_texel_maps
    from sg_lightfield.training.train_stage import train_stage

    smooth, rougher = material("Smooth", 0.1, metallic=1.0), material("Rougher", 0.58, metallic=1.0)
    ball = mesh_object("Smooth ball", uv_sphere(0.6, 16, 8), smooth)
    other = mesh_object("Rougher ball", uv_sphere(0.6, 16, 8), rougher)
    other.location = (1.5, 0, 0)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.location = (0, -2, 2)
    scene = scene_with(ball, other, lamp)
    settings = BakeSettings.from_preset("draft", texel_density=6.0, lightfield_resolution=16, samples=4, sg_count=16,
                                        training_budget_s=2.0, lobe_refit_steps=10)
    plan = build_plan(scene, settings)
    counts = {m.name: m.sg_count for o in plan.baked_objects for m in o.materials}
    assert counts == {"Smooth": auto_sg_count(0.1), "Rougher": auto_sg_count(0.58)} and counts["Rougher"] < 16
    uniform = build_plan(scene, BakeSettings.from_preset("draft", sg_count=16, uniform_sg_count=True))
    assert {m.sg_count for o in uniform.baked_objects for m in o.materials} == {16}
    assert uniform.stage_hash("train") != plan.stage_hash("train")

    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    metrics = train_stage(tmp_path, plan).metrics["lightfield"]
    atlas, info = read_texel_maps(tmp_path)
    # amplitudes and lobes refitted through the glossy where the lobe spans 0.36 pixels of R = 16 (roughness >= 0.28)
    refit, shaded = metrics["amplitude_refit"], metrics["shaded_error"]
    assert refit["min_roughness"] == pytest.approx(0.282, abs=0.001)
    assert refit["lobes"]["min_roughness"] == pytest.approx(0.282, abs=0.001)
    rougher_texels = int(((channels(atlas, "valid") > 0) & (channels(atlas, "material_id") == next(
        m["id"] for m in info["materials"] if m["name"] == "Rougher"))).sum())
    assert refit["texels"] == rougher_texels > 0
    assert "Smooth" not in shaded  # too sharp for R = 16: kept as trained, and no error the quadrature can't give
    assert np.isfinite(shaded["Rougher"]) and shaded["Rougher"] >= 0 and "Rougher" in refit["shaded_error_before"]
    # kept only where it lowers the held-out error, so the reported error never exceeds the trained amplitudes'
    # (or, kept on that error, reverted where it raised the error between texels)
    assert set(refit["kept_for"]) | set(refit["reverted_for"]) | set(refit["reverted_between_texels_for"]) == \
        {"Rougher"}
    assert shaded["Rougher"] <= refit["shaded_error_before"]["Rougher"]
    # the lobe refit, too, is kept only where it does not raise the error between texels (SGs blended as the shader
    # does) by more than its tolerance
    lobes, between = refit["lobes"], metrics["interpolated_shaded_error"]
    assert lobes["steps"] == 10 and lobes["texels"] == rougher_texels and lobes["tolerance"] == 1.15
    assert set(lobes["kept_for"]) | set(lobes["reverted_for"]) == {"Rougher"}
    assert set(between) == {"Rougher"}
    assert 0 <= between["Rougher"] <= lobes["tolerance"] * lobes["interpolated_error_before"]["Rougher"]
    page = (tmp_path / "report.html").read_text()  # the report and the command line say what the refits did
    assert "lobe refit (axes, sharpness, amplitudes)</th><td>10 steps on " in page
    assert "glossy error between texels (SGs blended), Rougher" in page
    from sg_lightfield.headless.bake import _shaded_error_summary
    assert "between texels where the lobes were refitted" in _shaded_error_summary(metrics)
    _, _, amplitude, meta = read_sg_texture(tmp_path / "sg_lightfield.exr")
    assert int(meta["sg_count"]) == counts["Smooth"]
    rougher_id = next(m["id"] for m in info["materials"] if m["name"] == "Rougher")
    valid = channels(atlas, "valid") > 0
    on_rougher = valid & (channels(atlas, "material_id") == rougher_id)
    on_smooth = valid & ~on_rougher
    assert on_rougher.sum() > 10 and on_smooth.sum() > 10
    assert np.all(amplitude[on_rougher][:, counts["Rougher"]:] == 0)
    assert np.any(amplitude[on_rougher][:, :counts["Rougher"]] > 0)
    assert np.any(amplitude[on_smooth][:, counts["Rougher"]:] > 0)

    result = apply_stage(scene, plan, tmp_path)
    smooth_group = baked_group(ball.material_slots[0].material, "EEVEE")
    rougher_group = baked_group(other.material_slots[0].material, "EEVEE")
    assert smooth_group.name == GROUP_NAME and rougher_group.name == f"{GROUP_NAME} ({counts['Rougher']} SGs)"
    assert len(rougher_group.nodes) < len(smooth_group.nodes)
    assert [baked_group(o.material_slots[0].material, "CYCLES") for o in (ball, other)] == [smooth_group, rougher_group]
    assert result["sg_counts"] == counts and result["node_groups"] == {  # nested groups expanded in the counts
        g.name: flattened_node_count(g) for g in (smooth_group, rougher_group)}
    assert result["nodes"] > len(smooth_group.nodes) + 100 * counts["Smooth"]  # each glossy SG group expanded
    assert result["sg_evaluations_saved"] == pytest.approx(1 - sum(counts.values()) / (2 * counts["Smooth"]), abs=1e-3)
    rendered = _render_small(scene, tmp_path / "baked.exr", (0.75, -5, 0))  # both groups shade to finite colours
    assert np.all(np.isfinite(rendered)) and rendered.max() > 0
    names = list(result["node_groups"])
    assert remove_bake(scene) == 2
    assert not any(name in bpy.data.node_groups for name in names)


def test_sh_baseline_bakes_applies_and_shades_through_its_own_group(tmp_path):
    """The benchmark's SH L2 encoder end to end: an SH texture, the SH variant of the group, a finite Cycles
    render that sees the lamp, irradiance from the SH coefficients close to the rendered one (L2 SH holds
    irradiance to a few per cent), and Remove SG Bake takes the group away."""
    from sg_lightfield.bake_directory.sg_textures import is_sh_texture
    from sg_lightfield.training.train_stage import train_stage

    ball = mesh_object("SH ball", uv_sphere(0.6, 16, 8), material("SH metal", 0.5, metallic=1.0))
    floor = mesh_object("SH floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=3.0),
                        material("SH floor", 0.9))
    floor.location = (0, 0, -0.6)
    lamp = bpy.data.objects.new("SH lamp", bpy.data.lights.new("SH lamp", "AREA"))
    lamp.data.energy, lamp.location = 200.0, (0.5, -1.0, 2.5)
    scene = scene_with(ball, floor, lamp)
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=6.0, lightfield_resolution=8, samples=8))
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    trained = train_stage(tmp_path, plan, encoder="sh_l2")
    assert is_sh_texture(tmp_path / "sg_lightfield.exr") and trained.bytes_per_texel == 54
    assert np.isfinite(trained.metrics["lightfield"]["rmse"])
    info = apply_stage(scene, plan, tmp_path)
    group = baked_group(ball.material_slots[0].material)
    assert group.name == f"{GROUP_NAME} (SH L2)" and info["encoder"] == "sh_l2" and info["layout"]["sh_count"] == 9
    assert baked_group(ball.material_slots[0].material, "CYCLES") == group
    assert info["irradiance_from_sgs_rel_error_median"] < 0.1
    rendered = _render_small(scene, tmp_path / "baked.exr", (0, -5, 0))
    assert np.all(np.isfinite(rendered)) and rendered[6:12, 13:19].mean() > 0.01  # the lit ball
    group_name = group.name
    remove_bake(scene)
    assert group_name not in bpy.data.node_groups



def test_each_training_seed_keeps_its_own_checkpoint_and_gives_its_own_sgs(tmp_path):
    """The benchmark trains the CNN several times on the same light fields (one training's glossy error varies by
    up to 30 % with its seed, docs/design-additions.md §26). A seed has its own checkpoint: seed 1 must not resume
    seed 0's curve, and seed 0 run again resumes its own, done at its budget, to the same SGs."""
    from sg_lightfield.bake_directory.sg_textures import read_sg_texture
    from sg_lightfield.training.train_stage import train_stage

    ball = mesh_object("Seed ball", uv_sphere(0.6, 16, 8), material("Seed metal", 0.5, metallic=1.0))
    lamp = bpy.data.objects.new("Seed lamp", bpy.data.lights.new("Seed lamp", "AREA"))
    lamp.data.energy, lamp.location = 200.0, (0.5, -1.0, 2.5)
    scene = scene_with(ball, lamp)
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=4.0, lightfield_resolution=8, samples=4,
                                                      sg_count=2, training_budget_s=1.0))
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    textures = {}
    for seed in (0, 1, 0):
        trained = train_stage(tmp_path, plan, seed=seed)
        assert trained.epochs["lightfield"] > 0
        axis, sharpness, amplitude, meta = read_sg_texture(tmp_path / "sg_lightfield.exr")
        assert meta.get("seed") == (str(seed) if seed else None) and meta["encoder"] == "cnn"
        textures.setdefault(seed, []).append(np.concatenate([axis.ravel(), sharpness.ravel(), amplitude.ravel()]))
    assert len(list((tmp_path / "train").glob("lightfield_*.pt"))) == 2
    assert not np.array_equal(textures[0][0], textures[1][0])
    assert np.array_equal(textures[0][0], textures[0][1])


def test_training_by_epochs_runs_that_many_whatever_the_budget_and_gives_the_same_sgs_again(tmp_path):
    """A farm's nodes, busy or idle, must bake the same SGs: with training_epochs the CNN trains exactly that many
    epochs (the 1-s time budget set beside it is not what stops it), the plan says so with an estimate, the train stage
    is hashed with it (render is not), and the stage run again from scratch (no checkpoint) writes the same SGs."""
    import shutil

    from sg_lightfield.bake_directory.bake_plan import BakeInputError
    from sg_lightfield.bake_directory.sg_textures import read_sg_texture
    from sg_lightfield.training.train_stage import train_stage

    ball = mesh_object("Epoch ball", uv_sphere(0.6, 16, 8), material("Epoch metal", 0.5, metallic=1.0))
    lamp = bpy.data.objects.new("Epoch lamp", bpy.data.lights.new("Epoch lamp", "AREA"))
    lamp.data.energy, lamp.location = 200.0, (0.5, -1.0, 2.5)
    scene = scene_with(ball, lamp)
    knobs = dict(texel_density=4.0, lightfield_resolution=8, samples=4, sg_count=2, training_budget_s=1.0)
    plan = build_plan(scene, BakeSettings.from_preset("draft", training_epochs=700, **knobs))
    by_time = build_plan(scene, BakeSettings.from_preset("draft", **knobs))
    assert "training 700 epochs (~" in plan.summary() and "training <= 1 s" in by_time.summary()
    assert plan.stage_hash("train") != by_time.stage_hash("train")
    assert plan.stage_hash("render") == by_time.stage_hash("render")
    with pytest.raises(BakeInputError, match="training epochs -1 is outside"):
        BakeSettings.from_preset("draft", training_epochs=-1)
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    textures = []
    for _ in range(2):
        trained = train_stage(tmp_path, plan)
        assert trained.epochs["lightfield"] == 700 and trained.stopped_because["lightfield"] == "epochs"
        axis, sharpness, amplitude, _ = read_sg_texture(tmp_path / "sg_lightfield.exr")
        textures.append(np.concatenate([axis.ravel(), sharpness.ravel(), amplitude.ravel()]))
        shutil.rmtree(tmp_path / "train")  # the second run starts from scratch
    assert np.array_equal(textures[0], textures[1])


def test_with_environment_visibility_one_graph_shades_both_renderers_and_the_sg_irradiance_check_is_fair(tmp_path):
    """With IWEV the light field leaves the sky to IWEV, and the irradiance tile adds the sky back. The apply stage's
    check of the SGs' own irradiance compared them with that sky-lit total, and reported a median error of 0.98 on
    the courtyard; it must compare them with the light field they encode. And EEVEE spent minutes per courtyard
    material on a Cycles graph beside its own, so one graph feeds one output both renderers use."""
    from sg_lightfield.blender_addon.apply import irradiance_from_lightfields
    from sg_lightfield.bake_directory.lightfield_tiles import read_images
    from sg_lightfield.bake_directory.texel_maps import channels, read_texel_maps
    from sg_lightfield.training.train_stage import train_stage

    ball = mesh_object("Ball", uv_sphere(1.0), material("glossy", 0.3, metallic=1.0))
    ball.location = (0.0, 0.0, 1.0)
    lamp = bpy.data.objects.new("IWEV lamp", bpy.data.lights.new("IWEV lamp", "AREA"))
    lamp.data.energy, lamp.data.size, lamp.location = 60.0, 4.0, (0.5, -1.0, 3.5)  # a broad lamp the SGs can hold
    scene = scene_with(ball, lamp)
    uniform_world(scene, (1.0, 1.0, 1.0), "IWEV sky")
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=4.0, lightfield_resolution=8, samples=8))
    assert plan.environment.iwev
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    train_stage(tmp_path, plan, time_budget_s=10.0)
    measured = apply_stage(scene, plan, tmp_path)
    baked = ball.material_slots[0].material
    outputs = [n for n in baked.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    assert [o.target for o in outputs] == ["ALL"]
    assert baked_group(baked, "CYCLES") == baked_group(baked, "EEVEE") == bpy.data.node_groups[GROUP_NAME]
    assert not any(g.name.endswith(" (Cycles)") for g in bpy.data.node_groups)  # the old per-renderer graph
    assert measured["node_group"] == GROUP_NAME and measured["nodes"] > 0
    atlas, _ = read_texel_maps(tmp_path)
    texels, lightfield = read_images(tmp_path / "lightfield")
    _, sky = read_images(tmp_path / "env_occluded")
    normals = channels(atlas, "N.X", 3)[texels[:, 0], texels[:, 1]]
    # The sky is most of the light here, so a comparison with the total would be off by well over half.
    assert irradiance_from_lightfields(sky, normals).sum() > 2 * irradiance_from_lightfields(lightfield, normals).sum()
    assert measured["irradiance_from_sgs_rel_error_median"] < 0.5  # 0.24 measured; the sky-lit total gave 1.0
    remove_bake(scene)
    assert GROUP_NAME not in bpy.data.node_groups


def test_eevee_shader_failures_are_read_from_the_render_log():
    """EEVEE draws a material whose shader fails to compile in magenta and goes on; the evaluate stage names it.
    The log is what Blender 5.0.1 printed for the baked courtyard (docs/design-additions.md §13)."""
    from sg_lightfield.blender_addon.evaluate import shader_errors

    log = ("00:17.263  gpu.shader       | ERROR MAGlossy Ground (SG bake) Linking: \n"
           "                            |       | Error: Uniform block node_tree too big (125168/65536)\n"
           "                            | \n"
           "00:26.411  render           | Saved: 'ev/BLENDER_EEVEE_0.exr'\n")
    assert shader_errors(log) == ["Glossy Ground (SG bake): Uniform block node_tree too big (125168/65536)"]
    assert shader_errors(log + log) == shader_errors(log)  # one line per material, whatever the view count
    assert shader_errors("00:26.411  render           | Saved: 'ev/BLENDER_EEVEE_0.exr'\n") == []


def _emission_material(name, color_socket_of):
    """A material whose surface is Emission(colour); `color_socket_of(tree)` builds the nodes and returns the colour."""
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    emission = tree.nodes.new("ShaderNodeEmission")
    tree.links.new(color_socket_of(tree), emission.inputs["Color"])
    tree.links.new(emission.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return mat


def _sg_group_material(name, group):
    def build(tree):
        node = tree.nodes.new("ShaderNodeGroup")
        node.node_tree = group
        tree.links.new(tree.nodes.new("ShaderNodeUVMap").outputs[0], node.inputs["UV"])
        tree.links.new(tree.nodes.new("ShaderNodeNewGeometry").outputs["Normal"], node.inputs["Normal"])
        node.inputs["Roughness"].default_value = 0.3
        node.inputs["F0"].default_value = (0.04, 0.5, 1.0, 1.0)
        node.inputs["Albedo"].default_value = (0.8, 0.5, 0.2, 1.0)
        return node.outputs["Total"]
    return _emission_material(name, build)


def _random_env_sgs(rng):
    return [(tuple(m.safe_normalize(rng.normal(size=3))), float(rng.uniform(1, 100)), (1.0, 0.8, 0.6))
            for _ in range(ENV_SG_COUNT)]


def _largest_groups_cells(n, iwev, h, w, rng):
    """Random parameter cells (h, w) of n SGs, iwev IWEV SGs and the irradiance."""
    cells = {("irradiance", 0): np.concatenate([rng.uniform(0, 3, (h, w, 3)), np.ones((h, w, 1))], -1)}
    for j in range(n):
        cells[("sg", j)] = np.concatenate([rng.normal(size=(h, w, 3)), rng.uniform(0.2, 0.8, (h, w, 1))], -1)
        cells[("amp", j)] = np.concatenate([rng.uniform(0, 5, (h, w, 3)), np.zeros((h, w, 1))], -1)
    for j in range(iwev):
        cells[("iwev", j)] = np.concatenate([rng.normal(size=(h, w, 3)), rng.uniform(0, 1, (h, w, 1))], -1)
        cells[("iwev_amp", j)] = np.concatenate([rng.uniform(0, 0.5, (h, w, 3)), np.zeros((h, w, 1))], -1)
    return cells


def test_every_sg_count_the_settings_allow_fits_eevees_uniform_block():
    """EEVEE gives a material at most 64 KiB of uniforms; the group used to need 5388 bytes per SG (courtyard's IWEV
    materials rendered magenta from 8 SGs on). Now the most the settings allow (64 SGs, 16 IWEV SGs, 16 environment
    SGs) fits, and the presets' largest (16/16/16) uses a quarter of it."""
    from sg_lightfield.bake_directory.bake_plan import BakeInputError
    from sg_lightfield.shaders.node_group import UNIFORM_BLOCK_LIMIT, eevee_uniform_bytes

    with pytest.raises(BakeInputError):
        BakeSettings.from_preset("draft", sg_count=65)  # 64 is the most a bake can ask for
    env_sgs = _random_env_sgs(np.random.default_rng(3))
    image = bpy.data.images.new("uniform budget", 8, 8, float_buffer=True)
    sizes = {}
    for n in (16, 64):
        group = build_node_group(image, SGTextureLayout(n, iwev_count=16, atlas_size=(8, 8)), env_sgs,
                                 name=f"SG Lightfield uniform budget {n}")
        sizes[n] = eevee_uniform_bytes(_sg_group_material(f"uniform budget {n}", group))["bytes"]
    assert sizes[64] < UNIFORM_BLOCK_LIMIT, sizes
    assert sizes[16] < UNIFORM_BLOCK_LIMIT / 3, sizes  # measured 16608 (was 125168 with the old builder)
    assert (sizes[64] - sizes[16]) / 48 < 800, sizes  # bytes per SG (measured ~470; was 5388)


def test_eevee_compiles_the_largest_group_and_its_uniform_block_is_what_we_count(tmp_path):
    """One EEVEE render of two planes: the presets' largest group (16 SGs, 16 IWEV SGs, 16 environment SGs) compiles
    and shades as Cycles does; a material made to overflow the block fails as EEVEE does (magenta), and the size
    Blender reports for it is exactly `eevee_uniform_bytes`."""
    import subprocess
    import sys
    from pathlib import Path

    from sg_lightfield.blender_addon.evaluate import shader_errors
    from sg_lightfield.bake_directory.image_metrics import tonemap
    from sg_lightfield.shaders.node_group import UNIFORM_BLOCK_LIMIT, eevee_uniform_bytes

    n, iwev, h, w = 16, 16, 4, 4
    rng = np.random.default_rng(2)
    layout = SGTextureLayout(n, iwev_count=iwev, has_irradiance=True, atlas_size=(2 * w, 2 * h))
    env_sgs = _random_env_sgs(rng)
    tiles = {key: np.repeat(np.repeat(value, 2, axis=0), 2, axis=1)
             for key, value in _largest_groups_cells(n, iwev, h, w, rng).items()}
    path = write_exr(tmp_path / "packed.exr", pack_tiles(layout, tiles, (2 * h, 2 * w)), precision="half",
                     channels=["R", "G", "B", "A"])
    image = bpy.data.images.load(str(path))
    image.colorspace_settings.name, image.alpha_mode = "Non-Color", "CHANNEL_PACKED"
    image.pack()
    group = build_node_group(image, layout, env_sgs, name="SG Lightfield EEVEE uniform check")
    baked = _sg_group_material("Largest bake", group)

    def overflowing_chain(tree):  # each Vector Math Scale leaves its two unused vector inputs as uniforms
        value = tree.nodes.new("ShaderNodeNewGeometry").outputs["Normal"]
        for _ in range(2200):
            node = tree.nodes.new("ShaderNodeVectorMath")
            node.operation = "SCALE"
            tree.links.new(value, node.inputs[0])
            node.inputs["Scale"].default_value = 1.0
            value = node.outputs[0]
        return value
    overflowing = _emission_material("Overflowing", overflowing_chain)
    expected = {mat.name: eevee_uniform_bytes(mat)["bytes"] for mat in (baked, overflowing)}
    assert expected["Largest bake"] <= UNIFORM_BLOCK_LIMIT < expected["Overflowing"], expected

    scene = bpy.data.scenes.new("eevee uniforms")
    for x, mat in ((-1.1, baked), (1.1, overflowing)):
        mesh = bpy.data.meshes.new(mat.name)
        bm = bmesh.new()
        bm.loops.layers.uv.new("UVMap")
        bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=1.0, calc_uvs=True)
        bm.to_mesh(mesh)
        mesh.materials.append(mat)
        plane = bpy.data.objects.new(mat.name, mesh)
        plane.location.x = x
        scene.collection.objects.link(plane)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type, camera.data.ortho_scale, camera.location = "ORTHO", 4.4, (0, 0, 5)
    scene.collection.objects.link(camera)
    scene.camera, scene.world = camera, bpy.data.worlds.new("black")
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 32, 100
    blend = tmp_path / "uniforms.blend"
    with active_scene(scene), quiet_stdout():
        bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    script = Path(__file__).resolve().parent.parent / "blender_addon" / "eevee_worker.py"
    out = subprocess.run([sys.executable, str(script), str(blend), scene.name, str(tmp_path), "--engines",
                          "BLENDER_EEVEE,CYCLES", "--samples", "4"], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    log = out.stdout + "\n" + out.stderr
    failed = shader_errors(log)
    assert len(failed) == 1 and "Overflowing" in failed[0], failed
    reported = re.search(r"Uniform block node_tree too big \((\d+)/65536\)", log)
    assert reported and int(reported.group(1)) == expected["Overflowing"], (reported, expected)
    eevee = read_exr(tmp_path / "BLENDER_EEVEE_0.exr", channels=["R", "G", "B"])[0]
    cycles = read_exr(tmp_path / "CYCLES_0.exr", channels=["R", "G", "B"])[0]
    left, right = np.s_[8:24, 6:26], np.s_[8:24, 38:58]  # inside each plane
    magenta = np.all(eevee == (1.0, 0.0, 1.0), axis=-1)  # what EEVEE draws for a shader that failed
    assert magenta[right].all() and not magenta[left].any()
    assert tonemap(cycles[left]).min() > 0.1  # the bake's plane is lit
    assert np.abs(tonemap(eevee[left]) - tonemap(cycles[left])).mean() < 0.01  # same nodes, two engines
    for mat in (baked, overflowing):
        bpy.data.materials.remove(mat)


def test_evaluation_cameras_see_the_baked_objects_from_inside_a_closed_room():
    """The views orbiting the baked objects stood outside room's walls and rendered black (half of every room
    score was a black frame); now each looks at the baked objects' centre with no other surface in between."""
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.evaluate import _view_cameras

    scene = build_demo_scene("demo:room")
    plan = build_plan(scene, BakeSettings.from_preset("draft"))
    corners = [scene.objects[o.name].matrix_world @ Vector(c) for o in plan.baked_objects
               for c in scene.objects[o.name].bound_box]
    centre = Vector([(min(c[i] for c in corners) + max(c[i] for c in corners)) / 2 for i in range(3)])
    cameras = _view_cameras(scene, plan, 3)
    assert [made for _, made in cameras] == [False, True, True]
    with active_scene(scene) as depsgraph:
        for camera, _ in cameras[1:]:
            to_centre = centre - camera.location
            hit, _, _, _, obj, _ = scene.ray_cast(depsgraph, camera.location, to_centre.normalized(),
                                                  distance=to_centre.length)
            assert not hit or obj.original.name in {o.name for o in plan.baked_objects}, obj.name
    for camera, made in cameras:
        if made:
            data = camera.data
            bpy.data.objects.remove(camera)
            bpy.data.cameras.remove(data)


def test_the_evaluation_pictures_have_the_scene_cameras_aspect():
    from sg_lightfield.blender_addon.evaluate import evaluation_resolution

    scene = bpy.data.scenes.new("aspect")
    try:
        render = scene.render
        for size, expected in (((1920, 1080), (256, 144)), ((1080, 1920), (144, 256)), ((1000, 1000), (192, 192))):
            render.resolution_x, render.resolution_y = size
            assert evaluation_resolution(scene) == expected
        render.resolution_x, render.resolution_y, render.pixel_aspect_x = 1000, 1000, 2.0  # anamorphic pixels
        width, height = evaluation_resolution(scene)
        assert abs(width / height - 2.0) < 0.02 and abs(width * height - 256 * 144) < 300
    finally:
        bpy.data.scenes.remove(scene)
