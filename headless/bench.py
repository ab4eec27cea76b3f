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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m headless.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="room only, Draft and Preview")
    p.add_argument("--out", type=Path, default=Path("bench_out"))
    ns = p.parse_args(argv)
    scenes = ["room"] if ns.quick else ["room", "spheres", "courtyard"]
    presets = ["draft", "preview"] if ns.quick else list(PRESETS)
    results = {"capture": bench_capture(scenes, presets, ns.out), "render": bench_render(ns.out)}
    write_json_atomic(ns.out / "bench.json", results)
    print(f"\nwritten: {ns.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
