"""Numerical stability at the extremes (DESIGN section 7): the whole bake on `spheres` variants stays finite."""
import bpy  # noqa: I001
import numpy as np
import pytest
from mathutils import Matrix

from blender_addon.apply import remove_bake
from blender_addon.demo_scenes import build_demo_scene
from blender_addon.pipeline import BakeJob
from blender_addon.render import quiet_stdout
from blender_addon.scene_analysis import active_scene
from shaders.bake_plan import BakeSettings
from shaders.exr_io import read_exr
from shaders.lightfield_tiles import read_images
from shaders.sg_textures import read_sg_texture
from shaders.texel_maps import read_texel_maps

pytestmark = pytest.mark.slow


def _bsdfs(scene, prefix):
    for obj in scene.objects:
        if obj.name.startswith(prefix):
            yield obj.material_slots[0].material.node_tree.nodes["Principled BSDF"]


def _variant(name):
    scene = build_demo_scene("demo:spheres")
    if name == "roughness_min":
        for bsdf in _bsdfs(scene, "Sphere"):
            bsdf.inputs["Roughness"].default_value = 0.0  # floored to ROUGHNESS_MIN
    elif name == "roughness_one":
        for bsdf in list(_bsdfs(scene, "Sphere"))[:2]:
            bsdf.inputs["Roughness"].default_value = 1.0
    elif name == "hdr_sun":
        next(_bsdfs(scene, "Arc")).inputs["Emission Strength"].default_value = 1e5
    elif name == "all_black":
        for bsdf in _bsdfs(scene, "Arc"):
            bsdf.inputs["Emission Strength"].default_value = 0.0
    elif name.startswith("scale_"):
        factor = float(name.split("_")[1])
        for obj in scene.objects:
            if obj.parent is None:
                obj.matrix_world = Matrix.Scale(factor, 4) @ obj.matrix_world
    return scene


@pytest.mark.parametrize("variant", ["roughness_min", "roughness_one", "hdr_sun", "all_black", "scale_1e4",
                                     "scale_1e-3"])
def test_bake_stays_finite_at_the_extremes(tmp_path, variant):
    scene = _variant(variant)
    scale = float(variant.split("_")[1]) if variant.startswith("scale_") else 1.0
    settings = BakeSettings.from_preset("draft", texel_density=4.0 / scale, lightfield_resolution=8, samples=4,
                                        sg_count=4, training_budget_s=2.0)
    job = BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train", "apply"))
    job.run()
    atlas, _ = read_texel_maps(tmp_path)
    _, images = read_images(tmp_path / "lightfield")
    axis, sharpness, amplitude, meta = read_sg_texture(tmp_path / "sg_lightfield.exr")
    packed, _, _ = read_exr(tmp_path / "sg_packed.exr")
    for array in (atlas, images, axis, sharpness, amplitude, packed):
        assert np.all(np.isfinite(array))
    if variant == "hdr_sun":
        assert images.max() > 1e3 and float(meta["amplitude_scale"]) >= 1.0 and amplitude.max() > 1e3
    if variant == "all_black":
        assert images.max() == 0 and amplitude.max() == 0 and any("black" in w for w in job.plan.warnings)
    with active_scene(scene), quiet_stdout():  # the baked materials shade to finite colours
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 32, 18, 100
        scene.cycles.samples = 2
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.filepath = str(tmp_path / "baked.exr")
        bpy.ops.render.render(write_still=True, scene=scene.name)
    rendered, _, _ = read_exr(tmp_path / "baked.exr", channels=["R", "G", "B"])
    assert np.all(np.isfinite(rendered))
    remove_bake(scene)
