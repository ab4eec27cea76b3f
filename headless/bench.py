"""Benchmarks: `make bench` / `python -m headless.bench [--quick]`.

Speed targets live here, not in tests. Each section prints its measurements side by side and
writes them to bench_out/bench.json.
  capture   capture stage of `room` (and the other demos) at each preset's texel density; target < 10 s
            for `room` at the default (Draft) density.
  render    `room` at ~64^2 texels, R = 16, 16 spp: the atlas (one render call per tile) against one
            render call per texel (a measured subset, extrapolated), camera rays per second, the cost of
            the below-horizon cut (full-sphere rays for comparison), and IWEV post-processing of
            `courtyard` against its light-field render. Targets: atlas >= 10x faster than per texel;
            IWEV post-processing < 10 % of the light-field render.
  train     `spheres` (and with --full `room` at ~64^2 texels): the CNN against per-texel gradient descent
            (with and without the axis-alignment regulariser) at equal training time, fixed SG12 by NNLS
            and L2 SH by least squares: loss, RMSE, held-out midpoint error, bytes per texel; loss-vs-time
            plot and table in bench_out/train_<scene>.png / bench.json.
  apply     per SG count N = 4, 8, 16, 32: evaluator node count, apply time, EEVEE first render (shader
            compilation included) against a compiled re-render of the baked `spheres`.
  presets   each preset end to end on spheres, room and courtyard (--quick: Draft on spheres and room):
            bake time, share per stage, FLIP overall / per roughness class / EEVEE; Pareto plot
            bench_out/pareto.png (bake time vs FLIP). Target: Draft on room <= 5 minutes.
  hair      the hair filter (headless/bench_hair.py): onnxruntime time at 1024^2, PSNR/FLIP against Cycles
            of stochastic transparency, our filter and OIDN, the held-out groom apart; bench_out/hair_rows.png.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shaders.bake_plan import PRESETS, BakeSettings, write_json_atomic  # noqa: E402

CAPTURE_TARGET_S = 10.0
SECTIONS = ("capture", "render", "train", "apply", "presets", "hair")


def bench_capture(scenes, presets, out_root: Path) -> list[dict]:
    from blender_addon.capture import capture, remove_lightmap_uvs
    from blender_addon.demo_scenes import build_demo_scene
    from blender_addon.scene_analysis import build_plan

    rows = []
    for name in scenes:
        for preset in presets:
            scene = build_demo_scene(name)
            plan = build_plan(scene, BakeSettings.from_preset(preset))
            start = time.perf_counter()
            result = capture(scene, plan, out_root / f"capture_{name}_{preset}")
            seconds = time.perf_counter() - start
            remove_lightmap_uvs(scene)
            rows.append({"scene": name, "preset": preset, "texel_density": plan.settings.texel_density,
                         "texels": result.texels, "atlas": f"{result.atlas_width}x{result.atlas_height}",
                         "pushed_out": result.pushed_out_texels, "buried": result.buried_texels,
                         "seconds": round(seconds, 3), "texels_per_s": round(result.texels / seconds),
                         "share_of_target": round(seconds / CAPTURE_TARGET_S, 4)})
    print(f"\ncapture (target: room at draft density < {CAPTURE_TARGET_S:.0f} s)")
    print(f"{'scene':<10} {'preset':<11} {'tex/m':>6} {'texels':>8} {'atlas':>9} {'pushed':>7} {'buried':>7} "
          f"{'seconds':>8} {'texels/s':>9} {'x target':>9}")
    for r in rows:
        print(f"{r['scene']:<10} {r['preset']:<11} {r['texel_density']:>6g} {r['texels']:>8} {r['atlas']:>9} "
              f"{r['pushed_out']:>7} {r['buried']:>7} {r['seconds']:>8.3f} {r['texels_per_s']:>9} "
              f"{r['share_of_target']:>9.4f}")
    return rows


def bench_render(out_root: Path, per_texel_subset: int = 24) -> dict:
    import math
    import tempfile

    import numpy as np

    from blender_addon.capture import capture
    from blender_addon.demo_scenes import build_demo_scene
    from blender_addon.render import _RenderScene, _texel_inputs, render_stage, valid_texels
    from blender_addon.scene_analysis import build_plan
    from shaders.texel_maps import read_texel_maps

    resolution, samples = 16, 16
    scene = build_demo_scene("room")
    draft = build_plan(scene, BakeSettings.from_preset("draft"))
    density = 4.0 * math.sqrt(4096 / max(draft.texels, 1))
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=round(density, 2),
                                                      lightfield_resolution=resolution, samples=samples))
    out = out_root / "render_room"
    capture(scene, plan, out)
    atlas, _ = read_texel_maps(out)
    for tile in (out / "lightfield").glob("tile_*.exr"):
        tile.unlink()
    atlas_result = render_stage(scene, plan, out)
    texels = valid_texels(atlas)
    positions, normals, offsets = _texel_inputs(atlas, texels)
    rng = np.random.default_rng(0)
    subset = rng.choice(len(texels), size=min(per_texel_subset, len(texels)), replace=False)
    with tempfile.TemporaryDirectory(dir=out) as tmp, _RenderScene(scene, plan, Path(tmp), positions) as renderer:
        renderer.configure("lightfield")
        renderer.render(positions[:1], normals[:1], offsets[:1], np.ones(1), 1, 1, resolution, "warmup")
        start = time.perf_counter()
        for k in subset:
            renderer.render(positions[k:k + 1], normals[k:k + 1], offsets[k:k + 1], np.ones(1), 1, 1, resolution,
                            f"texel_{k}")
        per_texel_s = (time.perf_counter() - start) / len(subset)
        columns = math.ceil(math.sqrt(len(texels)))
        rows = math.ceil(len(texels) / columns)
        timings = {}
        for name, flag in (("upper hemisphere", 1.0), ("full sphere", 2.0)):
            start = time.perf_counter()
            renderer.render(positions, normals, offsets, np.full(len(texels), flag), columns, rows, resolution, name)
            timings[name] = time.perf_counter() - start
    court = build_demo_scene("courtyard")
    court_plan = build_plan(court, BakeSettings.from_preset("draft", lightfield_resolution=resolution,
                                                            samples=samples))
    court_out = out_root / "render_courtyard"
    capture(court, court_plan, court_out)
    for tile in list((court_out / "lightfield").glob("tile_*.exr")) + list((court_out / "env_visibility").glob("*.exr")):
        tile.unlink()
    court_result = render_stage(court, court_plan, court_out)
    court_lightfield_s = court_result.seconds  # includes the env passes; the ratio below is conservative
    row = {
        "texels": len(texels), "resolution": resolution, "samples": samples,
        "atlas_s": round(atlas_result.seconds, 3), "per_texel_call_s": round(per_texel_s, 4),
        "per_texel_extrapolated_s": round(per_texel_s * len(texels), 1),
        "atlas_speedup": round(per_texel_s * len(texels) / atlas_result.seconds, 1),
        "camera_rays_per_s": round(atlas_result.rays_per_second),
        "hemisphere_cut_s": round(timings["upper hemisphere"], 3), "full_sphere_s": round(timings["full sphere"], 3),
        "courtyard_texels": court_result.texels, "courtyard_render_s": round(court_lightfield_s, 3),
        "iwev_post_s": round(court_result.env_post_seconds, 3),
        "iwev_post_share": round(court_result.env_post_seconds / court_lightfield_s, 4),
    }
    print(f"\nrender (room, {row['texels']} texels, R = {resolution}, {samples} spp; targets: atlas >= 10x, "
          "IWEV post < 10 %)")
    print(f"  atlas render           {row['atlas_s']:>9.2f} s   ({row['camera_rays_per_s'] / 1e6:.2f} M camera rays/s)")
    print(f"  one call per texel     {row['per_texel_extrapolated_s']:>9.1f} s   ({row['per_texel_call_s'] * 1e3:.0f} ms "
          f"x {row['texels']}, measured on {len(subset)})")
    print(f"  atlas speed-up         {row['atlas_speedup']:>9.1f} x")
    print(f"  below-horizon cut      {row['hemisphere_cut_s']:>9.2f} s   vs full sphere {row['full_sphere_s']:.2f} s "
          f"({row['full_sphere_s'] / row['hemisphere_cut_s']:.2f}x)")
    print(f"  IWEV post (courtyard)  {row['iwev_post_s']:>9.3f} s   = {100 * row['iwev_post_share']:.2f} % of its "
          f"{row['courtyard_render_s']:.1f} s render")
    return row


def _neighbour_pairs(texels):
    """Index pairs of texels adjacent in the atlas (right and down neighbours)."""
    import numpy as np

    index = {(int(r), int(c)): i for i, (r, c) in enumerate(texels)}
    pairs = [(i, index[(r + dr, c + dc)]) for (r, c), i in index.items() for dr, dc in ((0, 1), (1, 0))
             if (r + dr, c + dc) in index]
    return np.array(pairs, np.int64).reshape(-1, 2)


def bench_train(out_root: Path, scene_name: str = "spheres", budget_s: float = 60.0, sg_count: int = 16,
                density: float | None = None, midpoints: int = 128) -> dict:
    import numpy as np
    import torch

    from blender_addon.capture import capture
    from blender_addon.demo_scenes import build_demo_scene
    from blender_addon.render import render_stage
    from blender_addon.scene_analysis import build_plan
    from shaders.lightfield_tiles import read_images
    from shaders.texel_maps import channels, read_texel_maps
    from training.baselines import (bytes_per_texel_fixed_sg, bytes_per_texel_sh_l2, eval_fixed_sg, eval_sh,
                                    fit_fixed_sg, fit_sh_l2)
    from training.sg_fit import (LightFieldData, TrainConfig, Trainer, error_metrics, midpoint_parameters,
                                 pair_indices, reconstruct, unit_midpoint)

    scene = build_demo_scene(scene_name)
    settings = BakeSettings.from_preset("draft", lightfield_resolution=16, samples=32, sg_count=sg_count,
                                        **({"texel_density": density} if density else {}))
    plan = build_plan(scene, settings)
    out = out_root / f"train_{scene_name}"
    capture(scene, plan, out)
    render_stage(scene, plan, out, midpoints=midpoints)
    atlas, _ = read_texel_maps(out)
    texels, images = read_images(out / "lightfield", plan.stage_hash("render"))
    pairs, held_out = read_images(out / "midpoints", plan.stage_hash("render"))
    normals = channels(atlas, "Ng.X", 3)[texels[:, 0], texels[:, 1]].astype(np.float64)
    a_idx, b_idx = pair_indices(texels, pairs)
    n_mid = unit_midpoint(normals[a_idx], normals[b_idx])
    rows, curves = [], {}

    def add(name, prediction, midpoint_prediction, seconds, bytes_per_texel):
        metrics = error_metrics(prediction, images, normals)
        mid = error_metrics(midpoint_prediction, held_out, n_mid)
        rows.append({"method": name, "seconds": round(seconds, 1), "loss": metrics["loss"], "rmse": metrics["rmse"],
                     "rmse_log": metrics["rmse_log"], "midpoint_rmse": mid["rmse"], "midpoint_loss": mid["loss"],
                     "bytes_per_texel": bytes_per_texel})

    data = LightFieldData.from_numpy(images, normals)
    neighbours = torch.from_numpy(_neighbour_pairs(texels))
    for name, mode, lr, align in (("CNN (ours)", "cnn", 1e-3, 0.0), ("per-texel GD", "per_texel", 1e-2, 0.0),
                                  ("per-texel GD + aligned axes", "per_texel", 1e-2, 0.05)):
        torch.manual_seed(0)
        trainer = Trainer(data, TrainConfig(sg_count=sg_count, time_budget_s=budget_s, learning_rate=lr,
                                            plateau_epochs=10**9), mode=mode, neighbours=neighbours,
                          axis_alignment=align)
        state = trainer.train()
        a, s, m = trainer.parameters_numpy()
        add(name, reconstruct(a, s, m, 16), reconstruct(*midpoint_parameters(a, s, m, a_idx, b_idx), 16),
            state.seconds[-1], 2 * sg_count * 7)
        curves[name] = (state.seconds, state.losses)
    start = time.perf_counter()
    axes, sharpness, amps = fit_fixed_sg(images, normals, 12)
    add(f"fixed SG12 (NNLS, sharpness {sharpness:g})", eval_fixed_sg(axes, sharpness, amps, 16),
        eval_fixed_sg(axes, sharpness, 0.5 * (amps[a_idx] + amps[b_idx]), 16), time.perf_counter() - start,
        bytes_per_texel_fixed_sg(12))
    start = time.perf_counter()
    coeffs = fit_sh_l2(images, normals)
    add("SH L2 (least squares)", eval_sh(coeffs, 16), eval_sh(0.5 * (coeffs[a_idx] + coeffs[b_idx]), 16),
        time.perf_counter() - start, bytes_per_texel_sh_l2())
    _plot_training(out_root / f"train_{scene_name}.png", curves, rows, scene_name)
    print(f"\ntrain ({scene_name}: {len(texels)} texels, R = 16, N = {sg_count}, {budget_s:g} s per iterative method, "
          f"{len(pairs)} held-out midpoints)")
    print(f"  {'method':<40} {'s':>6} {'loss':>9} {'RMSE':>8} {'RMSE log':>9} {'mid RMSE':>9} {'bytes':>6}")
    for r in rows:
        print(f"  {r['method']:<40} {r['seconds']:>6.1f} {r['loss']:>9.5f} {r['rmse']:>8.4f} {r['rmse_log']:>9.4f} "
              f"{r['midpoint_rmse']:>9.4f} {r['bytes_per_texel']:>6}")
    cnn, gd = rows[0], rows[1]
    print(f"  CNN midpoint RMSE / per-texel GD: {cnn['midpoint_rmse'] / gd['midpoint_rmse']:.2f} (target <= 0.67); "
          f"SG12 RMSE / CNN: {rows[3]['rmse'] / cnn['rmse']:.2f}, SH L2 RMSE / CNN: {rows[4]['rmse'] / cnn['rmse']:.2f} "
          "(target >= 2)")
    return {"scene": scene_name, "texels": len(texels), "rows": rows}


def bench_apply(out_root: Path, sg_counts=(4, 8, 16, 32)) -> list[dict]:
    """Per SG count: node count and build time of the evaluator group, EEVEE's first render of the baked
    `spheres` (shader compilation included) and a second render of the same view (compiled), 256x144.
    EEVEE runs on this machine's OpenGL (llvmpipe, software, without a GPU): the compile share is what
    scales with N; absolute frame times need a GPU."""
    from blender_addon.demo_scenes import build_demo_scene
    from blender_addon.evaluate import render_eevee
    from blender_addon.pipeline import BakeJob

    rows = []
    for n in sg_counts:
        scene = build_demo_scene("spheres")
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 256, 144, 100
        settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=8, sg_count=n,
                                            training_budget_s=5.0)
        out = out_root / f"apply_sg{n}"
        job = BakeJob(scene, settings, out, stages=("capture", "render", "train", "apply"))
        job.run()
        report = __import__("json").loads((out / "report.json").read_text())
        _, seconds = render_eevee(scene, [scene.camera.name] * 3, out)
        rows.append({"sg_count": n, "nodes": report["apply"]["nodes"], "apply_s": report["timings_s"].get("apply"),
                     "eevee_first_render_s": round(seconds[0], 2),
                     "eevee_compiled_render_s": round(min(seconds[1:]), 2),
                     "eevee_compile_s": round(seconds[0] - min(seconds[1:]), 2)})
        print(f"apply N={n:>2}: {rows[-1]['nodes']} nodes, apply {rows[-1]['apply_s']} s, EEVEE first render "
              f"{rows[-1]['eevee_first_render_s']} s, compiled {rows[-1]['eevee_compiled_render_s']} s "
              f"-> compile ~{rows[-1]['eevee_compile_s']} s")
    return rows


def bench_presets(out_root: Path, scenes, presets) -> list[dict]:
    """Each preset end to end (capture .. evaluate, EEVEE included) on each scene: bake time, share of time
    per stage, FLIP overall and per roughness class; a Pareto plot of bake time against FLIP."""
    import json

    from blender_addon.demo_scenes import build_demo_scene
    from blender_addon.pipeline import BakeJob

    rows = []
    for name in scenes:
        for preset in presets:
            scene = build_demo_scene(name)
            out = out_root / f"preset_{name}_{preset}"
            start = time.perf_counter()
            job = BakeJob(scene, BakeSettings.from_preset(preset), out)
            job.run()
            total = time.perf_counter() - start
            errors = json.loads((out / "report.json").read_text())["errors"]
            eevee = errors.get("eevee") or {}
            bake_s = sum(v for k, v in job.timings.items() if k != "evaluate")
            rows.append({"scene": name, "preset": preset, "bake_s": round(bake_s, 1), "total_s": round(total, 1),
                         "stage_share": {k: round(v / bake_s, 3) for k, v in job.timings.items() if k != "evaluate"},
                         "flip": round(errors["flip"], 4), "psnr_db": round(errors["psnr"], 2),
                         "flip_by_roughness": {k: None if v["flip"] is None else round(v["flip"], 4)
                                               for k, v in errors["flip_by_roughness"].items()},
                         "eevee_flip": None if "flip" not in eevee else round(eevee["flip"], 4),
                         "reference_noise_rmse": round(errors["reference_noise_rmse"], 4)})
            row = rows[-1]
            shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in row["stage_share"].items())
            print(f"preset {preset:<10} {name:<10} bake {row['bake_s']:7.1f} s ({shares}); FLIP {row['flip']:.4f} "
                  f"(EEVEE {row['eevee_flip']}), by roughness {row['flip_by_roughness']}")
    if rows:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        figure, axes = plt.subplots(figsize=(6, 4))
        for name in scenes:
            mine = [r for r in rows if r["scene"] == name]
            axes.plot([r["bake_s"] for r in mine], [r["flip"] for r in mine], "o-", label=name)
            for r in mine:
                axes.annotate(r["preset"], (r["bake_s"], r["flip"]), fontsize=7)
        axes.set_xscale("log")
        axes.set_xlabel("bake time (s, capture to apply)")
        axes.set_ylabel("mean FLIP vs Cycles reference")
        axes.legend()
        figure.tight_layout()
        figure.savefig(out_root / "pareto.png", dpi=120)
        plt.close(figure)
    return rows


def _plot_training(path: Path, curves: dict, rows: list, scene_name: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for name, (seconds, losses) in curves.items():
        left.plot(seconds, losses, label=name)
    left.set_xlabel("training seconds (CPU)"), left.set_ylabel("training loss (log L2, jittered)")
    left.set_yscale("log"), left.legend(), left.set_title(f"{scene_name}: loss vs time")
    names = [r["method"].split(" (")[0] for r in rows]
    x = range(len(rows))
    right.bar([i - 0.2 for i in x], [r["rmse"] for r in rows], 0.4, label="RMSE (texels)")
    right.bar([i + 0.2 for i in x], [r["midpoint_rmse"] for r in rows], 0.4, label="RMSE (held-out midpoints)")
    right.set_xticks(list(x), names, rotation=20, ha="right"), right.legend(), right.set_title("linear RMSE")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m headless.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="room only, Draft and Preview")
    p.add_argument("--out", type=Path, default=Path("bench_out"))
    p.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated subset of " + ",".join(SECTIONS))
    p.add_argument("--hair-data", type=Path, default=Path("hair_data"),
                   help="hair pairs from headless/hair_dataset.py (the hair section's quality table)")
    ns = p.parse_args(argv)
    sections = [s for s in ns.sections.split(",") if s]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        p.error(f"unknown section(s) {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    ns.out.mkdir(parents=True, exist_ok=True)
    scenes = ["room"] if ns.quick else ["room", "spheres", "courtyard"]
    presets = ["draft", "preview"] if ns.quick else list(PRESETS)
    results = {}
    if "capture" in sections:
        results["capture"] = bench_capture(scenes, presets, ns.out)
    if "render" in sections:
        results["render"] = bench_render(ns.out)
    if "train" in sections:
        results["train"] = [bench_train(ns.out, "spheres", budget_s=30.0 if ns.quick else 120.0)]
        if not ns.quick:
            results["train"].append(bench_train(ns.out, "room", budget_s=300.0, density=8.9))
    if "apply" in sections:
        results["apply"] = bench_apply(ns.out, (4, 16) if ns.quick else (4, 8, 16, 32))
    if "presets" in sections:
        preset_scenes = ["spheres", "room"] if ns.quick else ["spheres", "room", "courtyard"]
        results["presets"] = bench_presets(ns.out, preset_scenes, ["draft"] if ns.quick else list(PRESETS))
    if "hair" in sections:
        from headless.bench_hair import bench_hair

        results["hair"] = bench_hair(ns.out, ns.hair_data, ns.quick)
    write_json_atomic(ns.out / "bench.json", results)
    print(f"\nwritten: {ns.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
