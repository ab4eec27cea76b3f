"""Bake plan on the demo scenes and bad input, and headless/bake.py as a user runs it (real bpy)."""
import json
import re
import subprocess
import sys
from pathlib import Path

import bpy  # noqa: I001  (bmesh exists only once bpy is imported)
import bmesh
import pytest

from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
from sg_lightfield.blender_addon.scene_analysis import build_plan
from sg_lightfield.headless.bake import parse_args, script_args
from sg_lightfield.bake_directory.bake_plan import BakeInputError, BakePlan, BakeSettings
from tests.scene_helpers import base_name, material as _material, mesh_object, scene_with as _scene_with

REPO = Path(__file__).resolve().parent.parent
DRAFT = BakeSettings.from_preset("draft")


def test_spheres_plan_models_only_what_the_scene_requires():
    plan = build_plan(build_demo_scene("demo:spheres"), DRAFT)
    spheres = {f"Sphere (roughness {r})" for r in ("0.2", "0.3", "0.4", "0.5")}
    assert set(map(base_name, plan.sg_objects)) == spheres  # the emissive arcs keep their shading
    assert {base_name(o.name) for o in plan.baked_objects} == spheres | {"Floor"}  # rough: an irradiance lightmap
    assert list(map(base_name, plan.irradiance_only_materials)) == ["Floor"]
    assert not plan.environment.iwev  # black world: no environment visibility
    assert sorted(map(base_name, plan.emissive_objects)) == ["Arc 0", "Arc 1", "Arc 2"] and plan.lamps == []
    assert plan.hair_objects == [] and "hair off" in plan.summary()


def test_the_plan_names_materials_sharper_than_the_light_field_resolves_and_a_finer_one_clears_them():
    draft = build_plan(build_demo_scene("demo:materials"), DRAFT)
    assert [(base_name(name), round(r, 2)) for name, r in draft.sharper_than_resolved()] == [("Painted Metal", 0.25)]
    line = next(line for line in draft.decisions() if line.startswith("sharper than 16x16 light fields resolve"))
    # a demo built twice in one session names its materials "Painted Metal.001"
    assert re.search(r"blurred: Painted Metal(\.\d+)? at 0\.25 \(", line)
    assert "resolution of 32 resolves down to 0.20" in line
    assert "Checker Floor" not in line  # its roughness is a texture: measured per texel at capture, not judged here
    finer = build_plan(build_demo_scene("demo:materials"), BakeSettings.from_preset("draft", lightfield_resolution=32))
    assert finer.sharper_than_resolved() == [] and not any("sharper than" in line for line in finer.decisions())


def test_room_and_courtyard_plans():
    room = build_plan(build_demo_scene("room"), DRAFT)
    assert {base_name(o.name) for o in room.baked_objects} >= {"Glossy Sphere"}
    assert list(map(base_name, room.lamps)) == ["Lamp"] and "Light Panel" in map(base_name, room.emissive_objects)
    assert not room.environment.iwev
    # The gold sphere is all metal: its own scattering in the bake is glossy, so its light field leaves out a glossy
    # bounce; the walls' and the floor's leave out a diffuse one.
    assert list(map(base_name, room.glossy_bounce_objects)) == ["Glossy Sphere"]
    assert any(line.startswith("light fields rendered with one diffuse bounce fewer") and "Glossy Sphere" in line
               for line in room.decisions())
    court = build_plan(build_demo_scene("courtyard"), DRAFT)
    assert court.environment.kind == "hdri" and court.environment.iwev
    assert court.environment.iwev_channels in (1, 3)


def test_plan_json_roundtrip_and_tamper_detection():
    plan = build_plan(build_demo_scene("spheres"), DRAFT)
    data = json.loads(json.dumps(plan.to_dict()))
    assert BakePlan.from_dict(data).content_hash() == data["hash"]
    data["settings"]["samples"] = 999
    with pytest.raises(BakeInputError, match="hash"):
        BakePlan.from_dict(data)


def test_a_plan_json_written_before_a_later_setting_still_reads_as_intact():
    """plan.json of a bake made before irradiance_detail existed (no key, its hash over the older settings) loads as
    the older behaviour (detail 1) and passes the tamper check; a detail above 1 is part of the hash."""
    plan = build_plan(build_demo_scene("spheres"), BakeSettings.from_preset("draft", irradiance_detail=1))
    older = json.loads(json.dumps(plan.to_dict()))
    del older["settings"]["irradiance_detail"]
    loaded = BakePlan.from_dict(older)
    assert loaded.settings.irradiance_detail == 1 and loaded.content_hash() == older["hash"]
    before = plan.content_hash()
    plan.settings.irradiance_detail = 4
    assert plan.content_hash() != before
    data = json.loads(json.dumps(plan.to_dict()))
    data["settings"]["irradiance_detail"] = 2
    with pytest.raises(BakeInputError, match="hash"):
        BakePlan.from_dict(data)


def test_stage_hashes_follow_what_outputs_depend_on_not_the_plans_wording():
    """Rewording a reason or a warning keeps finished renders; a change in what is baked does not."""
    import copy

    plan = build_plan(build_demo_scene("demo:courtyard"), DRAFT)
    hashes = {stage: plan.stage_hash(stage) for stage in ("capture", "render", "train")}
    reworded = copy.deepcopy(plan)
    reworded.environment.reason += " (reworded)"
    reworded.warnings.append("a new warning")
    for obj in reworded.objects:
        obj.reason += " (reworded)"
        for mat in obj.materials:
            mat.reason += " (reworded)"
    assert {stage: reworded.stage_hash(stage) for stage in hashes} == hashes
    other = copy.deepcopy(plan)
    other.baked_objects[0].texels += 1
    assert all(other.stage_hash(stage) != hashes[stage] for stage in hashes)


def test_the_irradiance_detail_changes_the_renders_only_where_lightmap_only_objects_lose_their_light_fields():
    """With the detail image, objects with only irradiance lightmaps get no light fields: room's renders change with
    the detail, materials' (no such objects) stay valid for any detail (the bench re-applies a bake at detail 1)."""
    for name, changes in (("demo:room", True), ("demo:materials", False)):
        scene = build_demo_scene(name)
        plans = {detail: build_plan(scene, BakeSettings.from_preset("draft", irradiance_detail=detail))
                 for detail in (1, 4)}
        assert bool(plans[4].lightmap_only_objects) == changes
        for stage in ("render", "train"):
            assert (plans[1].stage_hash(stage) != plans[4].stage_hash(stage)) == changes, (name, stage)
        assert plans[1].stage_hash("apply") != plans[4].stage_hash("apply")


def test_empty_scene_is_one_clear_error():
    with pytest.raises(BakeInputError, match="no mesh, curve or text objects .*empty"):
        build_plan(_scene_with(), DRAFT)


def test_cameras_and_empties_only():
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    empty = bpy.data.objects.new("Empty", None)
    hair = bpy.data.objects.new("Hair", bpy.data.hair_curves.new("Hair"))
    with pytest.raises(BakeInputError, match="only camera, curves, empty"):
        build_plan(_scene_with(cam, empty, hair), DRAFT)


def test_no_glossy_material_and_no_material():
    """Only rough materials: an irradiance lightmap bake (no SGs, no env visibility); with rough materials left to
    the renderer there is nothing to bake."""
    rough = _material("rough", 0.9)
    cube = mesh_object("Rough Cube", lambda bm: bmesh.ops.create_cube(bm, size=1.0), rough)
    bare = mesh_object("No Material", lambda bm: bmesh.ops.create_cube(bm, size=1.0))
    scene = _scene_with(cube, bare)
    plan = build_plan(scene, DRAFT)
    assert [base_name(o.name) for o in plan.baked_objects] == ["Rough Cube"] and plan.texels > 0
    assert plan.sg_objects == [] and plan.max_sg_count == 0
    assert list(map(base_name, plan.irradiance_only_materials)) == ["rough"]
    assert "no light-field SGs" in plan.summary() and "irradiance lightmap only" in "\n".join(plan.decisions())
    with pytest.raises(BakeInputError, match="no object or instance has a glossy material"):
        build_plan(scene, BakeSettings.from_preset("draft", rough_materials="renderer"))


def test_rough_dielectrics_get_irradiance_lightmaps_rough_metals_sgs_and_emitters_keep_their_shading():
    def cube(name, mat):
        return mesh_object(name, lambda bm: bmesh.ops.create_cube(bm, size=1.0), mat)

    glossy, rough, rough_metal = _material("glossy", 0.2), _material("rough", 0.9), _material("rough metal", 0.8, 1.0)
    glowing = _material("glowing", 0.9)
    bsdf = next(n for n in glowing.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Emission Color"].default_value, bsdf.inputs["Emission Strength"].default_value = (1, 1, 1, 1), 5.0
    both = cube("Both", glossy)
    both.data.materials.append(rough)  # a rough material beside a glossy one: its texels keep SGs
    scene = _scene_with(cube("Glossy", glossy), cube("Rough", rough), cube("Rough Metal", rough_metal),
                        cube("Glowing", glowing), both)
    plan = build_plan(scene, DRAFT)
    materials = {base_name(m.name): m for o in plan.objects for m in o.materials}
    assert materials["rough"].irradiance_only and not materials["rough"].glossy and materials["rough"].sg_count == 0
    assert materials["rough metal"].glossy and materials["rough metal"].sg_count > 0
    assert not materials["glowing"].baked and "emissive" in materials["glowing"].reason
    assert {base_name(o.name) for o in plan.baked_objects} == {"Glossy", "Rough", "Rough Metal", "Both"}
    assert sorted(map(base_name, plan.sg_objects)) == ["Both", "Glossy", "Rough Metal"]
    renderer = build_plan(scene, BakeSettings.from_preset("draft", rough_materials="renderer"))
    assert {base_name(o.name) for o in renderer.baked_objects} == {"Glossy", "Rough Metal", "Both"}
    assert renderer.stage_hash("capture") != plan.stage_hash("capture")


def test_zero_area_and_loose_vertices_are_skipped_with_a_warning():
    glossy = _material("glossy", 0.2)
    ok = mesh_object("Good", lambda bm: bmesh.ops.create_cube(bm, size=1.0), glossy)

    def loose(bm):
        for i in range(3):
            bm.verts.new((i, 0, 0))

    verts_only = mesh_object("Loose Verts", loose, glossy)
    plan = build_plan(_scene_with(ok, verts_only), DRAFT)
    assert [o.name for o in plan.baked_objects] == ["Good"]
    assert any("Loose Verts" in w for w in plan.warnings)
    assert plan.baked_objects[0].texels == int(6 * DRAFT.texel_density**2)


@pytest.mark.parametrize("overrides, message", [
    (dict(texel_density=1e9), "texel density"), (dict(lightfield_resolution=4), "resolution"),
    (dict(lightfield_resolution=72), "light-field resolution 72 is not one of 8, 16, 32, 64, 128"),
    (dict(sg_count=32), "SG count 32 with irradiance detail 4: beyond 24 SGs"),
    (dict(samples=0), "samples"), (dict(sg_count=999), "SG count"), (dict(device="tpu"), "device"),
    (dict(lobe_refit_steps=-1), "lobe refit steps"), (dict(rough_materials="ignore"), "rough materials"),
    (dict(lightmap_samples=-4), "lightmap samples"), (dict(lightmap_samples=10**6), "lightmap samples")])
def test_absurd_settings_are_rejected(overrides, message):
    with pytest.raises(BakeInputError, match=message):
        BakeSettings.from_preset("draft", **overrides)


def test_blender_style_arguments_after_double_dash():
    argv = ["blender", "-b", "scene.blend", "-P", "headless/bake.py", "--", "--out", "/tmp/x", "--plan-only"]
    assert script_args(argv) == ["--out", "/tmp/x", "--plan-only"]
    ns = parse_args(script_args(argv))
    assert ns.plan_only and ns.out == Path("/tmp/x") and ns.stages == ["capture", "render", "train", "apply", "evaluate"]


def _bake(*args):
    return subprocess.run([sys.executable, str(REPO / "headless" / "bake.py"), *args], capture_output=True, text=True,
                          cwd=REPO)


def test_cli_plan_only_json_lines_parse(tmp_path):
    out = _bake("--scene", "demo:spheres", "--out", str(tmp_path / "bake"), "--plan-only", "--json")
    assert out.returncode == 0, out.stderr
    events = [json.loads(line) for line in out.stdout.splitlines() if line.strip()]
    assert [e["event"] for e in events] == ["plan", "done"]
    plan = json.loads((tmp_path / "bake" / "plan.json").read_text())
    assert plan["hash"] == events[0]["hash"] and plan["texels"] > 0


def test_cli_training_epochs_reach_the_plan_and_a_bad_count_is_one_error(tmp_path):
    """--training-epochs, typed or from a farm's --settings file, reaches plan.json and the plan's summary."""
    settings = tmp_path / "farm.json"
    settings.write_text(json.dumps({"training-epochs": 150}))
    for extra, epochs in ((["--training-epochs", "200"], 200), (["--settings", str(settings)], 150)):
        out = _bake("--scene", "demo:spheres", "--out", str(tmp_path / "bake"), "--plan-only", *extra)
        assert out.returncode == 0, out.stderr
        plan = json.loads((tmp_path / "bake" / "plan.json").read_text())
        assert plan["settings"]["training_epochs"] == epochs and f"training {epochs} epochs (~" in plan["summary"]
    bad = _bake("--scene", "demo:spheres", "--out", str(tmp_path / "bad"), "--plan-only", "--training-epochs", "-5")
    assert bad.returncode != 0 and bad.stderr.strip().splitlines()[-1].startswith("error: training epochs -5")


def test_cli_production_plan_gives_16_sgs_everywhere_and_the_floor_its_lightmap_samples(tmp_path):
    """Production: 16 SGs on every glossy sphere (--no-uniform-sg-count brings back the per-material rule: 8 at
    roughness 0.4 and 0.5); the lightmap-only floor gets no light field (its light is in the irradiance detail
    image), or with --irradiance-detail 1 its light field at 64 spp beside the spheres' 256."""
    lines = {}
    for key, extra in (("production", []), ("rule", ["--no-uniform-sg-count", "--lightmap-samples", "0"]),
                       ("detail 1", ["--irradiance-detail", "1"])):
        out = _bake("--scene", "demo:spheres", "--preset", "production", "--out", str(tmp_path / "bake"),
                    "--plan-only", *extra)
        assert out.returncode == 0, out.stderr
        plan = json.loads((tmp_path / "bake" / "plan.json").read_text())
        lines[key] = [line for line in plan["decisions"] if line.startswith(("SGs per material", "light fields of",
                                                                             "objects with lightmaps only"))]
        lines[key + " estimate"] = plan["render_estimate_s"]
    assert lines["production"] == [
        "SGs per material: Glossy (roughness 0.2) 16, Glossy (roughness 0.3) 16, Glossy (roughness 0.4) 16, Glossy "
        "(roughness 0.5) 16 (every glossy material the same (uniform))",
        "objects with lightmaps only (Floor): no light fields (the irradiance detail image holds their light)"]
    assert lines["detail 1"][1] == ("light fields of objects with lightmaps only (Floor): 64 samples per pixel "
                                    "(irradiance needs their mean), the others 256")
    assert lines["production estimate"] < lines["detail 1 estimate"]
    assert "Glossy (roughness 0.4) 8, Glossy (roughness 0.5) 8" in lines["rule"][0]


def test_cli_instance_copies_puts_each_particle_of_the_geometry_demo_in_the_plan(tmp_path):
    """demo:geometry's 12 particle-scattered pebbles: left to the renderer with what would bake them by default, one
    plan entry each with --instance-copies (also from a --settings file); the metaball and the NURBS surface bake
    through stand-ins either way."""
    plans = {}
    settings_file = tmp_path / "settings.json"
    settings_file.write_text(json.dumps({"instance-copies": True}))
    for key, extra in (("default", []), ("copies", ["--instance-copies"]), ("file", ["--settings", str(settings_file)])):
        out = _bake("--scene", "demo:geometry", "--out", str(tmp_path / key), "--plan-only", *extra)
        assert out.returncode == 0, out.stderr
        plans[key] = json.loads((tmp_path / key / "plan.json").read_text())
    by_name = {o["name"]: o for o in plans["default"]["objects"]}
    assert "left to the renderer" in by_name["Pebble Scatter"]["reason"]
    assert "Instances as Copies" in by_name["Pebble Scatter"]["reason"]
    assert all(by_name[n]["bake_lightfield"] and "mesh stand-in" in by_name[n]["reason"] for n in ("Blob", "Dome"))
    for key in ("copies", "file"):
        pebbles = [o for o in plans[key]["objects"] if o["instancer"] == "Pebble Scatter"]
        assert len(pebbles) == 12 and all(o["bake_lightfield"] and o["texels"] > 0 for o in pebbles)
        assert plans[key]["settings"]["instance_copies"] is True
    assert plans["copies"]["hash"] == plans["file"]["hash"] != plans["default"]["hash"]


@pytest.mark.parametrize("args, message", [
    (["--blend", "/nonexistent/scene.blend"], "scene.blend: .blend file not found"),
    (["--scene", "demo:nope"], "unknown demo scene"),
    (["--scene", "demo:spheres", "--reference-samples", "1"], "--reference-samples 1 is outside 2..65536"),
    (["--scene", "demo:spheres", "--lightfield-resolution", "48"], "light-field resolution 48 is not one of"),
])
def test_cli_bad_input_is_one_line_and_nonzero(tmp_path, args, message):
    out = _bake(*args, "--out", str(tmp_path / "o"))
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]


@pytest.mark.parametrize("section, args, message", [
    ("encoders", ["--encoder-resolution", "48"], "light-field resolution 48 is not one of"),
    ("encoders", ["--encoder-training-budget", "0"], "training budget 0.0 s is outside"),
    ("encoders", ["--encoder-lobe-refit-steps", "-1"], "lobe refit steps -1 is outside"),
    ("encoders", ["--encoder-trainings", "17"], "--encoder-trainings takes 1 to 16"),
    ("knobs", ["--knobs", "lightfield_resolution=48"], "light-field resolution 48 is not one of"),
    ("knobs", ["--knobs", "texel_density=8:nan"], "knob 'texel_density' takes finite values"),
    ("knobs", ["--knobs", "samples=many"], "knob 'samples' takes int values separated by ':'"),
    ("knobs", ["--knobs", "sharpness=2"], "unknown knob 'sharpness'; choose from texel_density"),
    ("knobs", ["--knobs", ","], "--knobs: no knob named"),
    ("knobs", ["--knob-training-epochs", "-1"], "training epochs -1 is outside"),
    ("knobs", ["--knob-reference-samples", "1"], "--knob-reference-samples takes 2 to 65536"),
    ("knobs", ["--knob-scene", "attic"], "invalid choice: 'attic'"),
])
def test_bench_checks_a_sections_settings_before_any_work(tmp_path, capsys, section, args, message):
    from sg_lightfield.headless.bench import main

    with pytest.raises(SystemExit) as stopped:
        main(["--out", str(tmp_path / "bench"), "--sections", section, *args])
    assert stopped.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "bench").exists()  # stopped before it made its output directory


def test_the_knob_sweep_reads_values_as_the_settings_type_and_bare_names_as_the_default_sweep():
    from sg_lightfield.headless.bench import KNOB_SWEEP, parse_knob_sweep

    sweep = parse_knob_sweep("lightfield_resolution=32, texel_density=8:2.5,irradiance_detail")
    assert sweep == {"lightfield_resolution": (32,), "texel_density": (8.0, 2.5),
                     "irradiance_detail": KNOB_SWEEP["irradiance_detail"]}
    assert type(sweep["lightfield_resolution"][0]) is int and type(sweep["texel_density"][0]) is float


def test_the_bench_discards_a_demo_scene_so_the_next_one_built_gets_the_same_names():
    from sg_lightfield.headless.bench import _discard_scene

    def names(scene):
        objects = sorted(o.name for o in scene.objects)
        return objects, sorted({s.material.name for o in scene.objects for s in o.material_slots if s.material})

    first = build_demo_scene("demo:courtyard")
    first_names, scenes = names(first), len(bpy.data.scenes)
    _discard_scene(first)
    assert len(bpy.data.scenes) == scenes - 1
    assert not any(bpy.data.objects.get(n) for n in first_names[0])  # its objects went with it
    second = build_demo_scene("demo:courtyard")
    assert names(second) == first_names  # the bench's per-material rows say "Stone", not "Stone.001"
    _discard_scene(second)


def test_cli_device_cuda_without_an_optix_gpu_stops_with_one_error_line(tmp_path):
    from sg_lightfield.blender_addon.render import optix_devices

    if optix_devices():
        pytest.skip("an OptiX GPU is here")
    out = _bake("--scene", "demo:spheres", "--out", str(tmp_path / "o"), "--device", "cuda", "--texel-density", "1",
                "--stages", "capture,render")
    assert out.returncode == 1
    errors = [line for line in out.stderr.splitlines() if line.startswith("error")]
    assert errors == [out.stderr.strip().splitlines()[-1]]
    assert "no OptiX GPU" in errors[0] and "--device cpu" in errors[0]
    assert not list((tmp_path / "o").glob("lightfield/tile_*.exr"))


def test_cli_empty_blend_is_one_line_and_nonzero(tmp_path):
    empty = tmp_path / "empty.blend"
    code = ("import bpy; bpy.ops.wm.read_factory_settings(use_empty=True); "
            f"bpy.ops.wm.save_as_mainfile(filepath={str(empty)!r})")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    out = _bake("--blend", str(empty), "--out", str(tmp_path / "o"))
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == ["error: nothing to bake: the scene has no mesh, curve or text objects (it is empty)"]


def test_cli_eta_counts_only_the_current_stage_progress(monkeypatch, capsys):
    """The bar's fraction covers the whole bake: a stage that starts at 50 % and reaches 60 % in 10 s has 40 s
    left, not the 6.7 s that dividing by the whole bake's fraction would claim."""
    from sg_lightfield.headless import bake

    clock = iter([100.0, 110.0])
    monkeypatch.setattr(bake.time, "monotonic", lambda: next(clock))
    reporter = bake.Reporter(as_json=True)
    reporter.progress("train", 0.5, "start")
    reporter.progress("train", 0.6, "later")
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert events[0]["eta_s"] is None and events[1]["eta_s"] == pytest.approx(40.0)


def test_the_bake_eta_replays_the_room_production_bake(monkeypatch, tmp_path):
    """Room Production on this CPU (docs section 31): its first two glossy tiles took 3653 s and held 41.6 % of the
    render's pixel samples, and 6560 s of render, train, apply and evaluate were left. The job's ETA then is its
    render rate for the render's rest plus the plan's estimates of the later stages: within 10 % of what was left,
    where one rate for the whole bar said 14872 s. Between tiles it counts down."""
    from sg_lightfield.blender_addon import pipeline

    clock = [0.0]
    monkeypatch.setattr(pipeline.time, "monotonic", lambda: clock[0])
    job = pipeline.BakeJob(build_demo_scene("demo:room"), BakeSettings.from_preset("production"), tmp_path,
                           reference_samples=512)  # that bake's evaluation
    estimates = job.estimates_s
    assert estimates["render"] == pytest.approx(job.plan.render_estimate_s())
    assert estimates["train"] > 600  # the budget, and the refits of the floor (0.25) and the gold (0.2) at R = 32
    job.current_stage = "render"
    job._overall("render", 0.0)  # the render's first report, before any tile
    assert job.eta_s() == pytest.approx(sum(estimates[s] for s in ("render", "train", "apply", "evaluate")))
    clock[0] = 3653.0
    glossy_samples = 2 * 3906 * 256
    fraction = glossy_samples / (glossy_samples + 3471 * 256 + (7 * 3906 + 2760) * 64)
    overall = job._overall("render", fraction)
    assert job.eta_s() == pytest.approx(6560, rel=0.1)
    assert overall == pytest.approx((estimates["capture"] + fraction * estimates["render"]) / sum(estimates.values()))
    clock[0] += 600.0
    assert job.eta_s() == pytest.approx(6560 - 600, rel=0.1)
    # Nothing of the gold or the floor reaches the refits at Preview's R = 16: its training is its budget.
    preview = pipeline.BakeJob(build_demo_scene("demo:room"), BakeSettings.from_preset("preview"), tmp_path / "p")
    assert preview.estimates_s["train"] == pytest.approx(120.0)


@pytest.mark.slow
def test_the_cli_evaluates_with_cycles_only_when_eevee_is_left_out(tmp_path):
    """--no-eevee-evaluation: the whole bake, its evaluation with Cycles only, and EEVEE named as left out (a machine
    without an OpenGL context would otherwise wait for EEVEE)."""
    out = _bake("--scene", "demo:spheres", "--out", str(tmp_path / "o"), "--texel-density", "1",
                "--lightfield-resolution", "8", "--samples", "2", "--training-epochs", "1", "--lobe-refit-steps", "0",
                "--irradiance-detail", "1", "--reference-samples", "4", "--no-eevee-evaluation")
    assert out.returncode == 0, out.stderr[-2000:]
    errors = json.loads((tmp_path / "o" / "report.json").read_text())["errors"]
    assert errors["flip"] > 0 and errors["eevee"] == {"error": "left out of this evaluation: Cycles' only"}
    # the baked scene's render never takes more samples than the reference
    assert (errors["reference_samples"], errors["test_samples"]) == (4, 4)
    assert "against 4-spp references" in out.stdout and "the baked scene at 4 spp" in out.stdout
    assert "EEVEE not evaluated: left out of this evaluation" in out.stdout + out.stderr


def test_the_evaluation_converges_its_reference_further_than_the_baked_render():
    """The reference takes 8x the light field's samples (at least 1024); the baked scene's render twice them (at
    least 128), never more than the reference, which --reference-samples sets."""
    from sg_lightfield.blender_addon.evaluate import reference_samples_for, test_samples_for

    expected = {"draft": (1024, 128), "preview": (1024, 128), "production": (2048, 512)}
    for preset, (reference, test) in expected.items():
        settings = BakeSettings.from_preset(preset)
        assert (reference_samples_for(settings), test_samples_for(settings)) == (reference, test), preset
        assert test_samples_for(settings, reference_samples_for(settings)) == test
    draft = BakeSettings.from_preset("draft")
    assert test_samples_for(draft, 16) == 16 and test_samples_for(draft, 4096) == 128
