"""Filter Hair from the command line: the same function as the panel's button.

    python headless/filter_hair.py (--blend scene.blend | --scene demo:hair) --out DIR
           [--network base|large | --model M.onnx] [--width W --height H] [--background-samples N]
    blender -b scene.blend -P headless/filter_hair.py -- --out DIR

Writes DIR/filtered.exr, filtered.png, unfiltered.png (plain stochastic transparency, for comparison) and
hair_filter.json. Exit 0 on success; 1 with one 'error: ...' line for bad input (no hair, no camera, a
missing or corrupt model); 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from .bake import Reporter, script_args  # noqa: E402
from ..bake_directory.bake_plan import BakeInputError  # noqa: E402
from ..hair.filtering import DEFAULT_NETWORK, DEFAULT_PASSES, MIRRORS, SHIPPED_MODELS, HairFilterError  # noqa: E402


def parse_args(args):
    p = argparse.ArgumentParser(prog="headless/filter_hair.py", description="Filter stochastic hair with the U-Net.")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--blend", type=Path, help="the .blend (never modified)")
    source.add_argument("--scene", help="an embedded demo scene, e.g. demo:hair")
    p.add_argument("--out", type=Path, required=True)
    model = p.add_mutually_exclusive_group()
    model.add_argument("--model", type=Path, help="ONNX hair filter (default: the shipped network)")
    model.add_argument("--network", choices=sorted(SHIPPED_MODELS), default=DEFAULT_NETWORK,
                       help=f"shipped network (default {DEFAULT_NETWORK}): large (1.5 s at 1024^2 on 2 cores with 4 "
                       "passes, the lowest error) or base (about half the time, higher error)")
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--background-samples", type=int, default=16)
    p.add_argument("--passes", type=int, choices=sorted(MIRRORS), default=DEFAULT_PASSES,
                   help="network passes over mirror images of the input, averaged (4: least error, 4x the time)")
    ns = p.parse_args(args)
    for name in ("width", "height", "background_samples"):
        value = getattr(ns, name)
        if value is not None and not 1 <= value <= 16384:
            p.error(f"--{name.replace('_', '-')} must be between 1 and 16384")
    return ns


def main(argv=None) -> int:
    try:
        ns = parse_args(script_args(sys.argv if argv is None else ["", *argv]))
    except SystemExit as exit_:
        return int(exit_.code or 0)
    from .bake import load_scene

    from ..hair import blender_scene as hair

    reporter = Reporter(as_json=False)
    try:
        scene = load_scene(ns)
        result = hair.filter_hair(scene, ns.out, model_path=ns.model, width=ns.width, height=ns.height,
                                  background_samples=ns.background_samples, passes=ns.passes, network=ns.network,
                                  progress=lambda f, m: reporter.progress("hair", f, m))
    except (BakeInputError, HairFilterError, OSError) as error:
        reporter.end_bar()
        print(f"error: {error}", file=sys.stderr)
        return 1
    reporter.end_bar()
    for warning in result.warnings:
        print(f"  ! {warning}")
    seconds = ", ".join(f"{k} {v:.2f} s" for k, v in result.seconds.items())
    print(f"filtered hair: {result.paths['filtered_png']} ({seconds})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
