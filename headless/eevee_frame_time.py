"""EEVEE's frame time of baked scenes against the same scenes without the bake, and the SG evaluator's share.

    python headless/eevee_frame_time.py BAKE_DIR [BAKE_DIR ...] [--resolution 1920x1080] [--samples 1,65]
                                        [--repeats 3] [--best-lighting] [--report FILE]
    blender -b --python headless/eevee_frame_time.py -- BAKE_DIR [...]

For each bake directory it opens the baked .blend and renders the scene camera with EEVEE in each set-up:
  with_bake            the scene as baked
  evaluator_off        the bake's evaluator node groups muted: what the rest of the baked materials cost
  without_bake         the original materials back in the baked slots, the same EEVEE settings: the scene before
  without_bake_best    (--best-lighting) EEVEE alone as the evaluate stage sets it up: ray tracing, baked probes
A frame is one EEVEE render sample. The frame time is the slope of the render time against the sample count (the
median of --repeats renders at each of two counts), which leaves out each render's fixed set-up and read-back (None
where the frames are lost in the renders' noise); the first render of a set-up compiles its shaders and is reported
on its own. The evaluator's share is
(with_bake - evaluator_off) / with_bake. Absolute numbers need a GPU: on a machine without one EEVEE runs on
llvmpipe, the software rasteriser. Prints one line per set-up and writes --report (JSON).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

import bpy  # noqa: E402

from ..bake_directory.bake_plan import BakeInputError  # noqa: E402
from ..blender_addon.apply import BAKE_RECORD_KEY, is_bake_group  # noqa: E402

EEVEE_WORKER = Path(__file__).resolve().parent.parent / "blender_addon" / "eevee_worker.py"
SETUPS = ("with_bake", "evaluator_off", "without_bake")


def _worker():
    """blender_addon/eevee_worker.py as a module: its scene set-ups (originals back, best lighting)."""
    spec = importlib.util.spec_from_file_location("sglf_eevee_worker", EEVEE_WORKER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def open_bake(bake_dir: Path):
    """Open the bake's baked.blend and return its baked scene; images that ship inside Blender (the demo scenes'
    HDRIs) are found again where this Blender keeps them."""
    blend = bake_dir / "baked.blend"
    if not blend.is_file():
        raise BakeInputError(f"{bake_dir}: no baked.blend (bake with the apply stage first)")
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    studio = Path(bpy.utils.system_resource("DATAFILES")) / "studiolights" / "world"
    for image in bpy.data.images:
        if image.source == "FILE" and not image.packed_file and image.filepath:
            path = Path(bpy.path.abspath(image.filepath))
            if not path.is_file() and (studio / path.name).is_file():
                image.filepath = str(studio / path.name)
    scenes = [s for s in [bpy.context.scene, *bpy.data.scenes] if s is not None and s.get(BAKE_RECORD_KEY)]
    if not scenes:
        raise BakeInputError(f"{blend}: no scene holds a bake")
    return scenes[0]  # the file's own scene first


def evaluator_nodes() -> list[tuple[str, object]]:
    """(owner, group node) for every group node, in a material or a user's node group, that runs one of the bake's
    evaluator groups (not the groups those run inside); owner is the material's or the node group's name."""
    owners = [(m.name, m.node_tree) for m in bpy.data.materials if m.node_tree is not None] + \
        [(g.name, g) for g in bpy.data.node_groups if not is_bake_group(g)]
    return [(name, node) for name, tree in owners for node in tree.nodes
            if node.bl_idname == "ShaderNodeGroup" and is_bake_group(node.node_tree)]


def render_seconds(scene, samples: int) -> float:
    scene.eevee.taa_render_samples = samples
    start = time.perf_counter()
    bpy.ops.render.render(write_still=False, scene=scene.name)
    return time.perf_counter() - start


def measure(scene, samples: tuple[int, int], repeats: int) -> dict:
    """First render (shaders compiled) and the frame time as the slope of render time over samples."""
    first = render_seconds(scene, samples[0])
    times = {n: [] for n in samples}
    for _ in range(repeats):
        for n in samples:
            times[n].append(render_seconds(scene, n))
    low, high = (statistics.median(times[n]) for n in samples)
    # None where more samples did not take longer: the frames are lost in the renders' noise (use more samples)
    frame_ms = round((high - low) / (samples[1] - samples[0]) * 1000.0, 4) if high > low else None
    return {"first_render_s": round(first, 4), "render_s": {str(n): [round(t, 4) for t in times[n]] for n in samples},
            "frame_ms": frame_ms}


def frame_times(bake_dir: Path, resolution: tuple[int, int], samples: tuple[int, int], repeats: int,
                best_lighting: bool = False) -> dict:
    worker = _worker()
    result = {"bake": str(bake_dir), "resolution": list(resolution), "samples": list(samples), "repeats": repeats}
    for setup in SETUPS + (("without_bake_best",) if best_lighting else ()):
        scene = open_bake(bake_dir)  # every set-up from the file as saved
        render = scene.render
        render.engine = worker.eevee_engine()
        render.resolution_x, render.resolution_y, render.resolution_percentage = *resolution, 100
        render.use_compositing = render.use_sequencer = False
        muted = {}
        if setup == "evaluator_off":
            for owner, node in evaluator_nodes():
                node.mute, muted[owner] = True, muted.get(owner, 0) + 1
        if setup.startswith("without_bake"):
            worker.restore_originals(scene)
        if setup == "without_bake_best":
            worker.best_lighting(scene)
        row = measure(scene, samples, repeats)
        row["evaluator_nodes_muted"] = muted
        result[setup] = row
        print(f"{bake_dir.name:>12} {setup:<18} first render {row['first_render_s']:7.2f} s  frame "
              + (f"{row['frame_ms']:8.3f} ms" if row["frame_ms"] is not None else "lost in noise"), flush=True)
    with_bake, off = result["with_bake"]["frame_ms"], result["evaluator_off"]["frame_ms"]
    result["evaluator_share"] = round((with_bake - off) / with_bake, 4) if with_bake and off is not None else None
    try:
        import gpu

        result["gpu"] = f"{gpu.platform.vendor_get()} {gpu.platform.renderer_get()}".strip()
    except Exception as error:  # noqa: BLE001 - named in the report, never a reason to lose the timings
        result["gpu"] = f"unknown ({error})"
    return result


def _pair(text: str, sep: str, name: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.split(sep))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name} must be two integers joined by '{sep}', not {text!r}") from None
    if a < 1 or b < 1:
        raise argparse.ArgumentTypeError(f"{name} must be positive, not {text!r}")
    return a, b


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("bakes", nargs="+", type=Path, help="bake directories holding baked.blend")
    p.add_argument("--resolution", type=lambda t: _pair(t, "x", "--resolution"), default=(1920, 1080))
    p.add_argument("--samples", type=lambda t: _pair(t, ",", "--samples"), default=(1, 65),
                   help="two EEVEE sample counts; the frame time is the slope between them")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--best-lighting", action="store_true", help="also EEVEE alone with ray tracing and probes")
    p.add_argument("--report", type=Path)
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    ns = p.parse_args(argv)
    if ns.samples[1] <= ns.samples[0] or ns.repeats < 1:
        p.error("--samples needs a larger second count and --repeats at least 1")
    rows = []
    for bake in ns.bakes:
        try:
            rows.append(frame_times(bake, ns.resolution, ns.samples, ns.repeats, ns.best_lighting))
        except BakeInputError as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
        if ns.report:  # after every scene: a run cut short keeps what it measured
            tmp = ns.report.with_suffix(".tmp")
            tmp.write_text(json.dumps(rows, indent=1, allow_nan=False))
            os.replace(tmp, ns.report)
    def ms(value):
        return f"{value:.3f} ms" if value is not None else "n/a"

    for row in rows:
        share = row["evaluator_share"]
        print(f"{Path(row['bake']).name}: with the bake {ms(row['with_bake']['frame_ms'])}, without "
              f"{ms(row['without_bake']['frame_ms'])}, evaluator share "
              + (f"{share:.0%}" if share is not None and math.isfinite(share) else "n/a") + f" ({row['gpu']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
