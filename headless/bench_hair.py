"""Hair filter benchmark: `python -m headless.bench --sections hair` (or `python -m headless.bench_hair`).

  inference   onnxruntime (CPU provider) time of each model at 1024x1024 (the network alone, and the product's
              filter call with 1 pass and with its default of 4 mirror passes; medians of 3), and our renderer's
              time for the 4-spp input of the `hair` demo at 1024x1024 (what the filter costs on top of the input) and
              for 16 spp (unfiltered stochastic transparency's cost); its shadow maps' cost against one map
  quality     on the hair dataset's views (headless/hair_dataset.py draws them from seeds; no files needed),
              PSNR and FLIP against the Cycles reference, composited (hair colour x colour factor +
              highlight over grey) and tone-mapped alike, for: stochastic transparency at 4 and 16 spp
              unfiltered, our filter at 1, 2 and 4 spp (4 mirror passes; at 4 spp also 1 and 2), and Intel
              Open Image Denoise (pyoidn) on the 4-spp input; on the validation pairs of the trained styles, on
              --unseen-views further views of the trained styles (indices past the dataset's: never trained on nor
              used to pick weights) and on the held-out style apart, with the per-pair verdicts of the trained
              styles' two splits pooled too.
              Targets: filtered 4 spp beats unfiltered 16 spp on both metrics, and beats OIDN on 4 spp.
  picture     bench_out/hair_rows.png: input 4 spp | ours | OIDN | reference, a few pairs of each split.
  candidates  "ours 4 spp" is the default shipped network (Large); the other shipped one ("base") and --candidate
              NAME=PATH (repeatable) are further 4-spp models scored beside it on the same renders (4 mirror
              passes; the 1- and 2-spp filters are Base networks), timed at 1024x1024 too, with
              per-pair differences against it and against 16 spp; Blender builds a groom differently each run, so
              two models compare fairly only inside one run.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from ..hair import pairs as hair_pairs
from ..hair import raster as hair_raster  # noqa: E402
from ..bake_directory.bake_plan import write_json_atomic  # noqa: E402
from ..hair.filtering import DEFAULT_NETWORK, MODELS_DIR, SHIPPED_MODELS, HairFilterError, load_filter  # noqa: E402
from ..bake_directory.image_metrics import flip, psnr, tonemap  # noqa: E402

HAIR_COLOR, LIGHT, BACKGROUND = np.array(hair_raster.EVALUATION_LOOK[0]), *hair_raster.EVALUATION_LOOK[1:]


def _composite(outputs):
    background = np.full(outputs.shape[1:] + (3,), BACKGROUND)
    return hair_raster.composite(outputs, HAIR_COLOR, background, LIGHT)


def _oidn(image):
    import pyoidn

    return np.asarray(pyoidn.denoise(np.ascontiguousarray(image, np.float32), hdr=True), np.float64)


def bench_inference(models: dict, size: int = 1024, repeats: int = 3, more_4spp_models=()) -> list[dict]:
    import bpy

    from ..hair import blender_scene as hair
    from ..blender_addon.demo_scenes import build_demo_scene
    from ..blender_addon.scene_analysis import active_scene

    rows = []
    scene = build_demo_scene("demo:hair")
    with active_scene(scene):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        strands = hair.strands_from_objects(hair.hair_objects(scene), depsgraph)
        camera = hair.pinhole_camera(scene, depsgraph, width=size, height=size)
        to_light, _, _ = hair.key_light(scene, depsgraph, np.mean(strands.bounds(), axis=0))
    hair_raster.render_stochastic(strands, camera, to_light, 1, shadow_maps=1)  # warm-up: first calls are slower
    start = time.perf_counter()
    render = hair_raster.render_stochastic(strands, camera, to_light, 4)
    input_s = time.perf_counter() - start
    start = time.perf_counter()
    hair_raster.render_stochastic(strands, camera, to_light, 16)
    input16_s = time.perf_counter() - start
    start = time.perf_counter()
    hair_raster.render_stochastic(strands, camera, to_light, 4, shadow_maps=1)
    input_one_map_s = time.perf_counter() - start
    for spp, path in sorted(models.items()) + [(4, Path(path)) for path in more_4spp_models]:
        hair_filter = load_filter(path)
        features = render.network_input(hair_filter.samples)
        hair_filter.run(features)  # warm-up
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            hair_filter.run(features)
            times.append(time.perf_counter() - start)
        filter_s = {}
        for passes in (1, 4):  # the product's call: input reshaping, mirror copies, mean and footprint mask included
            filter_times = []
            for _ in range(repeats):
                start = time.perf_counter()
                hair_filter.filter(render, passes=passes)
                filter_times.append(time.perf_counter() - start)
            filter_s[passes] = float(np.median(filter_times))
        rows.append({"model": path.name, "spp": spp, "size": f"{size}x{size}",
                     "onnxruntime_cpu_s": round(float(np.median(times)), 3),
                     "filter_1_pass_s": round(filter_s[1], 3), "filter_4_passes_s": round(filter_s[4], 3),
                     "stochastic_input_4spp_s": round(input_s, 3), "stochastic_input_16spp_s": round(input16_s, 3),
                     "shadow_maps": hair_raster.SHADOW_MAPS, "stochastic_input_4spp_one_shadow_map_s": round(input_one_map_s, 3),
                     "fragments": render.fragment_count})
    return rows


def _grooms():
    cache = {}

    def get(style, density):
        if (style, density) not in cache:
            import bpy

            from ..hair import blender_scene as hair
            from ..blender_addon.scene_analysis import active_scene

            scene, objects = hair.dataset_groom(style, density)
            with active_scene(scene):
                strands = hair.strands_from_objects(objects, bpy.context.evaluated_depsgraph_get())
            cache[(style, density)] = (objects, strands)
        return cache[(style, density)]
    return get


def candidate_filter(path):
    """A further model to score beside the shipped one: a readable hair filter of 4 samples per pixel, or
    HairFilterError / ValueError saying why not."""
    hair_filter = load_filter(path)
    if hair_filter.samples != 4:
        raise ValueError(f"a {hair_filter.samples}-spp filter; candidates are scored at 4 spp")
    return hair_filter


UNSEEN_SPLIT, POOLED_SPLIT = "unseen views (trained styles)", "trained styles, validation and unseen views pooled"


def unseen_view_jobs(count: int) -> list[tuple[str, int, str]]:
    """Views of the trained styles past the dataset's indices: drawn like its pairs, never rendered into it."""
    from . import hair_dataset

    return hair_dataset.dataset_jobs(hair_dataset.PAIRS + count, 0)[hair_dataset.PAIRS:]


def bench_quality(models: dict, out_root: Path, max_pairs: int = 40, pictures: int = 3,
                  extra_models: dict | None = None, unseen_views: int = 0) -> dict:
    """The dataset's views (headless/hair_dataset.py draws them from seeds, so no files are needed): its
    validation pairs of the trained styles and its held-out style, and unseen_views more views of the trained
    styles; input and Cycles reference rendered here. extra_models: {name: path} of further 4-spp models, scored
    as "<name> 4 spp"."""
    from ..hair.blender_scene import render_reference
    from . import hair_dataset

    filters = {spp: load_filter(path) for spp, path in models.items()}
    candidate_filters = {f"{name} 4 spp": candidate_filter(path) for name, path in (extra_models or {}).items()}
    groom = _grooms()
    jobs = hair_dataset.dataset_jobs(hair_dataset.PAIRS, hair_dataset.HELD_OUT)
    tables, rows_img = {}, []
    validation = [job for job in jobs if job[0] == "train" and hair_pairs.split_of(job[1]) == "validation"]
    held_out = [job for job in jobs if job[0] == "held_out"]
    splits = [("validation (trained styles)", validation[:max_pairs]), ("held-out style", held_out[:max_pairs])]
    if unseen_views:
        splits.insert(1, (UNSEEN_SPLIT, unseen_view_jobs(unseen_views)))
    split_scores = {}
    for split_name, views in splits:
        scores, without_hair = {}, 0
        split_scores[split_name] = scores
        for name, index, style in views:
            # Blender's hair generator does not give the same strands twice (curve counts differ by ~0.5 %
            # between builds), so the methods are compared on this run's build, input and reference alike.
            objects, strands = groom(style, hair_dataset.DENSITY)
            camera, light, render, _ = hair_dataset.dataset_view(strands, name, index, samples=16)
            target = render_reference(objects, camera, light, samples=hair_dataset.REFERENCE_SAMPLES, seed=index)
            if float(target[2].max()) < 1e-3:  # no hair in view: every method shows the bare background (PSNR inf)
                without_hair += 1
                continue
            reference = tonemap(_composite(target))
            candidates = {"stochastic 4 spp": _composite(render.unfiltered(4)),
                          "stochastic 16 spp": _composite(render.unfiltered(16))}
            for spp, hair_filter in sorted(filters.items()):
                candidates[f"ours {spp} spp"] = _composite(hair_filter.filter(render, passes=4)[0])
                if spp == 4:  # what the mirror passes add
                    for passes in (1, 2):
                        candidates[f"ours 4 spp, {passes} pass{'es' if passes > 1 else ''}"] = \
                            _composite(hair_filter.filter(render, passes=passes)[0])
            for name, hair_filter in candidate_filters.items():
                candidates[name] = _composite(hair_filter.filter(render, passes=4)[0])
            try:
                candidates["OIDN on 4 spp"] = _oidn(candidates["stochastic 4 spp"])
            except ImportError:
                pass
            for name, image in candidates.items():
                ldr = tonemap(image)
                scores.setdefault(name, {"psnr": [], "flip": []})
                scores[name]["psnr"].append(psnr(ldr, reference))
                scores[name]["flip"].append(flip(reference, ldr)[0])
            if len(scores["stochastic 4 spp"]["psnr"]) <= pictures and "ours 4 spp" in candidates:
                row = [tonemap(candidates["stochastic 4 spp"]), tonemap(candidates["ours 4 spp"])]
                row.append(tonemap(candidates["OIDN on 4 spp"]) if "OIDN on 4 spp" in candidates
                           else np.zeros_like(reference))
                rows_img.append(np.concatenate(row + [reference], axis=1))
        tables[split_name] = {name: {"psnr_db": round(float(np.mean(v["psnr"])), 2),
                                     "flip": round(float(np.mean(v["flip"])), 4), "pairs": len(v["psnr"]),
                                     "skipped_without_hair": without_hair,
                                     "flip_per_pair": [round(float(x), 5) for x in v["flip"]],
                                     "psnr_db_per_pair": [round(float(x), 3) for x in v["psnr"]]}
                              for name, v in scores.items()}
        tables[split_name]["paired"] = paired_differences(scores, "ours 4 spp",
                                                          ("stochastic 16 spp", "OIDN on 4 spp"))
        for name in candidate_filters:
            tables[split_name]["paired"].update(paired_differences(scores, name, ("stochastic 16 spp", "ours 4 spp")))
    if unseen_views:  # the trained styles' verdict on every view the networks never trained on
        validation_scores = split_scores["validation (trained styles)"]
        pooled = {method: {metric: validation_scores.get(method, {}).get(metric, []) + values[metric]
                           for metric in values}
                  for method, values in split_scores[UNSEEN_SPLIT].items()}
        tables[POOLED_SPLIT] = {"paired": paired_differences(pooled, "ours 4 spp", ("stochastic 16 spp",))}
        for name in candidate_filters:
            tables[POOLED_SPLIT]["paired"].update(paired_differences(pooled, name, ("stochastic 16 spp",)))
    if rows_img:
        from ..bake_directory.bake_report import save_png

        save_png(out_root / "hair_rows.png", np.concatenate(rows_img, axis=0), min_width=1)
    return tables


def paired_differences(scores: dict, ours: str, others) -> dict:
    """Per-pair differences of `ours` against each other method on the same views (FLIP: other - ours, PSNR:
    ours - other; positive means ours is better): mean, its standard error, and the pairs ours wins. Views
    differ far more than methods do, so this says whether a small difference of means is more than noise."""
    paired = {}
    for other in others:
        if ours not in scores or other not in scores:
            continue
        row = {}
        for metric, sign in (("flip", -1.0), ("psnr", 1.0)):
            gain = sign * (np.asarray(scores[ours][metric]) - np.asarray(scores[other][metric]))
            row[metric] = {"mean_gain": round(float(gain.mean()), 5),
                           "standard_error": round(float(gain.std(ddof=1) / np.sqrt(len(gain))), 5)
                           if len(gain) > 1 else None,
                           "wins": int((gain > 0).sum()), "pairs": len(gain)}
        paired[f"{ours} vs {other}"] = row
    return paired


def shipped_models() -> dict:
    names = {4: SHIPPED_MODELS[DEFAULT_NETWORK].name, 2: "hair_base@2spp.onnx", 1: "hair_base@1spp.onnx"}
    return {spp: MODELS_DIR / name for spp, name in names.items() if (MODELS_DIR / name).is_file()}


UNSEEN_VIEWS = 48  # the full bench's views past the dataset: with the 24 validation pairs, 72 trained-style views


def bench_hair(out_root: Path, quick: bool = False, candidates: dict | None = None,
               unseen_views: int | None = None) -> dict:
    """The default shipped network is "ours 4 spp"; the other shipped ones are scored as candidates beside it
    under their names. unseen_views: views of the trained styles past the dataset's (None: UNSEEN_VIEWS, 0 when
    quick)."""
    models = shipped_models()
    candidates = dict(candidates or {})
    for network, path in SHIPPED_MODELS.items():
        if network != DEFAULT_NETWORK and path.is_file():
            candidates.setdefault(network, path)
    result = {"inference": bench_inference(models, size=256 if quick else 1024,
                                           more_4spp_models=candidates.values())}
    for row in result["inference"]:
        print(f"hair inference {row['model']:<24} {row['size']}: onnxruntime CPU {row['onnxruntime_cpu_s']:.3f} s "
              f"(filter with 1 pass {row['filter_1_pass_s']:.3f} s, "
              f"4 mirror passes {row['filter_4_passes_s']:.3f} s); "
              f"our stochastic input 4 spp {row['stochastic_input_4spp_s']:.2f} s, 16 spp "
              f"{row['stochastic_input_16spp_s']:.2f} s ({row['fragments']} fragments); {row['shadow_maps']} shadow maps "
              f"cost {row['stochastic_input_4spp_s'] / row['stochastic_input_4spp_one_shadow_map_s']:.2f}x one")
    if models:
        if unseen_views is None:
            unseen_views = 0 if quick else UNSEEN_VIEWS
        result["quality"] = bench_quality(models, out_root, max_pairs=8 if quick else 40, extra_models=candidates,
                                          unseen_views=unseen_views)
        for split, table in result["quality"].items():
            print(f"\nhair quality, {split} (PSNR dB / FLIP, mean over pairs):")
            for name, row in table.items():
                if name == "paired":
                    continue
                skipped = f", {row['skipped_without_hair']} without hair in view skipped" \
                    if row.get("skipped_without_hair") else ""
                print(f"  {name:<20} {row['psnr_db']:6.2f}  {row['flip']:.4f}  ({row['pairs']} pairs{skipped})")
            for comparison, row in table.get("paired", {}).items():
                flip_row, psnr_row = row["flip"], row["psnr"]
                print(f"  {comparison}, per pair (positive: ours better): FLIP {flip_row['mean_gain']:+.4f} "
                      f"+- {flip_row['standard_error'] or 0:.4f} (wins {flip_row['wins']}/{flip_row['pairs']}), "
                      f"PSNR {psnr_row['mean_gain']:+.2f} +- {psnr_row['standard_error'] or 0:.2f} dB "
                      f"(wins {psnr_row['wins']}/{psnr_row['pairs']})")
    else:
        print(f"hair quality: no shipped model in {MODELS_DIR}")
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m headless.bench_hair", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("bench_out"))
    p.add_argument("--quick", action="store_true")
    p.add_argument("--candidate", action="append", default=[], metavar="NAME=PATH",
                   help="another 4-spp ONNX model to score beside the shipped one (repeatable)")
    p.add_argument("--unseen-views", type=int, metavar="N",
                   help=f"views of the trained styles past the dataset's to score too (default {UNSEEN_VIEWS}, "
                   "0 with --quick; about 15 s each)")
    ns = p.parse_args(argv)
    if ns.unseen_views is not None and not 0 <= ns.unseen_views <= 10_000:
        p.error("--unseen-views takes 0 to 10000")
    candidates = {}
    for item in ns.candidate:
        name, _, path = item.partition("=")
        if not name or not path or not Path(path).is_file():
            p.error(f"--candidate {item!r}: expected NAME=PATH of an existing ONNX file")
        try:
            candidate_filter(path)  # checked before the bench's minutes of rendering
        except (HairFilterError, ValueError) as error:
            p.error(f"--candidate {item!r}: {error}")
        candidates[name] = Path(path)
    ns.out.mkdir(parents=True, exist_ok=True)
    result = bench_hair(ns.out, ns.quick, candidates, ns.unseen_views)
    write_json_atomic(ns.out / "bench_hair.json", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
