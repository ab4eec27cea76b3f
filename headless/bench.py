"""Benchmarks: `make bench` / `python -m headless.bench [--quick]`.

Speed targets live here, not in tests. Each section prints its measurements side by side and
writes them to bench_out/bench.json; bench_out/results.md shows the plots first, then every section's tables.
  capture   capture stage of `room` (and the other demos) at each preset's texel density; target < 10 s
            for `room` at the default (Draft) density.
  render    `room` at ~64^2 texels, R = 16, 16 spp: the atlas (one render call per tile) against one
            render call per texel (a measured subset, extrapolated; calls that keep the scene between them,
            and DESIGN §4's naive calls that sync it anew each time), camera rays per second, the cost of
            the below-horizon cut (full-sphere rays for comparison), and IWEV post-processing of
            `courtyard` against its light-field render. Targets: atlas >= 10x faster than per texel;
            IWEV post-processing < 10 % of the light-field render.
  train     `spheres` (and with --full `room` at ~64^2 texels): the CNN against per-texel gradient descent
            (with and without the axis-alignment regulariser) at equal training time, fixed SG12 by NNLS
            and L2 SH by least squares: loss, RMSE, held-out midpoint error, bytes per texel; loss-vs-time
            plot and table in bench_out/train_<scene>.png / bench.json.
  knobs     every quality knob's cost and error: from Draft on spheres (--knob-scene: any demo, materials included),
            one knob at a time (KNOB_SWEEP, or --knobs), baked and evaluated against one set of references
            (--knob-reference-samples): bake seconds per stage, FLIP overall, on glossy pixels and per material.
            --knob-training-epochs compares at equal training. The presets come from this table.
  apply     per SG count N = 4, 8, 16, 32: evaluator node count, apply time, EEVEE first render (shader
            compilation included) against a compiled re-render of the baked `spheres`.
  presets   each preset end to end on spheres, room and courtyard (--quick: Draft on spheres and room):
            bake time, share per stage, FLIP overall / per roughness class / EEVEE; Pareto plot
            bench_out/pareto.png (bake time vs FLIP). Target: Draft on room <= 5 minutes.
  sgcount   how many SGs a material needs, by roughness: the CNN at N = 2..16 on spheres and room, error of the
            reflected radiance; the measured rule behind bake_directory/bake_plan.py SG_COUNT_BY_ROUGHNESS; sg_count.png.
  encoders  free SGs against fixed SG12 and L2 SH (each baked, applied, evaluated) at equal bytes per texel, on spheres:
            RMSE and FLIP on glossy pixels (and per roughness class; RMSE also against the converged image),
            reflected-radiance error of each sphere's texels at its roughness, split into the SGs' fit and the
            closed form's error. R = 32 (Production's) with the presets' lobe refit unless --encoder-* say
            otherwise; the CNN trained 3 times (seeds; --quick: once) and averaged. Target: >= 2x lower RMSE.
  materials demo:materials (textured, bump-mapped, mixed, grouped and emissive materials beside glass, alpha and coat
            left to the renderer) at Draft and Preview (--quick: Draft): FLIP of EEVEE with the bake and of EEVEE
            without it (ray tracing, a baked volume probe, the better of a sphere probe or none) against the
            Cycles reference, overall and per material; and the same scene with every texture replaced by its
            mean over the surface (measured by Cycles). Targets: EEVEE without the bake / with it >= 2;
            textured / mean-textured bake FLIP <= 1.2. Beside them the textured bake with irradiance detail 1
            (diffuse light from the light fields), on the same light fields and SGs: the cost and gain of the
            preset's detail image.
  geometry  demo:geometry (a smooth monkey, a live Bevel + Array + Subdivision stack, extruded text, a bevelled
            curve, node and collection instances, a metaball, a NURBS surface, particles as object copies) at Draft:
            per object its geometry, texels, capture seconds and the FLIP of EEVEE with and without the bake, per
            material; EEVEE's frame time with and without per-instance tiles and with the particles' own instances.
  stability the numerical-stability sweep: `spheres` at roughness 0 and 1, a 1e5 emitter, no light, scale 1e4 and
            1e-3, each baked and evaluated: every output finite, and the errors.
  farm      the Open Job Description template run locally with openjd (one process per task, 3 render tasks) against
            the one-process bake of spheres at Draft, both whole: wall-time overhead (target <= 10 %) and the tiles
            compared bit for bit.
  hair      the hair filter (headless/bench_hair.py): onnxruntime time at 1024^2, PSNR/FLIP against Cycles
            of stochastic transparency, our filter and OIDN, the held-out groom apart; bench_out/hair_rows.png.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from ..bake_directory.bake_plan import (  # noqa: E402
    LOBE_REFIT_STEPS, PRESETS, BakeInputError, BakeSettings, write_json_atomic)
from .bench_results import write_results_page  # noqa: E402

CAPTURE_TARGET_S = 10.0
SECTIONS = ("capture", "render", "train", "sgcount", "encoders", "knobs", "apply", "presets", "materials", "geometry",
            "stability", "farm", "hair")


def bench_capture(scenes, presets, out_root: Path) -> list[dict]:
    from ..blender_addon.capture import capture, remove_lightmap_uvs
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.scene_analysis import build_plan

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


def bench_render(out_root: Path, per_texel_subset: int = 24, device: str = "cpu") -> dict:
    import math
    import tempfile

    import numpy as np

    from ..blender_addon.capture import capture
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.render import _RenderScene, _texel_inputs, render_stage, valid_texels
    from ..blender_addon.scene_analysis import build_plan
    from ..bake_directory.texel_maps import read_texel_maps

    resolution, samples = 16, 16
    scene = build_demo_scene("room")
    draft = build_plan(scene, BakeSettings.from_preset("draft"))
    density = 4.0 * math.sqrt(4096 / max(draft.texels, 1))
    plan = build_plan(scene, BakeSettings.from_preset("draft", texel_density=round(density, 2),
                                                      lightfield_resolution=resolution, samples=samples,
                                                      device=device))
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

        def seconds_per_call(texel_indices, prefix):
            start = time.perf_counter()
            for k in texel_indices:
                renderer.render(positions[k:k + 1], normals[k:k + 1], offsets[k:k + 1], np.ones(1), 1, 1, resolution,
                                f"{prefix}{k}")
            return (time.perf_counter() - start) / len(texel_indices)

        per_texel_s = seconds_per_call(subset, "texel_")
        # DESIGN §4's naive loop: the same calls with the scene synced anew each time (no persistent data).
        renderer.scene.render.use_persistent_data = False
        synced = subset[:max(1, len(subset) // 3)]
        per_texel_synced_s = seconds_per_call(synced, "synced_texel_")
        renderer.scene.render.use_persistent_data = True
        renderer.render(positions[:1], normals[:1], offsets[:1], np.ones(1), 1, 1, resolution, "warmup_again")
        columns = math.ceil(math.sqrt(len(texels)))
        rows = math.ceil(len(texels) / columns)
        timings = {}
        for name, flag in (("upper hemisphere", 1.0), ("full sphere", 2.0)):
            start = time.perf_counter()
            renderer.render(positions, normals, offsets, np.full(len(texels), flag), columns, rows, resolution, name)
            timings[name] = time.perf_counter() - start
    court = build_demo_scene("courtyard")
    court_plan = build_plan(court, BakeSettings.from_preset("draft", lightfield_resolution=resolution,
                                                            samples=samples, device=device))
    court_out = out_root / "render_courtyard"
    capture(court, court_plan, court_out)
    for tile in list((court_out / "lightfield").glob("tile_*.exr")) + list((court_out / "env_visibility").glob("*.exr")):
        tile.unlink()
    court_result = render_stage(court, court_plan, court_out)
    court_lightfield_s = court_result.seconds  # includes the env passes; the ratio below is conservative
    row = {
        "devices": atlas_result.devices, "texels": len(texels), "resolution": resolution, "samples": samples,
        "atlas_s": round(atlas_result.seconds, 3), "per_texel_call_s": round(per_texel_s, 4),
        "per_texel_extrapolated_s": round(per_texel_s * len(texels), 1),
        "atlas_speedup": round(per_texel_s * len(texels) / atlas_result.seconds, 1),
        "per_texel_synced_call_s": round(per_texel_synced_s, 4), "per_texel_synced_subset": len(synced),
        "atlas_speedup_vs_synced_calls": round(per_texel_synced_s * len(texels) / atlas_result.seconds, 1),
        "camera_rays_per_s": round(atlas_result.rays_per_second),
        "hemisphere_cut_s": round(timings["upper hemisphere"], 3), "full_sphere_s": round(timings["full sphere"], 3),
        "courtyard_texels": court_result.texels, "courtyard_render_s": round(court_lightfield_s, 3),
        "iwev_post_s": round(court_result.env_post_seconds, 3),
        "iwev_post_share": round(court_result.env_post_seconds / court_lightfield_s, 4),
    }
    print(f"\nrender (room, {row['texels']} texels, R = {resolution}, {samples} spp, on {', '.join(row['devices'])}; "
          "targets: atlas >= 10x, IWEV post < 10 %)")
    print(f"  atlas render           {row['atlas_s']:>9.2f} s   ({row['camera_rays_per_s'] / 1e6:.2f} M camera rays/s)")
    print(f"  one call per texel     {row['per_texel_extrapolated_s']:>9.1f} s   ({row['per_texel_call_s'] * 1e3:.0f} ms "
          f"x {row['texels']}, measured on {len(subset)})")
    print(f"  atlas speed-up         {row['atlas_speedup']:>9.1f} x   (the target's measure: per-texel calls that keep "
          "the scene between calls, as the atlas tiles do)")
    print(f"  one call per texel, scene synced each call (DESIGN §4's naive loop) "
          f"{row['per_texel_synced_call_s'] * 1e3:.0f} ms x {row['texels']} (measured on {len(synced)}): atlas "
          f"{row['atlas_speedup_vs_synced_calls']:.1f} x faster")
    print(f"  below-horizon cut      {row['hemisphere_cut_s']:>9.2f} s   vs full sphere {row['full_sphere_s']:.2f} s "
          f"({row['full_sphere_s'] / row['hemisphere_cut_s']:.2f}x)")
    print(f"  IWEV post (courtyard)  {row['iwev_post_s']:>9.3f} s   = {100 * row['iwev_post_share']:.2f} % of its "
          f"{row['courtyard_render_s']:.1f} s render")
    return row


def _rendered_lightfields(out_root: Path, scene_name: str, density: float | None = None, midpoints: int = 128):
    """Light fields of a demo scene at R = 16, 32 spp (Draft density unless given), rendered once into
    bench_out/train_<scene> and reused: (texels, images, normals, midpoint pairs, held-out midpoints, neighbours:
    (M, 2) indices of every pair of adjacent texels of one object)."""
    import numpy as np

    from ..blender_addon.capture import capture
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.render import render_stage
    from ..blender_addon.scene_analysis import build_plan
    from ..bake_directory.lightfield_tiles import read_images
    from ..bake_directory.texel_maps import adjacent_texel_pairs, channels, read_texel_maps
    from ..training.sg_fit import pair_indices

    scene = build_demo_scene(scene_name)
    settings = BakeSettings.from_preset("draft", lightfield_resolution=16, samples=32,
                                        **({"texel_density": density} if density else {}))
    plan = build_plan(scene, settings)
    out = out_root / f"train_{scene_name}"
    capture(scene, plan, out)
    render_stage(scene, plan, out, midpoints=midpoints)
    atlas, _ = read_texel_maps(out)
    texels, images = read_images(out / "lightfield", plan.stage_hash("render"))
    pairs, held_out = read_images(out / "midpoints", plan.stage_hash("render"))
    normals = channels(atlas, "Ng.X", 3)[texels[:, 0], texels[:, 1]].astype(np.float64)
    neighbours = np.stack(pair_indices(texels, adjacent_texel_pairs(atlas)), axis=1)
    return texels, images, normals, pairs, held_out, neighbours


def bench_train(out_root: Path, scene_name: str = "spheres", budget_s: float = 60.0, sg_count: int = 16,
                density: float | None = None, midpoints: int = 128) -> dict:
    import torch

    from ..training.baselines import (bytes_per_texel_fixed_sg, bytes_per_texel_sh_l2, eval_fixed_sg, eval_sh,
                                    fit_fixed_sg, fit_sh_l2)
    from ..training.sg_fit import (LightFieldData, TrainConfig, Trainer, error_metrics, midpoint_parameters,
                                 pair_indices, reconstruct, unit_midpoint)

    texels, images, normals, pairs, held_out, neighbours = _rendered_lightfields(out_root, scene_name, density,
                                                                                  midpoints)
    a_idx, b_idx = pair_indices(texels, pairs)
    n_mid = unit_midpoint(normals[a_idx], normals[b_idx])
    rows, curves = [], {}

    def add(name, prediction, midpoint_prediction, seconds, bytes_per_texel, epochs=None):
        metrics = error_metrics(prediction, images, normals)
        mid = error_metrics(midpoint_prediction, held_out, n_mid)
        rows.append({"method": name, "seconds": round(seconds, 1), "loss": metrics["loss"], "rmse": metrics["rmse"],
                     "rmse_log": metrics["rmse_log"], "midpoint_rmse": mid["rmse"], "midpoint_loss": mid["loss"],
                     "bytes_per_texel": bytes_per_texel, "epochs": epochs,
                     "epochs_per_s": round(epochs / seconds, 2) if epochs and seconds > 0 else None})

    data = LightFieldData.from_numpy(images, normals)
    neighbours = torch.from_numpy(neighbours)
    # The interpolation term (sg_fit) scores blended neighbours against their blended light fields: measured not to
    # help the CNN, which interpolates already, so it is a baseline here, the strongest per-texel one.
    for name, mode, lr, align, interpolation in (
            ("CNN (ours)", "cnn", 1e-3, 0.0, 0.0), ("per-texel GD", "per_texel", 1e-2, 0.0, 0.0),
            ("per-texel GD + aligned axes", "per_texel", 1e-2, 0.05, 0.0),
            ("per-texel GD + interpolation term", "per_texel", 1e-2, 0.0, 1.0)):
        torch.manual_seed(0)
        trainer = Trainer(data, TrainConfig(sg_count=sg_count, time_budget_s=budget_s, learning_rate=lr,
                                            plateau_epochs=10**9, interpolation_weight=interpolation),
                          mode=mode, neighbours=neighbours, axis_alignment=align)
        state = trainer.train()
        a, s, m = trainer.parameters_numpy()
        add(name, reconstruct(a, s, m, 16), reconstruct(*midpoint_parameters(a, s, m, a_idx, b_idx), 16),
            state.seconds[-1], 2 * sg_count * 7, state.epoch)
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
    row = {r["method"].split(" (")[0]: r for r in rows}
    cnn, gd, gd_interpolation = row["CNN"], row["per-texel GD"], row["per-texel GD + interpolation term"]
    plateau_s = _time_to_within(*curves["CNN (ours)"], 0.02)
    cnn_final = _smoothed(curves["CNN (ours)"][1])[-1]
    gd_equal_s = _time_to_within(curves["per-texel GD"][0], curves["per-texel GD"][1], 0.0, cnn_final)
    print(f"  CNN plateau (smoothed loss within 2 % of its final value): {plateau_s:.0f} s; per-texel GD reaches the "
          f"CNN's final loss {cnn_final:.5f}: " + (f"at {gd_equal_s:.0f} s" if gd_equal_s is not None else "never"))
    print(f"  CNN midpoint RMSE / per-texel GD: {cnn['midpoint_rmse'] / gd['midpoint_rmse']:.2f} (target <= 0.67), "
          f"/ per-texel GD + interpolation term: {cnn['midpoint_rmse'] / gd_interpolation['midpoint_rmse']:.2f}; "
          f"SG12 RMSE / CNN: {row['fixed SG12']['rmse'] / cnn['rmse']:.2f}, "
          f"SH L2 RMSE / CNN: {row['SH L2']['rmse'] / cnn['rmse']:.2f} (target >= 2)")
    return {"scene": scene_name, "texels": len(texels), "rows": rows, "cnn_plateau_s": plateau_s,
            "gd_time_to_cnn_loss_s": gd_equal_s}


def _smoothed(losses, window: int = 10):
    import numpy as np

    losses = np.asarray(losses, np.float64)
    return np.array([losses[max(0, i - window + 1):i + 1].mean() for i in range(len(losses))])


def _time_to_within(seconds, losses, tolerance: float, target: float | None = None):
    """First time the smoothed loss is within `tolerance` of `target` (default: its own final value); None if never."""
    smooth = _smoothed(losses)
    goal = (smooth[-1] if target is None else target) * (1 + tolerance)
    hits = [t for t, v in zip(seconds, smooth) if v <= goal]
    return float(hits[0]) if hits else None


def _lobe_width(roughness: float) -> float:
    """1/sqrt(lam) of the GGX lobe in the reflection domain (the kernel of shaders/env_visibility.py), radians."""
    from ..shaders.sg_math import clamp_roughness, ndf_sg

    return 1.0 / math.sqrt(float(ndf_sg(None, clamp_roughness(roughness))[1]) / 4.0)


def bench_sg_count(out_root: Path, scenes=("spheres", "room"), budget_s: float = 60.0) -> dict:
    """How many SGs a material needs: per scene, the CNN at each candidate N (same data, same budget), and the
    relative error of the radiance a surface of each roughness reflects (training.sg_fit.glossy_error). The
    rule in bake_directory/bake_plan.py (SG_COUNT_BY_ROUGHNESS) is the smallest N whose error, worst over the scenes,
    is within SG_COUNT_ERROR_BUDGET of the error at the largest N."""
    import numpy as np
    import torch

    from ..bake_directory.bake_plan import SG_COUNT_CANDIDATES, SG_COUNT_ERROR_BUDGET
    from ..training.sg_fit import LightFieldData, TrainConfig, Trainer, glossy_error, reconstruct

    roughnesses = (0.05, 0.15, 0.25, 0.35, 0.45, 0.55)
    errors = {}  # scene -> N -> [error per roughness]
    for scene_name in scenes:
        _, images, normals, _, _, _ = _rendered_lightfields(out_root, scene_name)
        data = LightFieldData.from_numpy(images, normals)
        errors[scene_name] = {}
        for n in SG_COUNT_CANDIDATES:
            torch.manual_seed(0)
            trainer = Trainer(data, TrainConfig(sg_count=n, time_budget_s=budget_s, plateau_epochs=10**9))
            trainer.train()
            prediction = reconstruct(*trainer.parameters_numpy(), images.shape[1])  # glossy_error cuts the horizon
            errors[scene_name][n] = [glossy_error(prediction, images, normals, r) for r in roughnesses]
            print(f"sg count {scene_name} N={n:>2}: " + ", ".join(
                f"r {r:.2f}: {e:.4f}" for r, e in zip(roughnesses, errors[scene_name][n])), flush=True)
    worst = {n: np.max([errors[s][n] for s in scenes], axis=0) for n in SG_COUNT_CANDIDATES}
    ratio = {n: np.max([np.array(errors[s][n]) / np.array(errors[s][SG_COUNT_CANDIDATES[-1]]) for s in scenes], axis=0)
             for n in SG_COUNT_CANDIDATES}  # worst over the scenes of error(N) / error(most N)
    pixel = math.sqrt(4 * math.pi) / 16  # angular size of an R = 16 pixel
    need = [next(n for n in SG_COUNT_CANDIDATES if ratio[n][i] <= 1 + SG_COUNT_ERROR_BUDGET)
            if _lobe_width(r) >= pixel else "most (lobe narrower than a pixel)" for i, r in enumerate(roughnesses)]
    print(f"\nsg count: relative error of reflected radiance (worst of {', '.join(scenes)}), {budget_s:g} s CNN each")
    print("  N   " + " ".join(f"r={r:<6.2f}" for r in roughnesses))
    for n in SG_COUNT_CANDIDATES:
        print(f"  {n:<3} " + " ".join(f"{e:<8.4f}" for e in worst[n]))
    print(f"  needed (within {100 * SG_COUNT_ERROR_BUDGET:.0f} % of N={SG_COUNT_CANDIDATES[-1]} on every scene): "
          + ", ".join(f"r {r:.2f} -> {n}" for r, n in zip(roughnesses, need)))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6, 4))
    for i, r in enumerate(roughnesses):
        axes.plot(SG_COUNT_CANDIDATES, [worst[n][i] for n in SG_COUNT_CANDIDATES], "o-", label=f"roughness {r:.2f}")
    axes.set_xlabel("SGs per texel (N)")
    axes.set_ylabel("relative RMSE of reflected radiance")
    axes.set_yscale("log")
    axes.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(out_root / "sg_count.png", dpi=120)
    plt.close(figure)
    return {"roughness": list(roughnesses), "errors": {s: {str(n): v for n, v in e.items()} for s, e in errors.items()},
            "needed": dict(zip(map(str, roughnesses), need)), "budget_s": budget_s}


def bench_apply(out_root: Path, sg_counts=(4, 8, 16, 32)) -> list[dict]:
    """Per SG count: node count and build time of the evaluator group, EEVEE's first render of the baked
    `spheres` (shader compilation included) and a second render of the same view (compiled), 256x144.
    EEVEE runs on this machine's OpenGL (llvmpipe, software, without a GPU): the compile share is what
    scales with N; absolute frame times need a GPU."""
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.evaluate import render_eevee
    from ..blender_addon.pipeline import BakeJob

    rows = []
    for n in sg_counts:
        scene = build_demo_scene("spheres")
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 256, 144, 100
        settings = BakeSettings.from_preset("draft", lightfield_resolution=8, samples=8, sg_count=n,
                                            training_budget_s=5.0, irradiance_detail=1)  # 32 SGs need detail 1
        out = out_root / f"apply_sg{n}"
        job = BakeJob(scene, settings, out, stages=("capture", "render", "train", "apply"))
        job.run()
        report = __import__("json").loads((out / "report.json").read_text())
        _, seconds, failed = render_eevee(scene, [scene.camera.name] * 3, out)
        rows.append({"sg_count": n, "nodes": report["apply"]["nodes"], "apply_s": report["timings_s"].get("apply"),
                     "eevee_uniform_bytes": max((report["apply"].get("eevee_uniform_bytes") or {0: 0}).values()),
                     "eevee_first_render_s": round(seconds[0], 2),
                     "eevee_compiled_render_s": round(min(seconds[1:]), 2),
                     # first render minus a compiled one; None where later renders took longer than the first
                     # (measured with both node-group builders on llvmpipe)
                     "eevee_compile_s": round(seconds[0] - min(seconds[1:]), 2)
                     if seconds[0] > min(seconds[1:]) else None, "eevee_shader_errors": failed})
        print(f"apply N={n:>2}: {rows[-1]['nodes']} nodes, EEVEE uniforms {rows[-1]['eevee_uniform_bytes']} bytes, "
              f"apply {rows[-1]['apply_s']} s, EEVEE first render "
              f"{rows[-1]['eevee_first_render_s']} s, compiled {rows[-1]['eevee_compiled_render_s']} s "
              + (f"-> compile ~{rows[-1]['eevee_compile_s']} s" if rows[-1]["eevee_compile_s"] is not None
                 else "-> compile not separable from the frame time") + (f"; shaders FAILED: {failed}" if failed else ""))
    return rows


def bench_presets(out_root: Path, scenes, presets, earlier_rows=(), device: str = "cpu") -> list[dict]:
    """Each preset end to end (capture .. evaluate, EEVEE included) on each scene: bake time, share of time
    per stage, FLIP overall and per roughness class; a Pareto plot of bake time against FLIP. Rows of earlier
    runs (other scenes or presets, e.g. Production run on its own) are kept unless measured again."""
    import json

    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.pipeline import BakeJob

    measured = {(s, p, device) for s in scenes for p in presets}
    rows = [r for r in earlier_rows if (r["scene"], r["preset"], _device_of(r)) not in measured]
    for name in scenes:
        for preset in presets:
            scene = build_demo_scene(name)
            out = out_root / f"preset_{name}_{preset}"
            start = time.perf_counter()
            job = BakeJob(scene, BakeSettings.from_preset(preset, device=device), out)
            job.run()
            total = time.perf_counter() - start
            errors = json.loads((out / "report.json").read_text())["errors"]
            eevee = errors.get("eevee") or {}
            bake_s = sum(v for k, v in job.timings.items() if k != "evaluate")
            rows.append({"scene": name, "preset": preset, "device": device,
                         "bake_s": round(bake_s, 1), "total_s": round(total, 1),
                         "stage_share": {k: round(v / bake_s, 3) for k, v in job.timings.items() if k != "evaluate"},
                         "flip": round(errors["flip"], 4), "psnr_db": round(errors["psnr"], 2),
                         "flip_by_roughness": {k: None if v["flip"] is None else round(v["flip"], 4)
                                               for k, v in errors["flip_by_roughness"].items()},
                         "flip_by_material": {k: round(v["flip"], 4) for k, v in errors["flip_by_material"].items()},
                         "eevee_flip": None if "flip" not in eevee else round(eevee["flip"], 4),
                         "eevee_without_bake_flip": _rounded((errors.get("eevee_without_bake") or {}).get("flip")),
                         "reference_noise_rmse": round(errors["reference_noise_rmse"], 4),
                         "reference_noise_flip_by_roughness": {
                             k: None if v["flip"] is None else round(v["flip"], 4)
                             for k, v in errors["reference_noise_flip_by_roughness"].items()}})
            _discard_scene(scene)
            row = rows[-1]
            shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in row["stage_share"].items())
            print(f"preset {preset:<10} {name:<10} bake {row['bake_s']:7.1f} s ({shares}); FLIP {row['flip']:.4f} "
                  f"(EEVEE {row['eevee_flip']}, EEVEE without the bake {row['eevee_without_bake_flip']}), by roughness {row['flip_by_roughness']}, reference noise floor "
                  f"{row['reference_noise_flip_by_roughness']}, by material {row['flip_by_material']}")
    rows.sort(key=lambda r: (r["scene"], _device_of(r), list(PRESETS).index(r["preset"])))
    return rows


def _texture_means(scene, out_dir: Path) -> dict:
    """Material name -> {(node name, input identifier): mean RGB} of every link into a BSDF, Mix Shader or Emission
    input of the material's own tree, over the texels of the first baked object using it (a captured bake)."""
    import numpy as np

    from ..blender_addon.capture import ObjectTile
    from ..blender_addon.scene_analysis import BakeTarget, unbaked
    from ..blender_addon.surface_probe import mean_of_links
    from ..blender_addon.surface_shaders import BAKED_BSDFS
    from ..bake_directory.texel_maps import channels, read_texel_maps

    atlas, info = read_texel_maps(out_dir)
    object_ids = channels(atlas, "object_id").astype(np.int64)
    means = {}
    for entry in info["objects"]:
        tile = ObjectTile(**entry)
        obj = scene.objects.get(tile.name)
        if obj is None:  # an instance: measured through its object's first tile
            continue
        for slot in obj.material_slots:
            material = unbaked(slot.material)
            if material is None or material.name in means:
                continue
            inputs = [(node.name, socket.identifier) for node in material.node_tree.nodes
                      if node.type in BAKED_BSDFS | {"MIX_SHADER", "EMISSION"}
                      for socket in node.inputs if socket.type != "SHADER" and socket.is_linked]
            if inputs:
                means[material.name] = mean_of_links(scene, BakeTarget(obj.name, obj, obj.matrix_world.copy()), tile,
                                                     object_ids, material, inputs)
    return means


def _replace_textures_with_means(scene, means: dict) -> int:
    """Unlink each measured input and give it its mean (a Normal input unlinked is the surface's own normal, the mean
    of a bump or normal map's tilt). Returns the inputs replaced."""
    from ..blender_addon.scene_analysis import unbaked

    replaced = 0
    materials = {unbaked(s.material) for o in scene.objects for s in getattr(o, "material_slots", []) if s.material}
    for material in materials:
        for (node_name, identifier), value in means.get(material.name, {}).items():
            socket = next(s for s in material.node_tree.nodes[node_name].inputs if s.identifier == identifier)
            for link in list(socket.links):
                material.node_tree.links.remove(link)
            if socket.type == "RGBA":
                socket.default_value = (*value, 1.0)
            elif socket.type == "VALUE":
                socket.default_value = value[0]
            replaced += 1
    return replaced


def bench_materials(out_root: Path, presets=("draft", "preview")) -> list[dict]:
    """demo:materials with its textures and with each texture replaced by its mean, per preset: the bake's FLIP in
    Cycles and EEVEE, EEVEE without the bake, per material (see the module docstring for the targets)."""
    import json

    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.pipeline import BakeJob

    rows = []
    for preset in presets:
        means = {}
        for variant in ("textured", "mean textures"):
            scene = build_demo_scene("materials")
            replaced = _replace_textures_with_means(scene, means) if variant == "mean textures" else 0
            out = out_root / f"materials_{preset}_{variant.replace(' ', '_')}"
            start = time.perf_counter()
            job = BakeJob(scene, BakeSettings.from_preset(preset), out)
            job.run()
            total = time.perf_counter() - start
            if variant == "textured":
                means = _texture_means(scene, out)
            errors = json.loads((out / "report.json").read_text())["errors"]
            eevee, alone = errors.get("eevee") or {}, errors.get("eevee_without_bake") or {}
            bake_s = sum(v for k, v in job.timings.items() if k != "evaluate")

            def by_material(entries):
                return {k: None if v["flip"] is None else round(v["flip"], 4) for k, v in (entries or {}).items()}

            rows.append({"scene": "materials", "preset": preset, "variant": variant, "inputs_replaced": replaced,
                         "irradiance_detail": job.settings.irradiance_detail,
                         "capture_s": round(job.timings.get("capture", 0.0), 1), "bake_s": round(bake_s, 1),
                         "total_s": round(total, 1), "flip": round(errors["flip"], 4),
                         "eevee_flip": _rounded(eevee.get("flip")), "eevee_without_bake_flip": _rounded(alone.get("flip")),
                         "without_over_with": _rounded(alone["flip"] / eevee["flip"], 2)
                         if alone.get("flip") and eevee.get("flip") else None,
                         "flip_by_material": by_material(errors.get("flip_by_material")),
                         "eevee_flip_by_material": by_material(eevee.get("flip_by_material")),
                         "eevee_without_bake_flip_by_material": by_material(alone.get("flip_by_material")),
                         "plan_left_to_renderer": [f"{m.name}: {m.reason}" for o in job.plan.objects
                                                   for m in o.materials if not m.baked]})
            _discard_scene(scene)
            row = rows[-1]
            print(f"materials {preset:<8} {variant:<14} bake {row['bake_s']:6.1f} s; FLIP Cycles {row['flip']:.4f}, "
                  f"EEVEE with the bake {row['eevee_flip']}, without {row['eevee_without_bake_flip']} "
                  f"(ratio {row['without_over_with']}); per material with / without: "
                  + ", ".join(f"{k} {v} / {row['eevee_without_bake_flip_by_material'].get(k)}"
                              for k, v in row["eevee_flip_by_material"].items()))
        rows.append(_materials_detail_row(preset, out_root / f"materials_{preset}_textured", rows[-2]))
        textured, flat = rows[-3], rows[-2]
        if textured["eevee_flip"] and flat["eevee_flip"]:
            textured["over_mean_textures"] = round(textured["eevee_flip"] / flat["eevee_flip"], 3)
            print(f"materials {preset}: EEVEE FLIP textured / mean textures {textured['over_mean_textures']} "
                  "(target <= 1.2)")
    return rows


def _materials_detail_row(preset: str, textured_dir: Path, textured_row: dict) -> dict:
    """The textured bake again with its diffuse light from the light fields (irradiance detail 1) instead of the
    preset's detail image: the same light fields and SGs (capture, apply and evaluate run on a copy of the bake
    directory), so the two rows differ only in that knob."""
    import json
    import shutil

    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.pipeline import BakeJob

    out = textured_dir.with_name(textured_dir.name + "_detail_1")
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(textured_dir, out, ignore=shutil.ignore_patterns("baked.blend", "irradiance_detail.exr"))
    scene = build_demo_scene("materials")
    job = BakeJob(scene, BakeSettings.from_preset(preset, irradiance_detail=1), out,
                  stages=("capture", "apply", "evaluate"))
    job.run()
    errors = json.loads((out / "report.json").read_text())["errors"]
    eevee, alone = errors.get("eevee") or {}, errors.get("eevee_without_bake") or {}
    _discard_scene(scene)
    row = {"scene": "materials", "preset": preset, "variant": "textured, irradiance detail 1",
           "irradiance_detail": 1, "capture_s": round(job.timings.get("capture", 0.0), 1),
           "flip": round(errors["flip"], 4), "eevee_flip": _rounded(eevee.get("flip")),
           "eevee_without_bake_flip": _rounded(alone.get("flip")),
           "eevee_flip_by_material": {k: _rounded(v["flip"]) for k, v in (eevee.get("flip_by_material") or {}).items()}}
    detail = BakeSettings.from_preset(preset).irradiance_detail
    print(f"materials {preset:<8} irradiance detail {detail} / 1: capture {textured_row.get('capture_s')} / "
          f"{row['capture_s']} s; EEVEE FLIP {textured_row['eevee_flip']} / {row['eevee_flip']}; Checker Floor "
          f"{textured_row['eevee_flip_by_material'].get('Checker Floor')} / "
          f"{row['eevee_flip_by_material'].get('Checker Floor')}")
    return row


def bench_geometry(out_root: Path, preset="draft") -> list[dict]:
    """demo:geometry (a smooth monkey, a Bevel + Array + Subdivision stack, extruded text, a bevelled curve, node and
    collection instances, a metaball, a NURBS surface, particles baked as object copies) at one preset: per object its
    geometry, texels and the bake's FLIP in EEVEE with and without it, per material; EEVEE's frame time with the
    instance tiles, without them and with the particle system's own instances in place of the copies."""
    import json

    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.pipeline import BakeJob

    scene = build_demo_scene("geometry")
    out = out_root / f"geometry_{preset}"
    job = BakeJob(scene, BakeSettings.from_preset(preset, instance_copies=True), out)
    job.run()
    errors = json.loads((out / "report.json").read_text())["errors"]
    eevee, alone = errors.get("eevee") or {}, errors.get("eevee_without_bake") or {}
    texels = {o["name"]: o["texels"] for o in job.results["capture"].objects}
    rows = []
    for plan in job.plan.objects:
        material = plan.materials[0].name if plan.materials else None
        rows.append({"scene": "geometry", "preset": preset, "object": plan.name, "geometry": plan.geometry,
                     "baked": plan.bake_lightfield, "texels": texels.get(plan.name, 0),
                     "capture_s": round(job.timings["capture"], 2),
                     "eevee_flip": _rounded((eevee.get("flip_by_material") or {}).get(material, {}).get("flip")),
                     "eevee_without_bake_flip": _rounded(
                         (alone.get("flip_by_material") or {}).get(material, {}).get("flip"))})
        row = rows[-1]
        print(f"geometry {preset:<8} {plan.name:<8} {plan.geometry:<36} texels {row['texels']:5d}; EEVEE FLIP with the "
              f"bake {row['eevee_flip']}, without {row['eevee_without_bake_flip']}")
    rows.append({"scene": "geometry", "preset": preset, "object": "(all)", "capture_s": round(job.timings["capture"], 2),
                 "bake_s": round(sum(v for k, v in job.timings.items() if k != "evaluate"), 1),
                 "flip": _rounded(errors.get("flip")), "eevee_flip": _rounded(eevee.get("flip")),
                 "eevee_without_bake_flip": _rounded(alone.get("flip"))})
    print(f"geometry {preset}: capture {rows[-1]['capture_s']} s, bake {rows[-1]['bake_s']} s; FLIP Cycles "
          f"{rows[-1]['flip']}, EEVEE with the bake {rows[-1]['eevee_flip']}, without {rows[-1]['eevee_without_bake_flip']}")
    rows[-1].update(_instance_tile_cost(scene))
    print(f"geometry {preset}: EEVEE frame at 960 x 540 {rows[-1]['eevee_frame_s_instance_tiles']} s with per-instance "
          f"tiles, {rows[-1]['eevee_frame_s_object_tiles']} s with the instances reading their object's tile"
          + (f", {rows[-1]['eevee_frame_s_original_instances']} s with the particle system's own instances in place of "
             "the copies" if "eevee_frame_s_original_instances" in rows[-1] else ""))
    _discard_scene(scene)
    return rows


def _instance_tile_cost(scene, frames=3) -> dict:
    """EEVEE's frame time of a baked scene (median of `frames` renders after one that compiles the shaders) with its
    instances' own tiles, and with them taken off (every instance then reads its object's tile: the lookup's cost)."""
    import statistics

    import bpy

    from ..blender_addon import lightmap_modifier, stand_ins
    from ..blender_addon.scene_analysis import active_scene, quiet_stdout

    scene.render.engine = "BLENDER_EEVEE_NEXT" if bpy.app.version < (5, 0, 0) else "BLENDER_EEVEE"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 960, 540, 100
    scene.render.filepath = "/dev/null" if sys.platform != "win32" else "NUL"

    def frame_s():
        times = []
        with active_scene(scene), quiet_stdout():
            for k in range(frames + 1):
                start = time.perf_counter()
                bpy.ops.render.render(scene=scene.name)
                times.append(time.perf_counter() - start)
        return round(statistics.median(times[1:]), 3)

    with_tiles = frame_s()
    saved = {obj: lightmap_modifier.swap_instance_tiles(obj, None) for obj in scene.objects
             if lightmap_modifier.instance_tiles_of(obj) is not None}
    without = frame_s()
    for obj, tiles in saved.items():
        lightmap_modifier.swap_instance_tiles(obj, tiles)
    cost = {"eevee_frame_s_instance_tiles": with_tiles, "eevee_frame_s_object_tiles": without,
            "instancers": sorted(o.name for o in saved)}
    copied = sorted(o.name for o in scene.objects if stand_ins.copied(o))
    if copied:  # the particles as object copies (baked) against the particle system's own instances (unbaked)
        with stand_ins.original_instancing(scene):
            cost["eevee_frame_s_original_instances"] = frame_s()
        cost["copied_instancers"] = copied
    return cost


def _discard_scene(scene):
    """Remove a demo scene, its bake and every data-block only it used, so the next demo built in this process gets
    its own names: its plan and report say "Floor", not "Floor.002"."""
    import bpy

    from ..blender_addon.apply import remove_bake

    remove_bake(scene)
    bpy.data.scenes.remove(scene)
    bpy.data.orphans_purge(do_local_ids=True, do_linked_ids=True, do_recursive=True)


def _device_of(row: dict) -> str:
    return row.get("device", "cpu")  # rows written before the --device option were all on the CPU


def _plot_pareto(path: Path, rows: list, encoder_rows=()):
    """Bake time against FLIP per scene: all pixels, and the glossy pixels of each roughness class. The encoders
    section's bakes of `spheres` (free SGs against fixed SG12 and SH L2 at equal bytes) are drawn as their own
    points where they have a bake time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("all pixels", lambda r: r["flip"]),
              ("glossy, roughness < 0.3", lambda r: r["flip_by_roughness"].get("roughness < 0.3")),
              ("glossy, 0.3 <= roughness < 0.6", lambda r: r["flip_by_roughness"].get("0.3 <= roughness < 0.6")))
    figure, axes = plt.subplots(1, len(panels), figsize=(15, 4))
    for ax, (title, value) in zip(axes, panels):
        for name, device in sorted({(r["scene"], _device_of(r)) for r in rows}):
            mine = [r for r in rows if (r["scene"], _device_of(r)) == (name, device) and value(r) is not None]
            ax.plot([r["bake_s"] for r in mine], [value(r) for r in mine], "o-" if device == "cpu" else "o--",
                    label=name if device == "cpu" else f"{name}, OptiX + CUDA")
            for r in mine:
                ax.annotate(r["preset"], (r["bake_s"], value(r)), fontsize=7)
        for r in (r for r in encoder_rows if r.get("bake_s") and value(r) is not None):
            y = value(r)
            ax.plot([r["bake_s"]], [y], "s" if "free" in r["encoder"] else "x", color="grey")
            ax.annotate(f"spheres, {r['encoder']}, {r['bytes_per_texel']} B", (r["bake_s"], y), fontsize=6,
                        color="grey")
        ax.set_xscale("log")
        ax.set_xlabel("bake time (s, capture to apply)")
        ax.set_ylabel("mean FLIP vs Cycles reference")
        ax.set_title(title)
        ax.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _over_glossy(classes: dict, key: str = "flip") -> float:
    """Pixel-weighted mean of `key` over the roughness classes of glossy (baked) pixels that have pixels; an RMSE
    key is averaged as a mean square."""
    names = [k for k in classes if not k.startswith("roughness >=") and classes[k]["pixels"]]
    total = max(sum(classes[k]["pixels"] for k in names), 1)
    if key == "rmse":
        return math.sqrt(sum(classes[k][key] ** 2 * classes[k]["pixels"] for k in names) / total)
    return sum(classes[k][key] * classes[k]["pixels"] for k in names) / total


def _rounded(value, digits: int = 4):
    return None if value is None else round(value, digits)


def _rounded_values(values: dict) -> dict:
    return {k: _rounded(v) for k, v in values.items()}


def _mean_value(by_key: dict) -> float:
    return sum(by_key.values()) / max(len(by_key), 1)


def bench_encoders(out_root: Path, budget_s: float = 60.0, resolution: int = 32, samples: int = 32,
                   reference_samples: int = 128, texel_density: float = 4.0,
                   lobe_refit_steps: int = LOBE_REFIT_STEPS, seeds: int = 3) -> list[dict]:
    """The free SGs against the production lightmappers' encodings at equal bytes per texel, on `spheres`: CNN with
    5 SGs (70 B) against fixed SG12 by NNLS (72 B), and CNN with 4 SGs (56 B) against L2 SH (54 B, shaded by the
    SH variant of the node group); each baked, applied and evaluated against Cycles (RMSE and FLIP on glossy
    pixels), plus the numpy error of the reflected radiance per material (glossy_error of its texels at its
    roughness, against the rendered light fields; the floor is an irradiance lightmap and has no SGs), and for the
    SG encoders that error split into the SGs' fit and the node group's closed form (encoding_error_split). The
    light fields are Production's resolution (R = 32) at Draft's density (4 texels per metre) and 32 spp, and the
    free SGs get the presets' lobe refit (lobe_refit_steps; it reaches roughness >= lobe_refit_min_roughness(R):
    0.2 at R = 32, 0.28 at R = 16); the baselines' fixed lobes have nothing to refit. The CNN is trained `seeds`
    times on the same light fields (seeds 0, 1, ...): one training's glossy RMSE varies by up to 30 % with its
    initial weights (docs/design-additions.md §26), so a free encoder's row holds the mean over its trainings and
    each training's RMSE (the split is of seed 0's). §18 has the ratios at R = 16 and at 128 spp, §19 the split,
    §22 against texel density, §25-26 this setting's."""
    import numpy as np

    from ..blender_addon.apply import apply_stage
    from ..blender_addon.capture import capture
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.evaluate import evaluate_stage
    from ..blender_addon.render import render_stage
    from ..blender_addon.scene_analysis import build_plan
    from ..bake_directory.image_metrics import rmse_against_converged
    from ..bake_directory.lightfield_tiles import read_images
    from ..bake_directory.sg_textures import read_sg_texture, read_sh_texture
    from ..bake_directory.texel_maps import channels, read_texel_maps, texels_of_objects
    from ..training.baselines import eval_sh
    from ..training.glossy_refit import encoding_error_split
    from ..training.sg_fit import glossy_error, reconstruct
    from ..training.train_stage import evenly, texel_roughness, train_stage

    rows = []

    def reflected_errors(prediction, images, normals, roughness) -> dict:
        """Roughness -> glossy_error of that material's texels (it cuts the prediction at the horizon itself)."""
        return {f"{value:g}": round(glossy_error(prediction[roughness == value], images[roughness == value],
                                                 normals[roughness == value], value), 4)
                for value in np.unique(roughness)}

    for name, sg_count, encoder in (("free SG5 (CNN)", 5, "cnn"), ("fixed SG12 (NNLS)", 5, "fixed_sg"),
                                    ("free SG4 (CNN)", 4, "cnn"), ("SH L2 (least squares)", 4, "sh_l2")):
        scene = build_demo_scene("spheres")
        plan = build_plan(scene, BakeSettings.from_preset("draft", lightfield_resolution=resolution, samples=samples,
                                                          sg_count=sg_count, uniform_sg_count=True,
                                                          training_budget_s=budget_s, texel_density=texel_density,
                                                          lobe_refit_steps=lobe_refit_steps))
        out = out_root / f"encoders_{encoder}{sg_count}_density{texel_density:g}_r{resolution}_{samples}spp" \
            f"{f'_lobes{lobe_refit_steps}' if lobe_refit_steps else ''}"
        start = time.perf_counter()
        capture(scene, plan, out)
        render_stage(scene, plan, out)
        render_s = time.perf_counter() - start
        atlas, texel_info = read_texel_maps(out)
        texels, images = read_images(out / "lightfield")
        with_sgs = texels_of_objects(atlas, texel_info, texels, plan.sg_objects)  # the floor is a lightmap, no SGs
        texels, images = texels[with_sgs], images[with_sgs]
        normals = channels(atlas, "Ng.X", 3)[texels[:, 0], texels[:, 1]].astype(np.float64)
        roughness = texel_roughness(atlas, texel_info, texels, plan)
        r, c = texels[:, 0], texels[:, 1]
        trainings, references = [], {}  # each training is scored against the same path-traced references
        for seed in range(seeds if encoder == "cnn" else 1):  # the baselines are least squares: one answer
            start = time.perf_counter()
            trained = train_stage(out, plan, encoder=encoder, seed=seed)
            apply_stage(scene, plan, out)
            bake_s = render_s + time.perf_counter() - start
            errors = evaluate_stage(scene, plan, out, views=2, with_eevee=False, reference_samples=reference_samples,
                                    reference_cache=references)
            classes = errors["flip_by_roughness"]
            split = None  # the SH baseline has no SGs to split; the free SGs' split is seed 0's
            if encoder == "sh_l2":
                prediction = eval_sh(read_sh_texture(out / "sg_lightfield.exr")[0][r, c], images.shape[1])
            else:
                axis, sharpness, amplitude, _ = read_sg_texture(out / "sg_lightfield.exr")
                axis, sharpness, amplitude = axis[r, c], sharpness[r, c], amplitude[r, c]
                prediction = reconstruct(axis, sharpness, amplitude, images.shape[1])
                if seed == 0:
                    split = {}
                    for value in np.unique(roughness):  # up to ENCODING_SPLIT_TEXELS evenly picked texels per sphere
                        each = evenly(np.flatnonzero(roughness == value), ENCODING_SPLIT_TEXELS)
                        split[f"{value:g}"] = {k: round(v, 4) for k, v in encoding_error_split(
                            images[each], normals[each], axis[each], sharpness[each], amplitude[each],
                            value).items()}
            glossy_rmse = _over_glossy(classes, "rmse")
            glossy_noise_rmse = _over_glossy(errors["reference_noise_flip_by_roughness"], "rmse")
            trainings.append({
                "seed": seed, "bytes_per_texel": trained.bytes_per_texel, "glossy_rmse": glossy_rmse,
                "glossy_reference_noise_rmse": glossy_noise_rmse,
                "glossy_rmse_against_converged": rmse_against_converged(glossy_rmse, glossy_noise_rmse),
                "glossy_flip": _over_glossy(classes, "flip"), "flip": errors["flip"],
                "reflected_error": reflected_errors(prediction, images, normals, roughness),
                "encoding_error_split": split, "fit_s": trained.seconds, "bake_s": bake_s,
                "flip_by_roughness": {k: v["flip"] for k, v in classes.items()},
                "rmse_by_roughness": {k: v["rmse"] for k, v in classes.items()},
                "flip_by_material": {k: v["flip"] for k, v in errors["flip_by_material"].items()}})
        _discard_scene(scene)  # after the last training: bake removed, scene deleted, names free again
        rows.append({"encoder": name, "texel_density": texel_density, "reference_samples": reference_samples,
                     **_mean_over_trainings(trainings),
                     "trainings": [{"seed": t["seed"], "glossy_rmse": round(t["glossy_rmse"], 4),
                                    "glossy_rmse_against_converged": round(t["glossy_rmse_against_converged"], 4),
                                    "glossy_flip": round(t["glossy_flip"], 4),
                                    "rmse_by_roughness": _rounded_values(t["rmse_by_roughness"])} for t in trainings]})
    _print_encoders(rows, f"spheres, {texel_density:g} texels/m, R = {resolution}, {samples} spp; "
                    f"CNN {budget_s:g} s{f' + {lobe_refit_steps} lobe-refit steps' if lobe_refit_steps else ''}, "
                    f"{seeds} training{'s' if seeds > 1 else ''} each; {reference_samples}-spp references")
    return rows


def _mean_over_trainings(trainings: list[dict]) -> dict:
    """One row from an encoder's trainings: numbers and per-key numbers averaged (an RMSE as a root mean square,
    so the mean row's RMSE is that of all its trainings' pixels), the seed-0 split kept."""
    def mean(values, square=False):
        values = [v for v in values if v is not None]
        if not values:
            return None
        return math.sqrt(sum(v * v for v in values) / len(values)) if square else sum(values) / len(values)

    first, row = trainings[0], {}
    for key, value in first.items():
        if key in ("seed", "encoding_error_split"):
            continue
        square = "rmse" in key
        if isinstance(value, dict):
            row[key] = _rounded_values({k: mean([t[key].get(k) for t in trainings], square) for k in value})
        elif isinstance(value, float):
            row[key] = round(mean([t[key] for t in trainings], square), 4 if key not in ("fit_s", "bake_s") else 1)
        else:
            row[key] = value
    row["encoding_error_split"] = first["encoding_error_split"]
    return row


def _print_encoders(rows: list[dict], setting: str):
    """The encoders section's table, the reflected error split and the ratios at equal bytes."""
    print(f"\nencoders at equal bytes ({setting}); reflected radiance error against the rendered light fields, "
          "per sphere's roughness")
    print(f"  {'encoder':<24} {'bytes':>5} {'glossy RMSE':>11} {'(converged)':>11} {'glossy FLIP':>11} {'FLIP':>7}  "
          "reflected error; glossy RMSE of each training")
    for r in rows:
        reflected = ", ".join(f"{k}: {v:.3f}" for k, v in r["reflected_error"].items())
        each = " ".join(f"{t['glossy_rmse']:.4f}" for t in r["trainings"]) if len(r["trainings"]) > 1 else ""
        print(f"  {r['encoder']:<24} {r['bytes_per_texel']:>5} {r['glossy_rmse']:>11.4f} "
              f"{r['glossy_rmse_against_converged']:>11.4f} {r['glossy_flip']:>11.4f} {r['flip']:>7.4f}  {reflected}"
              f"{f'; {each}' if each else ''}")
    print("  (a free encoder's numbers are the mean over its trainings, RMSE as a root mean square)")
    print(f"  (converged): RMSE against the converged image, the references' own noise (RMSE "
          f"{rows[0]['glossy_reference_noise_rmse']:.4f} on glossy pixels) taken out (rmse_against_converged)")
    print("  the SGs' reflected error split (encoding_error_split, held-out views, per roughness): fit of the SGs "
          "to the light field / the node group's closed form against the SGs' exact reflection")
    for r in rows:
        if r["encoding_error_split"]:
            parts = ", ".join(f"{k}: {v['fit']:.3f} / {v['closed_form']:.3f}"
                              for k, v in r["encoding_error_split"].items())
            print(f"  {r['encoder']:<24} {parts}")
    free5, sg12, free4, sh = rows
    for baseline, free in ((sg12, free5), (sh, free4)):
        by_class = ", ".join(f"{name} {baseline['rmse_by_roughness'][name] / rmse:.2f}"
                             for name, rmse in free["rmse_by_roughness"].items()
                             if rmse and not name.startswith("roughness >="))
        ratio = baseline["glossy_rmse"] / free["glossy_rmse"]
        converged = baseline["glossy_rmse_against_converged"] / max(free["glossy_rmse_against_converged"], 1e-9)
        each = [baseline["glossy_rmse"] / t["glossy_rmse"] for t in free["trainings"]]
        spread = f", each training {min(each):.2f} to {max(each):.2f}" if len(each) > 1 else ""
        print(f"  {baseline['encoder']} / {free['encoder']}: glossy RMSE {ratio:.2f}{spread}, against the converged "
              f"image {converged:.2f} (target >= 2; by class: {by_class}), "
              f"glossy FLIP {baseline['glossy_flip'] / free['glossy_flip']:.2f}, "
              f"reflected error {_mean_value(baseline['reflected_error']) / _mean_value(free['reflected_error']):.2f}")


ENCODING_SPLIT_TEXELS = 96  # texels per sphere the encoders section splits the reflected error of (~20 s each)


KNOB_SWEEP = {"texel_density": (2.0, 8.0), "lightfield_resolution": (8, 32), "samples": (4, 64), "sg_count": (4, 24),
              "training_budget_s": (15.0, 240.0), "lightmap_samples": (4, 64), "irradiance_detail": (1, 8),
              "lobe_refit_steps": (0, 600)}
KNOB_SCENES = ("spheres", "room", "courtyard", "materials")


def parse_knob_sweep(text: str) -> dict:
    """'knob=v1:v2,knob=v3' -> {knob: (v1, v2), knob: (v3,)}, knobs from KNOB_SWEEP, values as the setting's type;
    a bare knob name takes KNOB_SWEEP's values. ValueError with one readable message otherwise."""
    sweep = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        knob, _, values = item.partition("=")
        if knob not in KNOB_SWEEP:
            raise ValueError(f"unknown knob '{knob}'; choose from {', '.join(KNOB_SWEEP)}")
        kind = type(KNOB_SWEEP[knob][0])
        try:
            sweep[knob] = tuple(kind(v) for v in values.split(":")) if values else KNOB_SWEEP[knob]
        except ValueError:
            raise ValueError(f"knob '{knob}' takes {kind.__name__} values separated by ':', not '{values}'") from None
        if not all(math.isfinite(v) for v in sweep[knob]):
            raise ValueError(f"knob '{knob}' takes finite values, not '{values}'")
    if not sweep:
        raise ValueError("no knob named")
    return sweep


def knob_settings(knob: str | None, value, training_epochs: int = 0) -> BakeSettings:
    """Draft with one knob changed (none: Draft itself), trained `training_epochs` epochs when above 0: one run of the
    knob sweep, with the bake's own checks of its settings."""
    return BakeSettings.from_preset("draft", **({"training_epochs": training_epochs} if training_epochs else {}),
                                    **({knob: value} if knob else {}))


def bench_knobs(out_root: Path, scene_name: str = "spheres", sweep=None, reference_samples: int = 128,
                training_epochs: int = 0) -> list[dict]:
    """Every quality knob's measured cost and error: from Draft, one knob at a time to each value of KNOB_SWEEP,
    baked end to end and evaluated against Cycles (2 views, 256x144, no EEVEE): bake seconds per stage and FLIP
    overall, on glossy pixels and per material. The presets in bake_directory/bake_plan.py are chosen from this
    table. The references are path traced once at `reference_samples` and shared by every run (the scene is built
    the same each time). training_epochs > 0 trains every run that many epochs instead of Draft's time budget, so
    that knobs which change the texel count are compared at equal training, not at equal seconds."""
    import json

    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.evaluate import evaluate_stage
    from ..blender_addon.pipeline import BakeJob

    sweep = sweep or KNOB_SWEEP
    runs = [("draft", None, None)] + [(f"{knob}={value:g}", knob, value) for knob, values in sweep.items()
                                      for value in values]
    rows, references = [], {}
    for label, knob, value in runs:
        scene = build_demo_scene(scene_name)
        settings = knob_settings(knob, value, training_epochs)
        out = out_root / f"knobs_{scene_name}_{label.replace('=', '_')}"
        job = BakeJob(scene, settings, out, stages=("capture", "render", "train", "apply"))
        job.run()
        errors = evaluate_stage(scene, job.plan, out, views=2, with_eevee=False, reference_samples=reference_samples,
                                test_samples=min(reference_samples, 128), reference_cache=references)
        classes = errors["flip_by_roughness"]
        report = json.loads((out / "report.json").read_text())
        rows.append({"run": label, "scene": scene_name, "reference_samples": reference_samples,
                     "training_epochs": training_epochs, "bake_s": round(sum(job.timings.values()), 1),
                     "glossy_noise_flip": round(_over_glossy(errors["reference_noise_flip_by_roughness"]), 4),
                     "stages_s": {k: round(v, 1) for k, v in job.timings.items()},
                     "flip": round(errors["flip"], 4),
                     "glossy_flip": round(_over_glossy(classes), 4),
                     "lightmap_flip": _rounded(classes["roughness >= 0.6"]["flip"]),
                     "lightmap_noise_flip": _rounded(
                         errors["reference_noise_flip_by_roughness"]["roughness >= 0.6"]["flip"]),
                     "texels": report.get("texels"), "bytes_per_texel": report.get("bytes_per_texel"),
                     "reference_noise_rmse": round(errors["reference_noise_rmse"], 4),
                     "flip_by_material": {k: round(v["flip"], 4) for k, v in errors["flip_by_material"].items()
                                          if v["flip"] is not None}})
        r = rows[-1]
        print(f"knob {r['run']:<24} bake {r['bake_s']:7.1f} s {r['stages_s']}  FLIP {r['flip']:.4f}  glossy FLIP "
              f"{r['glossy_flip']:.4f} (reference noise {r['glossy_noise_flip']:.4f})  rough (lightmap) FLIP "
              f"{r['lightmap_flip']} (noise {r['lightmap_noise_flip']})  ({r['texels']} texels, "
              f"{r['bytes_per_texel']} B/texel); by material {r['flip_by_material']}", flush=True)
        _discard_scene(scene)
    return rows


def bench_farm(out_root: Path, tile_count: int = 3, preset: str = "draft") -> dict:
    """The Open Job Description template run locally (openjd run: one process per task) against the one-process
    bake of the same scene and preset, both whole (capture to evaluate), one after the other on this machine."""
    import json
    import shutil
    import subprocess

    import numpy as np

    repo = Path(__file__).resolve().parent.parent
    single, farm = out_root / f"farm_single_{preset}", out_root / f"farm_openjd_{preset}"
    for folder in (single, farm):
        shutil.rmtree(folder, ignore_errors=True)
    start = time.perf_counter()
    one = subprocess.run([sys.executable, str(repo / "headless" / "bake.py"), "--scene", "demo:spheres", "--preset",
                          preset, "--out", str(single)], capture_output=True, text=True)
    one_s = time.perf_counter() - start
    if one.returncode != 0:
        raise RuntimeError(f"one-process bake failed: {one.stderr[-1000:]}")
    start = time.perf_counter()
    job = subprocess.run([str(Path(sys.executable).parent / "openjd"), "run",
                          str(repo / "farm" / "openjd" / "sg_lightfield_bake.yaml"), "-p", "BlendFile=demo:spheres",
                          "-p", f"OutputDir={farm}", "-p", f"Preset={preset}", "-p", f"TileCount={tile_count}",
                          "-p", f"Python={sys.executable}", "-p", f"Repository={repo}"], capture_output=True, text=True)
    farm_s = time.perf_counter() - start
    if job.returncode != 0:
        raise RuntimeError(f"openjd run failed: {job.stdout[-1000:]}")
    from ..bake_directory.exr_io import read_exr

    starts = []  # what each task pays before its stage: Python, bpy, the scene and the plan (a --plan-only run)
    for _ in range(3):
        begin = time.perf_counter()
        subprocess.run([sys.executable, str(repo / "headless" / "bake.py"), "--scene", "demo:spheres", "--preset",
                        preset, "--out", str(out_root / "farm_startup"), "--plan-only"], capture_output=True)
        starts.append(time.perf_counter() - begin)
    tasks = 1 + tile_count + 1 + 1
    names = sorted(p.relative_to(single).as_posix() for p in single.glob("*/*.exr"))
    identical = all(np.array_equal(read_exr(single / n)[0], read_exr(farm / n)[0]) for n in names)
    stage_s = {name: json.loads((folder / "report.json").read_text())["timings_s"]
               for name, folder in (("one_process", single), ("openjd", farm))}
    row = {"scene": "spheres", "preset": preset, "tile_count": tile_count, "one_process_s": round(one_s, 1),
           "openjd_s": round(farm_s, 1), "overhead_percent": round(100 * (farm_s / one_s - 1), 1),
           "tiles_compared": len(names), "tiles_identical": identical, "tasks": tasks,
           "task_start_s": round(float(np.median(starts)), 2),
           "start_overhead_percent": round(100 * (tasks - 1) * float(np.median(starts)) / one_s, 1),
           "stage_s_one_process": stage_s["one_process"], "stage_s_openjd": stage_s["openjd"]}
    print(f"farm: spheres {preset}, one process {one_s:.1f} s, openjd run ({tile_count} render tasks, each task its "
          f"own process) {farm_s:.1f} s: overhead {row['overhead_percent']:+.1f} % (target <= 10 %; the stages' own "
          f"run-to-run spread is in it); {tasks} tasks starting at {row['task_start_s']:.2f} s each: "
          f"{row['start_overhead_percent']:.1f} % of the one-process bake; "
          f"{len(names)} tiles {'bit-identical' if identical else 'DIFFER'}")
    return row


def bench_stability(out_root: Path, variants=None) -> list[dict]:
    """The numerical-stability sweep: each extreme `spheres` variant (demo_scenes.STABILITY_VARIANTS) baked end to
    end at small settings and evaluated against its Cycles reference. Reports whether every output (texel maps,
    light fields, SG textures, packed image, the baked render) is finite, and the errors."""
    import numpy as np

    from ..blender_addon.demo_scenes import STABILITY_VARIANTS, build_stability_variant
    from ..blender_addon.evaluate import evaluate_stage
    from ..blender_addon.pipeline import BakeJob
    from ..bake_directory.exr_io import read_exr
    from ..bake_directory.lightfield_tiles import read_images
    from ..bake_directory.sg_textures import read_sg_texture
    from ..bake_directory.texel_maps import read_texel_maps

    rows = []
    for variant in variants or STABILITY_VARIANTS:
        scene, scale = build_stability_variant(variant)
        out = out_root / f"stability_{variant}"
        settings = BakeSettings.from_preset("draft", texel_density=4.0 / scale, lightfield_resolution=8, samples=16,
                                            training_budget_s=20.0)
        start = time.perf_counter()
        job = BakeJob(scene, settings, out, stages=("capture", "render", "train", "apply"))
        job.run()
        bake_s = time.perf_counter() - start
        atlas, _ = read_texel_maps(out)
        _, images = read_images(out / "lightfield")
        sg = read_sg_texture(out / "sg_lightfield.exr")
        packed, _, _ = read_exr(out / "sg_packed.exr")
        errors = evaluate_stage(scene, job.plan, out, views=1, resolution=(128, 72), reference_samples=64,
                                with_eevee=False)
        finite = all(np.all(np.isfinite(a)) for a in (atlas, images, *sg[:3], packed))
        finite = finite and all(np.isfinite(errors[k]) for k in ("rmse", "flip"))
        rows.append({"variant": variant, "finite": bool(finite), "bake_s": round(bake_s, 1),
                     "lightfield_max": float(images.max()), "amplitude_max": float(sg[2].max()),
                     "flip": round(errors["flip"], 4), "psnr_db": round(errors["psnr"], 2),
                     "reference_noise_rmse": round(errors["reference_noise_rmse"], 4),
                     "warnings": list(job.plan.warnings)})
        _discard_scene(scene)
        r = rows[-1]
        print(f"stability {variant:<14} finite {str(r['finite']):<5} bake {r['bake_s']:6.1f} s  light field max "
              f"{r['lightfield_max']:10.4g}  SG amplitude max {r['amplitude_max']:10.4g}  FLIP {r['flip']:.4f}  "
              f"PSNR {r['psnr_db']:.2f} dB", flush=True)
    print(f"stability: every output finite in {sum(r['finite'] for r in rows)} of {len(rows)} variants")
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


def _read_bench_json(out: Path) -> dict:
    import json

    try:
        return json.loads((out / "bench.json").read_text())
    except (OSError, ValueError):
        return {}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m headless.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="smaller sections: capture of room only; presets Draft on spheres and room; SG counts on "
                   "spheres only; shorter training; fewer knob values")
    p.add_argument("--out", type=Path, default=Path("bench_out"))
    p.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated subset of " + ",".join(SECTIONS))
    p.add_argument("--scenes", help="presets section: comma-separated demo scenes (default spheres,room,courtyard)")
    p.add_argument("--presets", help="presets section: comma-separated presets (default all); rows of other "
                   "scenes and presets already in OUT/bench.json are kept")
    p.add_argument("--encoder-density", type=float, default=PRESETS["draft"]["texel_density"],
                   metavar="TEXELS_PER_METRE",
                   help="encoders section: texel density of its four bakes (default 4, Draft's; the CNN's budget grows "
                   "with the texel count)")
    p.add_argument("--encoder-reference-samples", type=int, default=128, metavar="SPP",
                   help="encoders section: spp of the path-traced references (default 128)")
    p.add_argument("--encoder-resolution", type=int, default=32, metavar="R",
                   help="encoders section: light-field resolution R, a power of two (default 32, Production's)")
    p.add_argument("--encoder-samples", type=int, default=32, metavar="SPP",
                   help="encoders section: light-field samples per pixel (default 32)")
    p.add_argument("--encoder-training-budget", type=float, metavar="SECONDS",
                   help="encoders section: the CNN's seconds per free-SG bake (default 60, 30 with --quick, times the "
                   "texel count's growth with --encoder-density)")
    p.add_argument("--encoder-lobe-refit-steps", type=int, default=LOBE_REFIT_STEPS, metavar="STEPS",
                   help=f"encoders section: the free SGs' lobe refit (default {LOBE_REFIT_STEPS}, "
                   "the presets'; 0: off)")
    p.add_argument("--encoder-trainings", type=int, metavar="N",
                   help="encoders section: CNN trainings (seeds) per free-SG bake, averaged (default 3, 1 with "
                   "--quick)")
    p.add_argument("--knob-scene", choices=KNOB_SCENES, default="spheres",
                   help="knobs section: the demo scene the knobs are swept on (default spheres)")
    p.add_argument("--knobs", metavar="KNOB[=V1:V2],...",
                   help="knobs section: the knobs and values to sweep (default every knob of KNOB_SWEEP at its values; "
                   "a bare name takes those), e.g. lightfield_resolution=32,texel_density=8")
    p.add_argument("--knob-reference-samples", type=int, default=128, metavar="SPP",
                   help="knobs section: spp of the path-traced references, rendered once for the whole sweep "
                   "(default 128)")
    p.add_argument("--knob-training-epochs", type=int, default=0, metavar="N",
                   help="knobs section: train every run N epochs instead of Draft's time budget (default 0: the "
                   "budget), so that knobs changing the texel count are compared at equal training")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="render and presets sections: Cycles (and the training) on the CPU or on OptiX GPUs and CUDA "
                   "(the render section's numbers are kept apart in bench.json as render_cuda)")
    ns = p.parse_args(argv)
    sections = [s for s in ns.sections.split(",") if s]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        p.error(f"unknown section(s) {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    if not 0.5 <= ns.encoder_density <= 64:
        p.error("--encoder-density takes 0.5 to 64 texels per metre")
    if not 2 <= ns.encoder_reference_samples <= 65536:
        p.error("--encoder-reference-samples takes 2 to 65536")
    if ns.encoder_trainings is not None and not 1 <= ns.encoder_trainings <= 16:
        p.error("--encoder-trainings takes 1 to 16")
    if not 2 <= ns.knob_reference_samples <= 65536:
        p.error("--knob-reference-samples takes 2 to 65536")
    knob_sweep = None
    if ns.knobs is not None:
        try:
            knob_sweep = parse_knob_sweep(ns.knobs)
            for knob, values in knob_sweep.items():  # each run's settings, checked before any work
                for value in values:
                    knob_settings(knob, value, ns.knob_training_epochs)
        except (ValueError, BakeInputError) as error:
            p.error(f"--knobs: {error}")
    else:
        try:
            knob_settings(None, None, ns.knob_training_epochs)
        except BakeInputError as error:
            p.error(f"--knob-training-epochs: {error}")
    texel_share = (ns.encoder_density / PRESETS["draft"]["texel_density"]) ** 2  # same CNN time per texel
    encoder_budget_s = ns.encoder_training_budget if ns.encoder_training_budget is not None else \
        (30.0 if ns.quick else 60.0) * texel_share
    try:  # the encoders' bakes get the bake's own checks of their settings
        BakeSettings.from_preset("draft", lightfield_resolution=ns.encoder_resolution, samples=ns.encoder_samples,
                                 texel_density=ns.encoder_density, training_budget_s=encoder_budget_s,
                                 lobe_refit_steps=ns.encoder_lobe_refit_steps)
    except BakeInputError as error:
        p.error(f"encoders section (--encoder-*): {error}")
    ns.out.mkdir(parents=True, exist_ok=True)
    scenes = ["room"] if ns.quick else ["room", "spheres", "courtyard"]
    presets = ["draft", "preview"] if ns.quick else list(PRESETS)
    results = {}
    if "capture" in sections:
        results["capture"] = bench_capture(scenes, presets, ns.out)
    if "render" in sections:
        results["render" if ns.device == "cpu" else "render_cuda"] = bench_render(ns.out, device=ns.device)
    if "train" in sections:
        results["train"] = [bench_train(ns.out, "spheres", budget_s=30.0 if ns.quick else 120.0)]
        if not ns.quick:
            results["train"].append(bench_train(ns.out, "room", budget_s=300.0, density=8.9))
    if "sgcount" in sections:
        results["sgcount"] = bench_sg_count(ns.out, ("spheres",) if ns.quick else ("spheres", "room"),
                                            budget_s=30.0 if ns.quick else 60.0)
    if "encoders" in sections:
        results["encoders"] = bench_encoders(ns.out, budget_s=encoder_budget_s,
                                             texel_density=ns.encoder_density,
                                             reference_samples=ns.encoder_reference_samples,
                                             resolution=ns.encoder_resolution, samples=ns.encoder_samples,
                                             lobe_refit_steps=ns.encoder_lobe_refit_steps,
                                             seeds=ns.encoder_trainings or (1 if ns.quick else 3))
    if "knobs" in sections:
        results["knobs"] = bench_knobs(ns.out, ns.knob_scene, knob_sweep or (
            {"lightfield_resolution": (32,), "samples": (64,)} if ns.quick else None),
            reference_samples=ns.knob_reference_samples, training_epochs=ns.knob_training_epochs)
    if "apply" in sections:
        results["apply"] = bench_apply(ns.out, (4, 16) if ns.quick else (4, 8, 16, 32))
    earlier = _read_bench_json(ns.out)
    preset_scenes = ns.scenes.split(",") if ns.scenes else ["spheres", "room"] if ns.quick else \
        ["spheres", "room", "courtyard"]
    preset_names = ns.presets.split(",") if ns.presets else ["draft"] if ns.quick else list(PRESETS)
    if set(preset_scenes) - {"spheres", "room", "courtyard", "materials"} or set(preset_names) - set(PRESETS):
        p.error(f"--scenes takes spheres, room, courtyard, materials and --presets {', '.join(PRESETS)}")
    if "presets" in sections:
        results["presets"] = bench_presets(ns.out, preset_scenes, preset_names, earlier.get("presets", ()), ns.device)
    if "materials" in sections:
        results["materials"] = bench_materials(ns.out, ("draft",) if ns.quick else ("draft", "preview"))
    if "geometry" in sections:
        results["geometry"] = bench_geometry(ns.out)
    if "stability" in sections:
        results["stability"] = bench_stability(ns.out)
    if "farm" in sections:
        results["farm"] = bench_farm(ns.out)
    if "hair" in sections:
        from .bench_hair import bench_hair

        results["hair"] = bench_hair(ns.out, ns.quick)
    merged = {**earlier, **results}  # sections run earlier are kept
    if results.keys() & {"presets", "encoders"} and merged.get("presets"):
        _plot_pareto(ns.out / "pareto.png", merged["presets"], merged.get("encoders", ()))
    write_json_atomic(ns.out / "bench.json", merged)
    page = write_results_page(ns.out, merged)
    print(f"\nwritten: {ns.out / 'bench.json'}, {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
