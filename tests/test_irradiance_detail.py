"""Diffuse light at its own resolution: the capture's Cycles diffuse bake of the baked surfaces (irradiance_detail.py)
sharpens a lamp's shadow that the light fields' texels blur, agrees with the light fields' own irradiance where the
light is smooth, and is removed with the bake."""
import bpy  # noqa: I001
import bmesh
import numpy as np
import pytest

from sg_lightfield.blender_addon.apply import (DETAIL_IMAGE_NAME, apply_stage, baked_groups,
                                               irradiance_from_lightfields, remove_bake)
from sg_lightfield.blender_addon.capture import capture
from sg_lightfield.blender_addon.irradiance_detail import DETAIL_FILE, texel_means
from sg_lightfield.blender_addon.render import quiet_stdout, render_stage
from sg_lightfield.blender_addon.scene_analysis import active_scene, build_plan
from sg_lightfield.bake_directory.bake_plan import BakeInputError, BakeSettings
from sg_lightfield.bake_directory.bake_report import read_report
from sg_lightfield.bake_directory.exr_io import read_exr, read_exr_metadata
from sg_lightfield.bake_directory.image_metrics import LUMINANCE
from sg_lightfield.bake_directory.lightfield_tiles import read_images
from sg_lightfield.bake_directory.texel_maps import channels, read_texel_maps
from tests.scene_helpers import cube, lit_ortho_scene, material, mesh_fingerprint, mesh_object, scene_with


def _shadow_scene():
    """A rough floor (an irradiance lightmap: no training) 4 m wide with a 0.8 m box on it, a small area lamp beside
    and above the box (a shadow with a sharp edge), a dim grey world; an orthographic camera looking down."""
    rough = material("Rough Floor", roughness=0.9)
    floor = mesh_object("Shadow Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=2.0,
                                                                         calc_uvs=True), rough, uv_map="UVMap")
    box = mesh_object("Shadow Box", cube(0.8), rough)
    box.location = (0.0, 0.0, 0.4)
    scene = lit_ortho_scene(floor, box, name="irradiance detail test", lamp_energy=400.0, lamp_size=0.1,
                            lamp_location=(1.2, 0.6, 2.0), world_color=(0.05, 0.05, 0.05), ortho_scale=3.6,
                            camera_height=5, resolution=72)
    return scene, floor, box


def _render(scene, path, samples):
    scene.cycles.samples = samples
    scene.render.filepath = str(path)
    with active_scene(scene), quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    return read_exr(path, channels=["R", "G", "B"])[0].astype(np.float64) @ LUMINANCE


def _images_read_by(groups) -> set:
    """Names of the images the node groups and the groups nested in them look up."""
    names, stack = set(), list(groups)
    while stack:
        tree = stack.pop()
        for node in tree.nodes:
            if node.bl_idname == "ShaderNodeTexImage" and node.image:
                names.add(node.image.name)
            elif node.bl_idname == "ShaderNodeGroup" and node.node_tree:
                stack.append(node.node_tree)
    return names


@pytest.mark.slow
def test_the_detail_image_sharpens_a_lamp_shadow_and_agrees_with_the_light_fields(tmp_path):
    """Texel density 2 (50 cm texels): the box's shadow blurs over a texel in the light fields' irradiance. Baked at 4x
    the density, the same bake's Cycles render is much closer to the path-traced reference over the floor. The detail
    image's mean over the texels agrees with the light fields' quadrature (two independent estimates); with it, these
    irradiance lightmaps need no light fields at all. Remove takes the image away with the bake and leaves the meshes
    as they were."""
    scene, floor, box = _shadow_scene()
    meshes_before = mesh_fingerprint(floor.data), mesh_fingerprint(box.data)
    reference = _render(scene, tmp_path / "reference.exr", 512)
    errors, reports = {}, {}
    for detail in (1, 4):
        out = tmp_path / f"detail{detail}"
        settings = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=64,
                                            irradiance_detail=detail)
        plan = build_plan(scene, settings)
        assert [m.irradiance_only for o in plan.baked_objects for m in o.materials] == [True, True]
        capture(scene, plan, out)
        assert (out / DETAIL_FILE).is_file() == (detail > 1)
        rendered = render_stage(scene, plan, out)
        assert plan.lightfield_texels == (plan.texels if detail == 1 else 0)
        tiles = len(list((out / "lightfield").glob("*.exr")))
        assert sum(rendered.tiles_rendered.values()) == (0 if detail > 1 else tiles)
        info = apply_stage(scene, plan, out)
        ours = _render(scene, tmp_path / f"ours{detail}.exr", 16)
        errors[detail] = float(np.abs(ours - reference).mean() / reference.mean())
        reports[detail] = info
        images = _images_read_by(baked_groups(floor.material_slots[0].material))
        assert (DETAIL_IMAGE_NAME in images) == (detail > 1), images
        assert remove_bake(scene) == 2
        assert bpy.data.images.get(DETAIL_IMAGE_NAME) is None
    assert (mesh_fingerprint(floor.data), mesh_fingerprint(box.data)) == meshes_before
    assert errors[4] < 0.7 * errors[1], errors
    assert reports[4]["irradiance_detail_over_lightfields"] is None  # no light fields to compare with
    lightfield_plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8,
                                                                 samples=64, irradiance_detail=1))
    texels, images = read_images(tmp_path / "detail1" / "lightfield", lightfield_plan.stage_hash("render"))
    atlas, _ = read_texel_maps(tmp_path / "detail1", lightfield_plan.stage_hash("capture"))
    from_lightfields = irradiance_from_lightfields(images, channels(atlas, "N.X", 3)[texels[:, 0], texels[:, 1]])
    detail_image, _, _ = read_exr(tmp_path / "detail4" / DETAIL_FILE)
    from_detail = texel_means(detail_image, np.ones(detail_image.shape[:2], bool), 4, texels)
    assert 0.9 < from_detail.sum() / from_lightfields.sum() < 1.1, from_detail.sum() / from_lightfields.sum()
    report = read_report(tmp_path / "detail4")
    assert report["irradiance_detail"]["detail"] == 4 and report["irradiance_detail"]["pixels_written"] > 0


@pytest.mark.slow
def test_a_capture_keeps_a_matching_detail_image_and_apply_refuses_a_stale_one(tmp_path):
    """A second capture with the same plan keeps the finished detail image (a farm's last task runs capture again),
    but not once an object's texel scale moved the layout under the same plan; a plan asking for another detail makes
    apply refuse the file with the reason, until capture bakes it again."""
    scene, floor, _ = _shadow_scene()
    settings = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=4,
                                        irradiance_detail=2)
    plan = build_plan(scene, settings)
    capture(scene, plan, tmp_path)
    first = (tmp_path / DETAIL_FILE).stat().st_mtime_ns
    capture(scene, plan, tmp_path)
    assert (tmp_path / DETAIL_FILE).stat().st_mtime_ns == first
    assert read_report(tmp_path)["irradiance_detail"].get("kept") is True
    floor["sglf_texel_scale"] = 2.0  # the same plan, another layout: the image is baked again, not kept
    capture(scene, plan, tmp_path)
    assert read_report(tmp_path)["irradiance_detail"].get("kept") is None
    stale = read_exr_metadata(tmp_path / DETAIL_FILE)["layout"]
    del floor["sglf_texel_scale"]
    capture(scene, plan, tmp_path)
    assert read_exr_metadata(tmp_path / DETAIL_FILE)["layout"] != stale
    render_stage(scene, plan, tmp_path)
    other = build_plan(scene, BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8,
                                                       samples=4, irradiance_detail=3))
    with pytest.raises(BakeInputError, match="detail \\(2, the settings ask for 3\\); run the capture stage again"):
        apply_stage(scene, other, tmp_path)
    assert not any(s.material.name.endswith("(SG bake)") for o in scene.objects for s in o.material_slots
                   if s.material)


def test_texel_means_average_each_texels_written_pixels():
    """A 2 x 3 atlas at detail 2: each texel's mean takes only the pixels a bake wrote."""
    detail = 2
    image = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3)
    written = np.ones((4, 6), bool)
    written[0, 0] = False
    texels = np.array([[0, 0], [1, 2]])
    means = texel_means(image, written, detail, texels)
    assert np.allclose(means[0], image[[0, 1, 1], [1, 0, 1]].mean(axis=0))
    assert np.allclose(means[1], image[2:4, 4:6].reshape(-1, 3).mean(axis=0))


def test_node_group_reads_the_detail_image_as_its_numpy_reference_does(tmp_path):
    """The irradiance lightmap group with its irradiance from a detail image (2 pixels per texel, bilinear in both
    renderers) instead of a tile: a Cycles render of it equals the numpy reference at every texel centre, the detail
    image holding a ramp (so any row flip or half-pixel offset shows) and the roughness and view varied."""
    from sg_lightfield.bake_directory.exr_io import write_exr
    from sg_lightfield.bake_directory.sg_textures import pack_tiles
    from sg_lightfield.shaders.node_group import SGTextureLayout, build_node_group
    from sg_lightfield.shaders.sg_shading import NumpyOps, shade
    from tests.test_apply import parity_scene

    h, w, detail = 4, 4, 2
    layout = SGTextureLayout(0, has_irradiance=True, atlas_size=(2 * w, 2 * h), irradiance_detail=detail)
    assert layout.tiles == []
    packed = write_exr(tmp_path / "packed.exr", pack_tiles(layout, {}, (2 * h, 2 * w)), precision="half",
                       channels=["R", "G", "B", "A"])
    rows, cols = np.mgrid[0:2 * h * detail, 0:2 * w * detail].astype(np.float64)  # row 0 = the atlas' top
    ramp = np.stack([0.2 + 0.05 * cols, 0.1 + 0.08 * rows, 1.0 + 0.03 * (cols + rows)], -1)
    detail_path = write_exr(tmp_path / "detail.exr", ramp, precision="float", channels=["R", "G", "B"])
    images = [bpy.data.images.load(str(p)) for p in (packed, detail_path)]
    for image in images:
        image.colorspace_settings.name, image.alpha_mode = "Non-Color", "CHANNEL_PACKED"
    group = build_node_group(images[0], layout, (), "SG Lightfield detail parity", irradiance_image=images[1])
    scene, node = parity_scene(group, w, h)
    # render pixel (i, j) is the middle of atlas cell (i, j): 2 texels, 4 detail pixels wide, centre at 4 i + 2
    centre = ramp[2::4, 2::4] - (ramp[2::4, 2::4] - ramp[1::4, 1::4]) / 2  # the ramp between pixels 4i+1 and 4i+2

    def lookup(kind, j):
        assert (kind, j) == ("irradiance", 0)
        return centre, np.ones((h, w))

    worst = 0.0
    for roughness, theta in ((0.6, 0.0), (1.0, 60.0)):
        normal = (np.sin(np.radians(theta)), 0.0, np.cos(np.radians(theta)))
        node.inputs["Normal"].default_value = normal
        node.inputs["Roughness"].default_value = roughness
        node.inputs["F0"].default_value = (0.04, 0.04, 0.04, 1.0)
        node.inputs["Albedo"].default_value = (0.8, 0.5, 0.2, 1.0)
        scene.render.filepath = str(tmp_path / "parity.exr")
        with active_scene(scene), quiet_stdout():
            bpy.ops.render.render(write_still=True, scene=scene.name)
        rendered, _, _ = read_exr(tmp_path / "parity.exr", channels=["R", "G", "B"])
        reference = shade(NumpyOps(), lookup, np.broadcast_to(normal, (h, w, 3)), np.broadcast_to((0.0, 0.0, 1.0),
                          (h, w, 3)), np.full((h, w), roughness), np.broadcast_to((0.04, 0.04, 0.04), (h, w, 3)),
                          np.broadcast_to((0.8, 0.5, 0.2), (h, w, 3)), 0, 0, (), True, 0)["total"]
        worst = max(worst, float((np.abs(rendered - reference) / np.maximum(np.abs(reference), 0.1)).max()))
    assert worst < 1e-3, worst


@pytest.mark.slow
def test_a_surface_baked_through_a_copy_is_not_shadowed_by_its_own_original(tmp_path):
    """A plane with a Bevel modifier is baked through a temporary copy of its evaluated surface, coincident with the
    original: under a uniform white sky its irradiance is pi everywhere (a white Lambertian's E), not the 0 the
    original's surface at distance 0 gave before it was hidden from the copy's rays; its ray visibility comes back."""
    from sg_lightfield.blender_addon.surface_probe import RAY_VISIBILITY

    plane = mesh_object("Bevelled Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=4, y_segments=4, size=2.0,
                                                                           calc_uvs=True),
                        material("Rough Bevelled", roughness=0.9), uv_map="UVMap")
    plane.modifiers.new("Bevel", "BEVEL")
    plane.visible_shadow = False  # a user's choice: it must come back as it was
    scene = scene_with(plane, name="copy under the sky")
    world = bpy.data.worlds.new("white sky")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    scene.world = world
    visibility = {name: getattr(plane, name) for name in RAY_VISIBILITY}
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=2.0, irradiance_detail=4))
    assert plan.objects[0].geometry == "mesh + Bevel" and plan.objects[0].bake_lightfield
    capture(scene, plan, tmp_path)
    irradiance, _, _ = read_exr(tmp_path / DETAIL_FILE)
    lit = irradiance[..., 1][irradiance[..., 1] > 0]
    assert lit.size > 0.5 * irradiance[..., 1].size
    assert np.allclose(lit, np.pi, rtol=0.02), (lit.min(), np.median(lit))
    assert {name: getattr(plane, name) for name in RAY_VISIBILITY} == visibility
