"""The Bake operator and the pipeline job it drives (bpy as a module, real renders and training)."""
import hashlib

import bpy  # noqa: I001
import pytest

from sg_lightfield import blender_addon
from sg_lightfield.blender_addon.apply import remove_bake
from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
from sg_lightfield.blender_addon.pipeline import BakeJob
from sg_lightfield.blender_addon.scene_analysis import active_scene
from sg_lightfield.bake_directory.bake_plan import BakeSettings
from tests.scene_helpers import mesh_fingerprint

pytestmark = pytest.mark.slow


def scene_fingerprint(scene) -> str:
    """Meshes (incl. every UV layer), material assignments, material node trees and object properties."""
    h = hashlib.sha256()
    for obj in sorted(scene.objects, key=lambda o: o.name):
        h.update(obj.name.encode() + str(sorted(obj.keys())).encode())
        if obj.type == "MESH":
            h.update(mesh_fingerprint(obj.data).encode())
        for slot in obj.material_slots:
            material = slot.material
            h.update((material.name if material else "-").encode())
            if material is not None and material.node_tree is not None:
                h.update(str(sorted((n.name, n.bl_idname) for n in material.node_tree.nodes)).encode())
                h.update(str(sorted((l.from_node.name, l.to_node.name) for l in material.node_tree.links)).encode())
    return h.hexdigest()


@pytest.fixture
def addon():
    blender_addon.register()
    yield
    blender_addon.unregister()


def test_operator_bakes_spheres_at_draft_end_to_end_and_remove_restores(addon, tmp_path):
    scene = build_demo_scene("demo:spheres")
    with active_scene(scene):
        scene.sg_lightfield.preset = "DRAFT"  # the real preset, trained by a few epochs instead of its 30-s budget
        scene.sg_lightfield.training_epochs = 10
        scene.sg_lightfield.output_dir = str(tmp_path / "bake")
        before = scene_fingerprint(scene)
        assert bpy.ops.sg_lightfield.bake() == {"FINISHED"}
        baked = [s.material.name for o in scene.objects for s in o.material_slots if s.material]
        assert sum(name.endswith("(SG bake)") for name in baked) == 5  # four spheres and the lightmapped floor
        assert (tmp_path / "bake" / "report.json").is_file() and (tmp_path / "bake" / "sg_packed.exr").is_file()
        assert not scene.sg_lightfield.is_baking and "baked into" in scene.sg_lightfield.status
        assert bpy.ops.sg_lightfield.remove_bake() == {"FINISHED"}
        assert scene_fingerprint(scene) == before


def test_bad_settings_are_a_report_not_a_traceback(addon, tmp_path):
    scene = build_demo_scene("demo:spheres")
    with active_scene(scene):
        scene.sg_lightfield.output_dir = "//relative_but_unsaved"
        with pytest.raises(RuntimeError, match="save the .blend first"):  # an ERROR report, as the UI shows it
            bpy.ops.sg_lightfield.bake()
        assert "save the .blend first" in scene.sg_lightfield.status and not scene.sg_lightfield.is_baking


def test_the_panels_training_epochs_reach_the_bake_settings(addon):
    """The panel's Training Epochs (0: the time budget) reaches BakeSettings, custom preset or not."""
    from sg_lightfield.blender_addon.operators import settings_from_panel

    scene = build_demo_scene("demo:spheres")
    panel = scene.sg_lightfield
    assert settings_from_panel(panel).training_epochs == 0
    panel.training_epochs = 120
    for preset in ("DRAFT", "CUSTOM"):
        panel.preset = preset
        assert settings_from_panel(panel).training_epochs == 120, preset


def test_cancel_mid_render_leaves_the_scene_unchanged_and_the_next_run_reuses_tiles(tmp_path):
    scene = build_demo_scene("demo:spheres")
    before = scene_fingerprint(scene)
    settings = BakeSettings.from_preset("draft", texel_density=4.0, lightfield_resolution=8, samples=4,
                                        sg_count=2, training_budget_s=2.0)
    job = BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train", "apply"), tile_megapixels=0.005)
    rendered = 0
    while True:
        stage, fraction, message = job.step()
        if stage == "render" and "done" in message:
            rendered += 1
            if rendered == 2:
                break
    assert scene_fingerprint(scene) != before  # capture added the lightmap layer ...
    job.cancel()
    assert scene_fingerprint(scene) == before  # ... and cancel took it away again
    assert not [s for s in bpy.data.scenes if s.name.startswith("SGLF render")]
    again = BakeJob(scene, settings, tmp_path, stages=("capture", "render"), tile_megapixels=0.005)
    again.run()
    assert again.results["render"].tiles_skipped["lightfield"] == 2
    remove_bake(scene)
    assert scene_fingerprint(scene) == before


def test_training_in_a_worker_process_as_inside_blender(tmp_path):
    """Blender's Python has no torch: the add-on trains in a separate Python and reads its JSON progress."""
    scene = build_demo_scene("demo:spheres")
    settings = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=2,
                                        sg_count=2, training_budget_s=2.0)
    job = BakeJob(scene, settings, tmp_path, stages=("capture", "render", "train"), training="worker")
    messages = []
    job.run(lambda stage, fraction, message: messages.append((stage, fraction, message)))
    assert job.results["train"]["event"] == "stage" and (tmp_path / "sg_lightfield.exr").is_file()
    fractions = [f for s, f, _ in messages if s == "train"]
    assert fractions == sorted(fractions) and any("epoch" in m for s, _, m in messages if s == "train")
    remove_bake(scene)


def test_cancelling_a_rebake_puts_the_previous_bake_back(tmp_path):
    scene = build_demo_scene("demo:spheres")
    first = BakeSettings.from_preset("draft", texel_density=2.0, lightfield_resolution=8, samples=2, sg_count=2,
                                     training_budget_s=1.0)
    BakeJob(scene, first, tmp_path / "a", stages=("capture", "render", "train", "apply")).run()
    baked = scene_fingerprint(scene)
    second = BakeSettings.from_preset("draft", texel_density=5.0, lightfield_resolution=8, samples=2, sg_count=2,
                                      training_budget_s=1.0)  # another density: capture rewrites the lightmap
    job = BakeJob(scene, second, tmp_path / "b", stages=("capture", "render", "train", "apply"))
    while job.step()[0] != "render":
        pass
    assert scene_fingerprint(scene) != baked
    job.cancel()
    assert scene_fingerprint(scene) == baked  # the first bake's lightmap UVs and tiles are back
    remove_bake(scene)
