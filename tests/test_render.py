"""Render stage with real Cycles renders (small sizes, CPU): the custom OSL camera, lamps, IWEV, resume."""
import bpy  # noqa: I001
import bmesh
import math
import tempfile
import numpy as np
import pytest
from mathutils import Matrix

from sg_lightfield.blender_addon.capture import capture
from sg_lightfield.blender_addon.render import (ENV_VISIBILITY_ESTIMATOR, MIDPOINT_SAMPLES_FACTOR, optix_devices,
                                                render_stage)
from sg_lightfield.blender_addon.scene_analysis import build_plan, enable_nodes
from sg_lightfield.bake_directory.bake_plan import BakeCancelled, BakeInputError, BakeSettings
from sg_lightfield.shaders.env_visibility import above_horizon_fraction
from sg_lightfield.bake_directory.exr_io import read_exr, read_exr_metadata, write_exr
from sg_lightfield.bake_directory.lightfield_tiles import read_images, read_index
from sg_lightfield.shaders.octahedral import direction_to_pixel, pixel_directions
from sg_lightfield.bake_directory.texel_maps import channels, read_texel_maps, texels_of_objects
from tests.scene_helpers import cube, material, mesh_object, scene_with, uniform_world, uv_sphere

pytestmark = pytest.mark.slow


def _emissive(name, strength, color=(1.0, 1.0, 1.0)):
    """A pure emitter: radiance = strength * color, and it reflects nothing."""
    mat = bpy.data.materials.new(name)
    enable_nodes(mat)
    nodes = mat.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (*color, 1)
    emission.inputs["Strength"].default_value = strength
    mat.node_tree.links.new(emission.outputs[0], nodes["Material Output"].inputs["Surface"])
    return mat


def _optix_gpus():
    return [entry.name for entry in optix_devices()]


def _bake(scene, out, resolution=16, samples=4, density=2.0, device="cpu", **kwargs):
    plan = build_plan(scene, BakeSettings.from_preset("draft", lightfield_resolution=resolution, samples=samples,
                                                      texel_density=density, device=device))
    capture(scene, plan, out)
    result = render_stage(scene, plan, out, **kwargs)
    atlas, _ = read_texel_maps(out)
    return plan, result, atlas


def _texel_data(atlas, texels):
    r, c = texels[:, 0], texels[:, 1]
    return channels(atlas, "P.X", 3)[r, c].astype(float), channels(atlas, "Ng.X", 3)[r, c].astype(float)


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_probe_emitters_land_on_the_predicted_pixels_for_all_six_faces_of_a_box(tmp_path, device):
    if device == "cuda" and not _optix_gpus():
        pytest.skip("no OptiX GPU here (the CPU case runs; the device check ran this on an H100)")
    resolution = 16
    grid = pixel_directions(resolution)
    probes = [grid[4, 11], -grid[4, 11]]  # a pixel centre and its antipode: every face sees exactly one
    objects = [mesh_object("Box", cube(1.0), material("glossy", 0.2))]
    for i, d in enumerate(probes):
        objects.append(mesh_object(f"Probe {i}", uv_sphere(3.0, 16, 8), _emissive(f"probe {i}", 50.0)))
        objects[-1].location = 40.0 * d
    scene = scene_with(*objects)
    uniform_world(scene, (0, 0, 0))
    plan, result, atlas = _bake(scene, tmp_path, resolution=resolution, samples=4, density=4.0, device=device)
    texels, images = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    positions, normals = _texel_data(atlas, texels)
    faces = set()
    for p, n, image in zip(positions, normals, images):
        seen = [d for d in probes if d @ n > 0]
        assert len(seen) == 1
        target = 40.0 * seen[0] - p
        row, col = direction_to_pixel(target / np.linalg.norm(target), resolution)
        luminance = image.sum(axis=-1)
        assert np.unravel_index(np.argmax(luminance), luminance.shape) == (row, col)
        faces.add(tuple(np.round(n).astype(int)))
    assert len(faces) == 6


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_energy_inside_an_emitting_sphere_and_nothing_below_the_horizon(tmp_path, device):
    if device == "cuda" and not _optix_gpus():
        pytest.skip("no OptiX GPU here (the CPU case runs; the device check ran this on an H100)")
    radiance = 2.5
    shell = mesh_object("Shell", uv_sphere(6.0, 32, 16), _emissive("shell", radiance))
    floor = mesh_object("Disc", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                        material("glossy", 0.2))
    scene = scene_with(shell, floor)
    uniform_world(scene, (0, 0, 0))
    plan, result, atlas = _bake(scene, tmp_path, resolution=16, samples=4, density=4.0, midpoints=6, device=device)
    assert result.devices == (["CPU"] if device == "cpu" else _optix_gpus())
    texels, images = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    _, normals = _texel_data(atlas, texels)
    fraction = above_horizon_fraction(normals, 16).reshape(-1, 16, 16)
    pairs, held_out = read_images(tmp_path / "midpoints", plan.stage_hash("render"))
    assert pairs.shape == (6, 4) and held_out.shape == (6, 16, 16, 3)
    assert read_index(tmp_path / "midpoints").samples == 4 * MIDPOINT_SAMPLES_FACTOR  # a cleaner reference
    np.testing.assert_allclose(held_out[fraction[:6] == 1.0], radiance, rtol=2e-3)  # midpoints see the shell too
    full, none = fraction == 1.0, fraction == 0.0
    assert full.sum() > 0 and none.sum() > 0
    np.testing.assert_allclose(images[full], radiance, rtol=2e-3)  # uniform emitter: no noise, half precision
    assert np.all(images[none] == 0.0)
    partial = ~full & ~none  # straddling the horizon: the cut keeps the same fraction (noisy at 4 spp)
    assert images[partial].mean() == pytest.approx(radiance * fraction[partial].mean(), rel=0.05)


def test_device_cuda_without_an_optix_gpu_is_one_clear_error_and_changes_no_setting(tmp_path):
    if _optix_gpus():
        pytest.skip("an OptiX GPU is here")
    floor = mesh_object("Disc", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                        material("glossy", 0.2))
    scene = scene_with(floor)
    preferences = bpy.context.preferences.addons["cycles"].preferences
    backend_before, device_before = preferences.compute_device_type, scene.cycles.device
    datablocks_before = {name: len(getattr(bpy.data, name)) for name in ("scenes", "cameras", "materials", "worlds",
                                                                           "texts", "lights", "objects")}
    with pytest.raises(BakeInputError, match="no OptiX GPU.*--device cpu"):
        _bake(scene, tmp_path, device="cuda")
    assert preferences.compute_device_type == backend_before and scene.cycles.device == device_before
    assert {name: len(getattr(bpy.data, name)) for name in datablocks_before} == datablocks_before


def test_a_bake_leaves_nothing_in_the_temp_directory(tmp_path, monkeypatch):
    """Cycles' OSL compiler leaves the compiled camera shader (.oso) in the temp directory; the stage must not."""
    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    scene = scene_with(mesh_object("Disc", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                                   material("glossy", 0.2)))
    uniform_world(scene, (0.5, 0.5, 0.5))
    _bake(scene, tmp_path / "bake", resolution=8, samples=1, density=2.0)
    assert list(temp.iterdir()) == []


def test_midpoints_on_a_curved_surface_lie_on_it_and_see_what_its_texels_see(tmp_path):
    """The chord midpoint of two texels of a sphere lies inside it; the held-out midpoint must be rendered from the
    surface (it rendered black from inside before), seeing the emitting shell above its own horizon."""
    radiance = 2.5
    shell = mesh_object("Shell", uv_sphere(6.0, 32, 16), _emissive("shell", radiance))
    ball = mesh_object("Ball", uv_sphere(0.5, 48, 24), material("glossy", 0.2))
    scene = scene_with(shell, ball)
    uniform_world(scene, (0, 0, 0))
    plan, _, atlas = _bake(scene, tmp_path, resolution=16, samples=4, density=6.0, midpoints=8)
    pairs, held_out = read_images(tmp_path / "midpoints", plan.stage_hash("render"))
    assert len(pairs) == 8
    p1, n1 = _texel_data(atlas, pairs[:, :2])
    p2, n2 = _texel_data(atlas, pairs[:, 2:])
    chord = np.linalg.norm(0.5 * (p1 + p2), axis=1)
    assert np.all(chord < 0.5 - 1e-3)  # the chord midpoints really are inside the ball
    normal = (n1 + n2) / np.linalg.norm(n1 + n2, axis=1, keepdims=True)
    full = above_horizon_fraction(normal, 16).reshape(-1, 16, 16) == 1.0
    assert full.sum() > 8 * 100
    assert np.median(held_out[full]) == pytest.approx(radiance, rel=2e-3)
    # Near the blended horizon the tessellated ball's own faces take a few rays (measured: 2 % of pixels, -3.75 %).
    np.testing.assert_allclose(held_out[full], radiance, rtol=0.05)



def test_metal_objects_render_in_tiles_that_leave_out_a_glossy_bounce(tmp_path):
    """A metal's own scattering in the bake is glossy: its texels, and the held-out midpoints on it, render in tiles
    of their own with a glossy bounce left out; a dielectric's leave out a diffuse one."""
    metal = mesh_object("Metal", uv_sphere(0.5), material("metal", 0.3, metallic=1.0))
    glass = mesh_object("Dielectric", uv_sphere(0.5), material("dielectric", 0.3))
    glass.location.x = 2.0
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.location = (1, 2, 2)
    scene = scene_with(metal, glass, lamp)
    uniform_world(scene, (0, 0, 0))
    plan, _, atlas = _bake(scene, tmp_path, resolution=8, samples=2, density=4.0, midpoints=40)
    info = read_texel_maps(tmp_path)[1]
    for kind in ("lightfield", "midpoints"):
        for tile in read_index(tmp_path / kind).tiles:
            on_metal = texels_of_objects(atlas, info, np.asarray(tile.texels)[:, :2], [metal.name])
            assert on_metal.all() if tile.file.startswith("metal_") else not on_metal.any()
            assert tile.bounce_left_out == ("glossy" if tile.file.startswith("metal_") else "diffuse")
        assert any(t.file.startswith("metal_") for t in read_index(tmp_path / kind).tiles)


def test_point_and_area_lamps_are_in_the_light_field_and_stay_untouched(tmp_path):
    plane = mesh_object("Plane", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                        material("glossy", 0.2))
    point = bpy.data.objects.new("Point", bpy.data.lights.new("Point", "POINT"))
    point.data.energy, point.data.shadow_soft_size = 200.0, 0.0
    point.location = (3.0, 0.0, 3.0)
    area = bpy.data.objects.new("Area", bpy.data.lights.new("Area", "AREA"))
    area.data.energy, area.data.size = 200.0, 1.0
    area.matrix_world = Matrix.Translation((-3.0, 0.0, 3.0)) @ Matrix.Rotation(-np.pi / 4, 4, "Y")
    scene = scene_with(plane, point, area)
    uniform_world(scene, (0, 0, 0))
    plan, result, atlas = _bake(scene, tmp_path, resolution=16, samples=16, density=4.0)
    texels, images = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    positions, _ = _texel_data(atlas, texels)
    for lamp in (point, area):
        hits = []
        for p, image in zip(positions, images):
            d = np.array(lamp.location) - p
            row, col = direction_to_pixel(d / np.linalg.norm(d), 16)
            hits.append(image[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].sum())
        assert np.median(hits) > 1.0, lamp.name  # the lamp's radiance is there, the black world is 0
    assert not point.visible_camera and point.data.shadow_soft_size == 0.0  # the user's lamp is unchanged
    assert len([s for s in bpy.data.scenes if s.name.startswith("SGLF render")]) == 0


def test_environment_visibility_open_sky_roof_and_roughness(tmp_path):
    ground = {}
    for name, rough, y in (("Smooth", 0.15, -1.0), ("Rough", 0.55, 1.0)):
        ground[name] = mesh_object(name, lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1,
                                                                          size=0.5), material(name, rough))
        ground[name].matrix_world = Matrix.Translation((0.0, y, 0.0)) @ Matrix.Diagonal((16.0, 2.0, 1.0, 1.0))
    roof = mesh_object("Roof", cube(1.0), material("roof", 0.9))
    roof.matrix_world = Matrix.Translation((-4.0, 0.0, 0.4)) @ Matrix.Diagonal((8.0, 8.0, 0.2, 1.0))
    scene = scene_with(*ground.values(), roof)
    uniform_world(scene, (1.0, 1.0, 1.0))
    plan, result, atlas = _bake(scene, tmp_path, resolution=16, samples=8, density=4.0)
    assert plan.environment.iwev and plan.environment.iwev_channels == 1
    texels, w = read_images(tmp_path / "env_visibility", plan.stage_hash("render"))
    positions, normals = _texel_data(atlas, texels)
    zenith = direction_to_pixel(np.array([0.0, 0.0, 1.0]), 16)
    w_up = w[:, zenith[0], zenith[1], 0]
    assert np.all((w >= 0) & (w <= 1))
    open_sky = positions[:, 0] > 3.0
    away_from_roof = (pixel_directions(16)[..., 0] > 0) & (pixel_directions(16)[..., 2] > 0.2)
    np.testing.assert_allclose(w[open_sky][:, away_from_roof], 1.0, atol=0.04)  # 8 spp at the horizon
    under_roof = (positions[:, 0] < -3.0) & (positions[:, 0] > -5.0) & (positions[:, 2] < 0.1)  # the roof is baked too
    assert w_up[under_roof].max() < 0.05
    # Just outside the roof's edge the zenith is open: a smooth lobe sees mostly sky, a rough one also the roof.
    edge = (positions[:, 0] > 0.0) & (positions[:, 0] < 0.4)
    smooth, rough = edge & (positions[:, 1] < 0), edge & (positions[:, 1] > 0)
    assert w_up[smooth].mean() > w_up[rough].mean() + 0.05
    # The world is IWEV's: the light field's sky is black, while the roof it lights still shows up in it.
    _, lightfield = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    assert lightfield[open_sky][:, zenith[0], zenith[1]].max() == 0.0
    assert lightfield[open_sky].max() > 0.1


def _world_with_a_small_lamp(scene, direction, cos_radius, dim=0.2, bright=400.0):
    """A dim world with one bright disc (an HDRI's small wall lamp) of angular radius acos(cos_radius) about
    `direction`: its octahedral pixel's radiance varies far more than a pixel's few samples average out."""
    world = uniform_world(scene, (dim, dim, dim), name="small lamp world")
    nodes, links = world.node_tree.nodes, world.node_tree.links
    coordinates = nodes.new("ShaderNodeTexCoord")
    towards = nodes.new("ShaderNodeVectorMath")
    towards.operation = "DOT_PRODUCT"
    towards.inputs[1].default_value = direction
    inside = nodes.new("ShaderNodeMath")
    inside.operation = "GREATER_THAN"
    inside.inputs[1].default_value = cos_radius
    strength = nodes.new("ShaderNodeMapRange")
    strength.inputs["To Min"].default_value, strength.inputs["To Max"].default_value = 1.0, bright / dim
    links.new(coordinates.outputs["Generated"], towards.inputs[0])
    links.new(towards.outputs["Value"], inside.inputs[0])
    links.new(inside.outputs[0], strength.inputs["Value"])
    links.new(strength.outputs["Result"], nodes["Background"].inputs["Strength"])


def test_environment_visibility_of_open_sky_is_one_under_a_small_bright_lamp(tmp_path):
    """W_E comes from the texel's visibility, not from a few samples of the world's detail: an open floor under a
    2-degree lamp at 8 spp sees the lamp's pixel with W_E 1, as every other open pixel (rendered against the world
    itself, that pixel's L_E*V / L_E was a noisy ratio, clipped at 1: W_E down to 0.01 there)."""
    floor = mesh_object("Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=2.0),
                        material("floor", 0.15))
    scene = scene_with(floor)
    lamp = np.array([0.6, 0.0, 0.8])
    _world_with_a_small_lamp(scene, tuple(lamp), math.cos(math.radians(2.0)))
    plan, _, _ = _bake(scene, tmp_path, resolution=16, samples=8, density=2.0)
    assert plan.environment.iwev
    _, w = read_images(tmp_path / "env_visibility", plan.stage_hash("render"))
    _, sky = read_images(tmp_path / "env_occluded", plan.stage_hash("render"))
    row, col = direction_to_pixel(lamp, 16)
    upward = pixel_directions(16)[..., 2] > 0.2
    np.testing.assert_allclose(w[:, upward], 1.0, atol=1e-3)
    assert w[:, row, col].min() > 0.999
    # env_occluded is L_E*V: the open sky's own radiance, the lamp's pixel as bright in every texel
    lamp_pixel = sky[:, row, col].mean(axis=-1)
    assert lamp_pixel.min() > 2.0 and lamp_pixel.max() - lamp_pixel.min() < 1e-2 * lamp_pixel.max()
    tile = tmp_path / "env_occluded" / read_index(tmp_path / "env_occluded").tiles[0].file
    metadata = read_exr_metadata(tile)
    assert metadata.pop("visibility") == ENV_VISIBILITY_ESTIMATOR
    assert render_stage(scene, plan, tmp_path).tiles_rendered["env_visibility"] == 0  # finished: kept
    # a tile made by the estimator before, against the world itself, is rendered again
    write_exr(tile, read_exr(tile)[0], channels=["R", "G", "B"], metadata=metadata)
    assert render_stage(scene, plan, tmp_path).tiles_rendered["env_visibility"] == 1
    assert read_exr_metadata(tile)["visibility"] == ENV_VISIBILITY_ESTIMATOR


def _lit_ball():
    """A glossy ball under a point lamp and a tiny Draft plan of it: (object, scene, plan)."""
    obj = mesh_object("Ball", uv_sphere(1.0), material("glossy", 0.2))
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.location = (2, 2, 2)
    scene = scene_with(obj, lamp)
    uniform_world(scene, (0, 0, 0))
    settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=4, texel_density=4.0)
    return obj, scene, build_plan(scene, settings)


def test_resume_after_cancel_renders_only_the_rest_and_farm_shares_merge(tmp_path):
    obj, scene, plan = _lit_ball()
    for out in (tmp_path / "resumed", tmp_path / "fresh", tmp_path / "farm"):
        capture(scene, plan, out)
    calls = []

    def cancel_after_two():
        calls.append(1)
        return len(calls) > 3  # asked at the stage's start and after each tile

    with pytest.raises(BakeCancelled):
        render_stage(scene, plan, tmp_path / "resumed", max_tile_megapixels=0.003, should_cancel=cancel_after_two)
    resumed = render_stage(scene, plan, tmp_path / "resumed", max_tile_megapixels=0.003)
    total = resumed.tiles_rendered["lightfield"] + resumed.tiles_skipped["lightfield"]
    assert resumed.tiles_skipped["lightfield"] == 2 and total > 3
    with pytest.raises(Exception, match="not rendered"):
        render_stage(scene, plan, tmp_path / "farm", max_tile_megapixels=0.003, share="1/2")
        read_images(tmp_path / "farm" / "lightfield", plan.stage_hash("render"))
    second = render_stage(scene, plan, tmp_path / "farm", max_tile_megapixels=0.003, share="2/2")
    assert second.tiles_rendered["lightfield"] == total // 2
    render_stage(scene, plan, tmp_path / "fresh", max_tile_megapixels=0.003)
    reference = read_images(tmp_path / "fresh" / "lightfield", plan.stage_hash("render"))
    for out in ("resumed", "farm"):
        texels, images = read_images(tmp_path / out / "lightfield", plan.stage_hash("render"))
        np.testing.assert_array_equal(texels, reference[0])
        np.testing.assert_array_equal(images, reference[1])  # deterministic: identical, not merely close



def test_a_tile_rendered_for_other_texel_positions_is_rendered_again(tmp_path):
    """Tiles are keyed by what the camera renders each texel from, not only by the texels' atlas cells: after the
    object moves and is captured again into the same directory (same atlas, other surface points), no tile is
    taken as finished, and the light fields are those of the new positions."""
    obj, scene, plan = _lit_ball()
    capture(scene, plan, tmp_path / "bake")
    first = render_stage(scene, plan, tmp_path / "bake", max_tile_megapixels=0.003)
    obj.location.z += 3.0
    capture(scene, plan, tmp_path / "bake")
    capture(scene, plan, tmp_path / "moved")
    again = render_stage(scene, plan, tmp_path / "bake", max_tile_megapixels=0.003)
    assert again.tiles_skipped["lightfield"] == 0
    assert again.tiles_rendered["lightfield"] == first.tiles_rendered["lightfield"] > 1
    render_stage(scene, plan, tmp_path / "moved", max_tile_megapixels=0.003)
    np.testing.assert_array_equal(read_images(tmp_path / "bake" / "lightfield", plan.stage_hash("render"))[1],
                                  read_images(tmp_path / "moved" / "lightfield", plan.stage_hash("render"))[1])


def _equirect_to_octahedral(pixels, normal, resolution):
    """Average an equirectangular render (camera at identity: image centre = -Z, top = +Y) into octahedral
    pixels by solid angle; returns the image and the mask of pixels that got samples."""
    h, w, _ = pixels.shape
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    lon = ((np.arange(w) + 0.5) / w - 0.5) * 2 * np.pi
    lon, lat = np.meshgrid(lon, lat)
    d = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), -np.cos(lat) * np.cos(lon)], axis=-1)
    row, col = direction_to_pixel(d.reshape(-1, 3), resolution)
    weight = (np.cos(lat) * (d @ normal > 0)).ravel()
    flat = row * resolution + col
    total = np.bincount(flat, weight, resolution * resolution)
    out = np.stack([np.bincount(flat, weight * pixels[..., k].ravel(), resolution * resolution) for k in range(3)], -1)
    return (out / np.maximum(total, 1e-30)[:, None]).reshape(resolution, resolution, 3), total.reshape(resolution,
                                                                                                      resolution) > 0


def test_atlas_light_field_equals_a_panoramic_render_of_the_same_texel(tmp_path):
    resolution = 16
    floor = mesh_object("Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                        material("glossy", 0.3))
    floor.scale = (4, 4, 1)
    panel = mesh_object("Panel", cube(1.0), _emissive("panel", 4.0, (1.0, 0.8, 0.6)))
    panel.matrix_world = Matrix.Translation((1.5, 0.5, 1.5)) @ Matrix.Diagonal((1.0, 2.0, 0.2, 1.0))
    wall = mesh_object("Wall", cube(1.0), material("wall", 0.9))
    wall.matrix_world = Matrix.Translation((-1.5, 0.0, 1.0)) @ Matrix.Diagonal((0.2, 3.0, 2.0, 1.0))
    scene = scene_with(floor, panel, wall)
    uniform_world(scene, (0.05, 0.1, 0.2))
    scene.world["sglf_test"] = True
    plan = build_plan(scene, BakeSettings.from_preset("draft", lightfield_resolution=resolution, samples=64,
                                                      texel_density=2.0))
    plan.environment.iwev = False  # compare the full light field, world included, with the panorama
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    atlas, _ = read_texel_maps(tmp_path)
    texels, images = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    positions, normals = _texel_data(atlas, texels)
    k = int(np.argmin(np.linalg.norm(positions[:, :2], axis=1)))
    offset = channels(atlas, "ray_offset")[texels[k, 0], texels[k, 1]]
    camera = bpy.data.objects.new("Pano", bpy.data.cameras.new("Pano"))
    camera.data.type, camera.data.panorama_type = "PANO", "EQUIRECTANGULAR"
    camera.data.clip_start, camera.data.clip_end = 1e-6, 1e6
    camera.location = positions[k] + normals[k] * offset
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising = 64, False
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 256, 128, 100
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(tmp_path / "pano.exr")
    from sg_lightfield.blender_addon.render import quiet_stdout
    from sg_lightfield.blender_addon.scene_analysis import active_scene
    with active_scene(scene), quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    pano, _, _ = read_exr(tmp_path / "pano.exr", channels=["R", "G", "B"])
    reference, seen = _equirect_to_octahedral(pano, normals[k], resolution)
    full = (above_horizon_fraction(normals[k:k + 1], resolution)[0] == 1.0).reshape(resolution, resolution) & seen
    ours = images[k][full]
    theirs = reference[full]
    assert ours.sum() == pytest.approx(theirs.sum(), rel=0.05)  # same energy
    rmse = np.sqrt(np.mean((ours - theirs) ** 2))
    assert rmse < 0.15 * theirs.mean()  # same picture within the noise of 64 spp on both sides



def _panorama_at(scene, tmp_path, location, name, samples=64):
    from sg_lightfield.blender_addon.render import quiet_stdout
    from sg_lightfield.blender_addon.scene_analysis import active_scene
    camera = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    camera.data.type, camera.data.panorama_type = "PANO", "EQUIRECTANGULAR"
    camera.data.clip_start, camera.data.clip_end = 1e-6, 1e6
    camera.location = location
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising = samples, False
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 256, 128, 100
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(tmp_path / f"{name}.exr")
    with active_scene(scene), quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    return read_exr(tmp_path / f"{name}.exr", channels=["R", "G", "B"])[0]


def test_the_light_field_leaves_out_the_bounce_the_baked_surface_adds(tmp_path):
    """Inside a closed white box with one diffuse bounce allowed, the floor's light field holds the walls lit
    directly (diffuse bounces 0), as a panorama from the texel with the scene's budget less one sees it: the baked
    floor's own scattering is then the path's one diffuse bounce, as in the scene's renders. With the scene's own
    budget (the rule before) the light field held 1.4x as much light, and the demo room's walls came out 4-9 %
    too bright."""
    resolution = 16

    def inward_box(bm):
        bmesh.ops.create_cube(bm, size=4.0)
        bmesh.ops.reverse_faces(bm, faces=bm.faces)

    box = mesh_object("Box", inward_box, material("white", 1.0))
    panel = mesh_object("Panel", cube(0.5), _emissive("panel", 20.0))  # a mesh: lamps are hidden from panoramas
    panel.location = (0.5, 0.3, 1.0)
    scene = scene_with(box, panel)
    uniform_world(scene, (0, 0, 0))
    scene.cycles.diffuse_bounces = 1
    # irradiance detail 1: the rough box, a lightmap-only object, gets light fields
    plan = build_plan(scene, BakeSettings.from_preset("draft", lightfield_resolution=resolution, samples=64,
                                                      texel_density=1.0, irradiance_detail=1))
    capture(scene, plan, tmp_path)
    render_stage(scene, plan, tmp_path)
    atlas, _ = read_texel_maps(tmp_path)
    texels, images = read_images(tmp_path / "lightfield", plan.stage_hash("render"))
    positions, normals = _texel_data(atlas, texels)
    k = int(np.argmin(np.linalg.norm(positions - (0.0, 0.0, -2.0), axis=1)))  # the floor's centre
    assert normals[k] @ (0, 0, 1) > 0.99
    location = positions[k] + normals[k] * channels(atlas, "ray_offset")[texels[k, 0], texels[k, 1]]
    energy = {}
    for bounces in (0, 1):
        scene.cycles.diffuse_bounces = bounces
        pano = _panorama_at(scene, tmp_path, location, f"pano{bounces}")
        reference, seen = _equirect_to_octahedral(pano, normals[k], resolution)
        full = (above_horizon_fraction(normals[k:k + 1], resolution)[0] == 1.0).reshape(resolution, resolution) & seen
        energy[bounces] = reference[full].sum()
    ours = images[k][full].sum()
    assert energy[1] > 1.3 * energy[0]  # the bounce the bake adds is a large share of the light in a white box
    assert ours == pytest.approx(energy[0], rel=0.05)
    assert scene.cycles.diffuse_bounces == 1  # the user's setting is left as it was


def test_nan_and_negative_pixels_in_an_hdri_are_sanitised_with_a_warning(tmp_path):
    plane = mesh_object("Plane", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5),
                        material("glossy", 0.2))
    scene = scene_with(plane)
    uniform_world(scene, (1, 1, 1))
    image = bpy.data.images.new("bad sky", 16, 8, float_buffer=True)
    pixels = np.ones((8, 16, 4), np.float32)
    pixels[2, 3, :3], pixels[5, 9, 0], pixels[6, 1, 1] = np.nan, -4.0, np.inf
    image.pixels.foreach_set(pixels.ravel())
    nodes = scene.world.node_tree.nodes
    env = nodes.new("ShaderNodeTexEnvironment")
    env.image = image
    scene.world.node_tree.links.new(env.outputs["Color"], nodes["Background"].inputs["Color"])
    plan, result, atlas = _bake(scene, tmp_path, resolution=8, samples=4, density=2.0)
    assert any("'bad sky'" in w and "NaN/Inf/negative" in w for w in result.warnings)
    for kind in ("lightfield", "env_visibility"):
        _, images = read_images(tmp_path / kind, plan.stage_hash("render"))
        assert np.all(np.isfinite(images)) and images.min() >= 0
    assert np.isnan(np.array(image.pixels[:]).reshape(8, 16, 4)[2, 3, 0])  # the user's image is untouched


def test_objects_with_lightmaps_only_render_with_the_lightmap_samples_in_tiles_of_their_own(tmp_path):
    """Production renders a lightmap-only floor at 64 spp and the glossy ball at 256: same light, a quarter of the
    rays. Here 2 and 8 spp; the floor's mean radiance agrees with an 8-spp render of it, and the ball's tiles are
    the same texels at the same samples as without the split."""
    ball = mesh_object("Ball", uv_sphere(0.5), material("glossy", 0.3))
    floor = mesh_object("Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=2.0),
                        material("rough", 0.8))
    floor.location = (0, 0, -0.6)
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    lamp.location, lamp.data.energy = (1, 1, 2), 200.0
    scene = scene_with(ball, floor, lamp)
    uniform_world(scene, (0.2, 0.2, 0.2))
    floors = {}
    for lightmap_samples in (2, 0):
        settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=8, texel_density=6.0,
                                            lightmap_samples=lightmap_samples, irradiance_detail=1)
        plan = build_plan(scene, settings)
        out = tmp_path / f"lightmap_{lightmap_samples}"
        capture(scene, plan, out)
        render_stage(scene, plan, out, max_tile_megapixels=0.004)
        index = read_index(out / "lightfield", plan.stage_hash("render"))
        atlas, info = read_texel_maps(out)
        texels, images = read_images(out / "lightfield", plan.stage_hash("render"))
        on_floor = ~texels_of_objects(atlas, info, texels, [ball.name])
        floors[lightmap_samples] = images[on_floor].mean(axis=(0, 1, 2))
        lightmap_tiles = [t for t in index.tiles if t.file.startswith("lightmap_")]
        if lightmap_samples:
            assert lightmap_tiles and all(t.samples == 2 for t in lightmap_tiles), index.tiles
            assert {t.index for t in index.tiles} == set(range(len(index.tiles)))  # farm shares count them all
            for tile in index.tiles:  # each tile says on disk what it was rendered with
                samples = read_exr_metadata(out / "lightfield" / tile.file)["samples"]
                assert samples == ("2" if tile in lightmap_tiles else "8")
                ball_texels = texels_of_objects(atlas, info, np.asarray(tile.texels), [ball.name])
                assert ball_texels.all() if tile not in lightmap_tiles else not ball_texels.any()
            assert any(f"({floor.name}): 2 samples per pixel" in line for line in plan.decisions())
            split_hash, split_estimate = plan.stage_hash("render"), plan.render_estimate_s()
        else:
            assert not lightmap_tiles and all(t.samples == 0 for t in index.tiles)
            assert plan.stage_hash("render") != split_hash  # changing the lightmap samples renders again
            assert split_estimate < 0.6 * plan.render_estimate_s()
    assert np.all(floors[2] > 0)
    np.testing.assert_allclose(floors[2], floors[0], rtol=0.15)  # the same light, with more noise
