"""Benchmarks: `make bench` / `python -m headless.bench [--quick]`.

Speed targets live here, not in tests. Each section prints its measurements side by side and
writes them to bench_out/bench.json.
  capture   capture stage of `room` (and the other demos) at each preset's texel density; target < 10 s
            for `room` at the default (Draft) density.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shaders.bake_plan import PRESETS, BakeSettings, write_json_atomic  # noqa: E402

CAPTURE_TARGET_S = 10.0


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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m headless.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="room only, Draft and Preview")
    p.add_argument("--out", type=Path, default=Path("bench_out"))
    ns = p.parse_args(argv)
    scenes = ["room"] if ns.quick else ["room", "spheres", "courtyard"]
    presets = ["draft", "preview"] if ns.quick else list(PRESETS)
    results = {"capture": bench_capture(scenes, presets, ns.out)}
    write_json_atomic(ns.out / "bench.json", results)
    print(f"\nwritten: {ns.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
