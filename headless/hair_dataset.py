"""Make hair-filter training pairs: stochastic input (our renderer) and Cycles reference for random views.

    python headless/hair_dataset.py --out hair_data [--pairs 240] [--held-out 30] [--size 128]

Styles straight, wavy and curly take turns in DIR/train (every tenth pair is validation); the clumped
style is never trained on and goes to DIR/held_out. Each view is drawn from a generator seeded by
(seed, index, split) alone, so `dataset_view` gives the bench the same views without the files. The defaults
make the shipped models' dataset. Resumable: pairs already complete are skipped, so an interrupted run
continues where it stopped. Exit 0 on success, 1 with one 'error:' line otherwise.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from .bake import Reporter, script_args  # noqa: E402
from ..bake_directory.bake_plan import BakeInputError  # noqa: E402

# The shipped models' dataset (`make hair-model`); the bench scores the same views.
PAIRS, HELD_OUT, SIZE, REFERENCE_SAMPLES, DENSITY, SEED = 240, 30, 128, 192, 60000.0, 0


def dataset_jobs(pairs: int, held_out: int) -> list[tuple[str, int, str]]:
    """(split directory, index, style) of every pair: the training styles in turn, then the held-out style."""
    from ..hair import blender_scene as hair

    return [("train", i, hair.TRAIN_STYLES[i % len(hair.TRAIN_STYLES)]) for i in range(pairs)] + \
        [("held_out", i, hair.HELD_OUT_STYLE) for i in range(held_out)]


def dataset_view(strands, directory_name: str, index: int, seed: int = SEED, size: int = SIZE, samples=None):
    """The pair's view: (camera, light, stochastic render, draws), from (seed, index, split) alone."""
    import numpy as np

    from ..hair import pairs as hair_pairs
    from ..hair import raster as hair_raster

    rng = np.random.default_rng([seed, index, 0 if directory_name == "train" else 1])
    return hair_raster.random_view(rng, strands, size, samples or hair_pairs.PAIR_SAMPLES)


def parse_args(args):
    p = argparse.ArgumentParser(prog="headless/hair_dataset.py", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--pairs", type=int, default=PAIRS, help="training-style pairs (10%% become validation)")
    p.add_argument("--held-out", type=int, default=HELD_OUT, help="pairs of the held-out style")
    p.add_argument("--size", type=int, default=SIZE, help="image side in pixels")
    p.add_argument("--reference-samples", type=int, default=REFERENCE_SAMPLES, help="Cycles samples per pixel")
    p.add_argument("--density", type=float, default=DENSITY, help="groom density (strands per m^2 of scalp)")
    p.add_argument("--seed", type=int, default=SEED)
    ns = p.parse_args(args)
    if ns.size < 16 or ns.size > 4096 or ns.pairs < 0 or ns.held_out < 0 or ns.reference_samples < 1:
        p.error("--size must be 16..4096, --pairs/--held-out >= 0, --reference-samples >= 1")
    return ns


def make_pairs(ns, progress) -> dict:
    import numpy as np

    from ..hair import blender_scene as hair
    from ..blender_addon.scene_analysis import active_scene
    from ..hair import pairs as hair_pairs

    jobs = [(ns.out / name, i, style) for name, i, style in dataset_jobs(ns.pairs, ns.held_out)]
    todo = [job for job in jobs if not hair_pairs.is_complete(job[0], job[1])]
    grooms, made, start = {}, 0, time.monotonic()
    for number, (directory, index, style) in enumerate(todo):
        if style not in grooms:
            scene, objects = hair.dataset_groom(style, ns.density)
            with active_scene(scene):
                import bpy
                depsgraph = bpy.context.evaluated_depsgraph_get()
                grooms[style] = (objects, hair.strands_from_objects(objects, depsgraph))
        objects, strands = grooms[style]
        t0 = time.perf_counter()
        camera, light, stochastic, draws = dataset_view(strands, directory.name, index, ns.seed, ns.size)
        t1 = time.perf_counter()
        target = hair.render_reference(objects, camera, light, samples=ns.reference_samples,
                                       seed=index)
        t2 = time.perf_counter()
        hair_pairs.write_pair(directory, index, stochastic.features, target, {
            "style": style, "size": ns.size, "density": ns.density, "light": light.tolist(),
            "focal_px": camera.focal_px, "view_draws": draws,
            "world_to_camera": np.asarray(camera.world_to_camera).tolist(),
            "reference_samples": ns.reference_samples, "stochastic_s": round(t1 - t0, 3),
            "reference_s": round(t2 - t1, 3), "mean_alpha": round(float(target[2].mean()), 4)})
        made += 1
        progress((number + 1) / len(todo), f"{directory.name} {index} ({style})")
    return {"made": made, "skipped": len(jobs) - len(todo), "seconds": round(time.monotonic() - start, 1)}


def main(argv=None) -> int:
    try:
        ns = parse_args(script_args(sys.argv if argv is None else ["", *argv]))
    except SystemExit as exit_:
        return int(exit_.code or 0)
    reporter = Reporter(as_json=False)
    try:
        result = make_pairs(ns, lambda f, m: reporter.progress("pairs", f, m))
    except (BakeInputError, OSError) as error:
        reporter.end_bar()
        print(f"error: {error}", file=sys.stderr)
        return 1
    reporter.end_bar()
    print(f"hair pairs: {result['made']} made, {result['skipped']} already there, {result['seconds']} s -> {ns.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
