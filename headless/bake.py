"""SG Lightfield bake from the command line: the same pipeline as the panel's button.

    python headless/bake.py (--blend scene.blend | --scene demo:NAME) --out DIR [options]
    blender -b scene.blend -P headless/bake.py -- --out DIR [options]

Exit code 0 on success; otherwise one line 'error: ...' on stderr and exit code 1 (bad input),
2 (bad arguments) or 130 (cancelled). Stages available so far: the plan and capture (render, train,
apply and evaluate follow).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file, by Blender's -P or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from ..bake_directory.bake_plan import STAGES as ALL_STAGES  # noqa: E402
from ..bake_directory.bake_plan import PRESETS, ROUGH_MATERIALS, BakeCancelled, BakeInputError, BakeSettings  # noqa: E402
from ..bake_directory.exr_io import ExrError  # noqa: E402

IMPLEMENTED_STAGES = ALL_STAGES  # the plan is always made; stages are added here as they land


def script_args(argv: list[str]) -> list[str]:
    """Arguments meant for this script: everything after '--' when Blender runs it with -P."""
    return argv[argv.index("--") + 1:] if "--" in argv else argv[1:]


SETTINGS_FILE_OPTIONS = ("preset", "texel-density", "lightfield-resolution", "samples", "lightmap-samples", "sg-count",
                         "uniform-sg-count", "training-budget", "training-epochs", "lobe-refit-steps",
                         "irradiance-detail", "rough-materials", "instance-copies", "device", "midpoints",
                         "reference-samples", "no-eevee-evaluation", "tile-megapixels", "external-images",
                         "lightmap-uv")


def _settings_arguments(parser: argparse.ArgumentParser, path: str) -> list[str]:
    """The options of a --settings JSON file as command-line words (so they are checked like typed ones)."""
    try:
        values = json.loads(Path(path).expanduser().read_text())
    except OSError as exc:
        parser.error(f"--settings {path}: {exc.strerror or exc}")
    except ValueError as exc:
        parser.error(f"--settings {path}: not JSON ({exc})")
    if not isinstance(values, dict):
        parser.error(f"--settings {path}: a JSON object of options is expected")
    words = []
    for key, value in values.items():
        if key not in SETTINGS_FILE_OPTIONS:
            parser.error(f"--settings {path}: '{key}' is not a quality option; use one of "
                         f"{', '.join(SETTINGS_FILE_OPTIONS)}")
        if isinstance(value, bool):
            if key in ("uniform-sg-count",):
                words.append(f"--{key}" if value else f"--no-{key}")
            elif value:
                words.append(f"--{key}")
        elif isinstance(value, (int, float, str)) and not (isinstance(value, float) and not math.isfinite(value)):
            words += [f"--{key}", str(value)]
        else:
            parser.error(f"--settings {path}: '{key}' must be a number, a word or true/false, not {value!r}")
    return words


def parse_args(args: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="headless/bake.py", description="Bake an SG light field.")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--blend", type=Path, help="the .blend to bake (never modified unless --in-place)")
    source.add_argument("--scene", help="an embedded demo scene, e.g. demo:spheres (--blend demo:NAME is the same)")
    p.add_argument("--out", type=Path, required=True, help="bake directory")
    p.add_argument("--preset", default="draft", choices=sorted(PRESETS), help="quality preset")
    p.add_argument("--stages", default=",".join(ALL_STAGES), help="comma-separated subset of " + ",".join(ALL_STAGES))
    p.add_argument("--texel-density", type=float)
    p.add_argument("--lightfield-resolution", type=int)
    p.add_argument("--samples", type=int)
    p.add_argument("--lightmap-samples", type=int, help="samples for the light fields of objects with only irradiance "
                   "lightmaps (0: --samples; Production: 64)")
    p.add_argument("--sg-count", type=int, help="the most SGs a glossy material gets (0 = 16); each gets the "
                   "fewest its roughness needs, up to this")
    p.add_argument("--uniform-sg-count", action=argparse.BooleanOptionalAction,
                   help="give every glossy material --sg-count SGs, whatever its roughness (Production does; "
                   "--no-uniform-sg-count: each the fewest its roughness needs)")
    p.add_argument("--training-budget", type=float, dest="training_budget_s",
                   help="seconds of training at most (Draft 30, Preview 120, Production 600)")
    p.add_argument("--training-epochs", type=int, help="train exactly this many epochs per fit, however long they "
                   "take, instead of the time budget: the same bake on a busy or an idle machine (a farm's nodes); "
                   "0: by the time budget")
    p.add_argument("--lobe-refit-steps", type=int, help="Adam steps refitting the SGs' axes, sharpness and "
                   "amplitudes through the glossy shading after training (0: off; every preset: 150)")
    p.add_argument("--irradiance-detail", type=int, help="diffuse light at this many times the texel density, baked "
                   "by Cycles at capture (1: the light fields' irradiance at the texels; Draft, Preview: 4; "
                   "Production: 2)")
    p.add_argument("--rough-materials", choices=ROUGH_MATERIALS, default="irradiance",
                   help="dielectrics of roughness >= 0.6: an irradiance lightmap from the same light field, or the "
                   "renderer's own lighting")
    p.add_argument("--instance-copies", action="store_true",
                   help="bake particle, vertex, face, nested and node-made instances as object copies that render in "
                   "their place until "
                   "the bake is removed (without it they keep the renderer's own lighting)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--tile", metavar="i/N", help="render only share i of N of the tiles (render farms); "
                   "the shares merge in the bake directory")
    p.add_argument("--midpoints", type=int, default=0, metavar="M",
                   help="also render M held-out light fields at texel midpoints (interpolation metric)")
    p.add_argument("--reference-samples", type=int, default=0, metavar="N",
                   help="the evaluate stage's path-traced reference spp (0: 8x --samples, at least 1024); the baked "
                   "scene renders at twice --samples, at least 128, never more than N")
    p.add_argument("--no-eevee-evaluation", action="store_true",
                   help="the evaluate stage compares with Cycles only, without EEVEE (a machine where EEVEE gets no "
                   "OpenGL context, such as a farm node without one, would wait for it)")
    p.add_argument("--tile-megapixels", type=float, default=4.0, help="render pixels per tile (memory)")
    p.add_argument("--in-place", action="store_true", help="save the baked scene over --blend instead of DIR/baked.blend")
    p.add_argument("--external-images", action="store_true",
                   help="keep the SG image as a file beside the bake (relative path) instead of packing it")
    p.add_argument("--lightmap-uv", default="", metavar="LAYER",
                   help="use this existing UV layer as the lightmap (validated) instead of generating SGLightmap")
    p.add_argument("--plan-only", action="store_true", help="print the bake plan and stop")
    p.add_argument("--json", action="store_true", help="one JSON object per line on stdout instead of text")
    p.add_argument("--settings", default="", metavar="FILE",
                   help="a JSON object of quality options by their long names, e.g. {\"samples\": 64, "
                        "\"texel-density\": 8} (farm templates pass one file to every task); the command line wins")
    ns = p.parse_args(args)
    if ns.settings:
        ns = p.parse_args(_settings_arguments(p, ns.settings) + list(args))
    stages = [s.strip() for s in ns.stages.split(",") if s.strip()]
    unknown = [s for s in stages if s not in ALL_STAGES]
    if unknown:
        p.error(f"unknown stage(s) {unknown}; choose from {', '.join(ALL_STAGES)}")
    ns.stages = stages
    return ns


class Reporter:
    """Progress and results: text for people, one JSON object per line for machines."""

    def __init__(self, as_json: bool, stream=None, eta_s=None):
        """eta_s: a function giving the seconds left (the bake job's, which knows its stages); without it the ETA
        is the current stage's rate applied to the rest of the bar."""
        self.as_json = as_json
        self.stream = stream or sys.stderr
        self.eta_s = eta_s
        self._stage_start = {}
        self.bar_open = False  # a progress line without its newline yet

    def end_bar(self):
        if self.bar_open:
            print(file=self.stream, flush=True)
            self.bar_open = False

    def progress(self, stage: str, fraction: float, message: str = ""):
        """A progress bar with ETA on stderr for people; a JSON line for machines."""
        now = time.monotonic()
        fraction = min(max(float(fraction), 0.0), 1.0)
        # The rate since this stage began: the bar's fraction covers the whole bake, and a stage that resumes
        # finished work (a saved checkpoint) jumps ahead at once.
        start, start_fraction = self._stage_start.setdefault(stage, (now, fraction))
        if not self.as_json and fraction < 1 and now - getattr(self, "_last_bar", 0.0) < 0.25:
            return  # a person reads a few updates a second, not every epoch
        self._last_bar = now
        done = fraction - start_fraction
        if self.eta_s is not None:
            eta = self.eta_s()
        else:
            eta = (now - start) * (1 - fraction) / done if done > 1e-6 and now > start else None
        if self.as_json:
            self.event("progress", stage=stage, fraction=round(fraction, 4), message=message,
                       eta_s=None if eta is None else round(eta, 1))
            return
        filled = int(round(24 * fraction))
        eta_text = "ETA --" if eta is None else f"ETA {eta:4.0f}s"
        line = f"{stage:>8} [{'#' * filled}{'.' * (24 - filled)}] {100 * fraction:5.1f}% {eta_text}  {message[:48]:<48}"
        if not self.stream.isatty():  # a log file: whole lines, one per tenth of the way
            step = int(10 * fraction)
            if step == getattr(self, "_last_step", -1) and fraction < 1:
                return
            self._last_step = step
            print(line.rstrip(), file=self.stream, flush=True)
            return
        end = "\n" if fraction >= 1 else ""
        self.bar_open = fraction < 1
        print("\r" + line, end=end, file=self.stream, flush=True)

    def event(self, kind: str, **fields):
        if self.as_json:
            print(json.dumps({"event": kind, "time": round(time.time(), 3), **fields}), flush=True)
        elif kind == "plan":
            print(f"plan: {fields['summary']}")
            for line in fields.get("decisions", []):
                print(f"  - {line}")
            for warning in fields.get("warnings", []):
                print(f"  ! {warning}")
        elif kind == "stage":
            print(f"{fields['stage']}: {fields['summary']} ({fields['seconds']:.2f} s)")
            for warning in fields.get("warnings", []):
                print(f"  ! {warning}")
        elif kind == "saved":
            print(fields["message"])
        elif kind == "done":
            print(f"done: {fields.get('message', '')}")


def load_scene(ns):
    import bpy

    demo = ns.scene or (str(ns.blend) if ns.blend and str(ns.blend).startswith("demo:") else "")
    if demo:
        from ..blender_addon.demo_scenes import build_demo_scene

        scene = build_demo_scene(demo)
    elif ns.blend:
        path = ns.blend.expanduser().resolve()
        if not path.is_file():
            raise BakeInputError(f"{ns.blend}: .blend file not found")
        try:
            bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
        except RuntimeError as exc:
            raise BakeInputError(f"{ns.blend}: cannot open ({str(exc).strip().splitlines()[-1]})") from exc
        scene = bpy.context.scene
    else:
        scene = bpy.context.scene  # blender -b scene.blend -P headless/bake.py
        if scene is None:
            raise BakeInputError("no scene: pass --blend FILE or --scene demo:NAME")
    if bpy.context.window is not None:
        bpy.context.window.scene = scene
    return scene


def _shaded_error_summary(lightfield_metrics: dict) -> str:
    """'; glossy error 0.08 (the CNN's SGs 0.17)': the mean over materials of the error of the node group's
    glossy against the exact reflection of the light field, after the refits and with the CNN's SGs, the materials
    whose refit was not kept, and with the lobe refit the same error between texels before and after it."""
    after = lightfield_metrics.get("shaded_error", {})
    before = lightfield_metrics.get("amplitude_refit", {}).get("shaded_error_before", {})
    if not after:
        return ""
    text = f"; glossy error {sum(after.values()) / len(after):.4f}"
    text += f" (the CNN's SGs {sum(before.values()) / len(before):.4f})" if before else ""
    refit = lightfield_metrics.get("amplitude_refit", {})
    reverted = refit.get("reverted_for", {})
    text += f"; refit not kept for {', '.join(reverted)} (it raised the error)" if reverted else ""
    reverted_between = refit.get("reverted_between_texels_for", {})
    text += (f"; refit not kept for {', '.join(reverted_between)} (it raised the error between texels)"
             if reverted_between else "")
    between = lightfield_metrics.get("interpolated_shaded_error", {})
    before = refit.get("lobes", {}).get("interpolated_error_before", {})
    if before and set(before) <= set(between):
        after = [between[name] for name in before]
        text += (f"; between texels where the lobes were refitted {sum(after) / len(after):.4f} (before "
                 f"{sum(before.values()) / len(before):.4f})")
        lobes_reverted = refit["lobes"]["reverted_for"]
        text += (f"; lobe refit not kept for {', '.join(lobes_reverted)} (it raised that error more than "
                 f"{refit['lobes'].get('tolerance', 1)}x)" if lobes_reverted else "")
    return text


def stage_summary(stage: str, result, plan) -> tuple[str, list]:
    """One line per finished stage for people (and the JSON 'stage' event)."""
    if stage == "capture":
        return (f"{result.texels} texels in a {result.atlas_width}x{result.atlas_height} atlas, "
                f"{result.coverage_percent:.1f}% covered, {result.pushed_out_texels} pushed out, "
                f"{result.buried_texels} buried"), result.warnings
    if stage == "render":
        rendered = ", ".join(f"{k} {v}" for k, v in result.tiles_rendered.items())
        skipped = sum(result.tiles_skipped.values())
        return (f"{result.texels} texels; tiles rendered: {rendered}"
                + (f"; {skipped} already finished" if skipped else "")
                + f"; {result.rays_per_second / 1e6:.2f} M rays/s"
                + (f" on {', '.join(result.devices)}" if result.devices else "")), result.warnings
    if stage == "train":
        metrics = result.metrics if hasattr(result, "metrics") else (result or {}).get("metrics", {})
        lf = metrics.get("lightfield", {})
        if "loss" not in lf:
            return ("no light-field SGs to train: no glossy material is baked (irradiance lightmaps only)"
                    if not plan.sg_objects else "the light field was not trained"), []
        return (f"{plan.max_sg_count} SGs; light field loss {lf['loss']:.4f}, RMSE {lf['rmse']:.4f}"
                + (f", midpoint RMSE {lf['midpoint']['rmse']:.4f}" if "midpoint" in lf else "")
                + _shaded_error_summary(lf)), []
    if stage == "evaluate":
        eevee = result.get("eevee") or {}
        eevee_text = (f"; EEVEE FLIP {eevee['flip']:.4f}, PSNR {eevee['psnr']:.2f} dB (first render "
                      f"{eevee['first_render_s']:.1f} s incl. shaders)" if "flip" in eevee else "")
        return (f"RMSE {result['rmse']:.4f}, PSNR {result['psnr']:.2f} dB, FLIP {result['flip']:.4f} over "
                f"{len(result['views'])} views against {result['reference_samples']}-spp references (their noise RMSE "
                f"{result['reference_noise_rmse']:.4f}), the baked scene at {result['test_samples']} spp"
                + eevee_text), ([f"EEVEE not evaluated: {eevee['error']}"] if "error" in eevee else []) + \
            [f"EEVEE could not compile a material's shader (it renders magenta): {error}"
             for error in eevee.get("shader_errors", ())]
    if stage == "apply":
        groups = ", ".join(f"'{name}' {nodes} nodes" for name, nodes in result["node_groups"].items())
        uniforms = result.get("eevee_uniform_bytes") or {}
        uniform_text = (f"; EEVEE uniforms up to {max(uniforms.values())} of {result['eevee_uniform_limit']} bytes"
                        if uniforms else "")
        return (f"{len(result['materials'])} materials baked (node groups: {groups}){uniform_text}",
                result.get("warnings", []))
    return "", []


def run(ns, reporter: Reporter) -> int:
    from ..blender_addon.pipeline import BakeJob

    settings = BakeSettings.from_preset(
        ns.preset, texel_density=ns.texel_density, lightfield_resolution=ns.lightfield_resolution,
        samples=ns.samples, lightmap_samples=ns.lightmap_samples, sg_count=ns.sg_count,
        uniform_sg_count=ns.uniform_sg_count,
        training_budget_s=ns.training_budget_s, training_epochs=ns.training_epochs,
        lobe_refit_steps=ns.lobe_refit_steps,
        rough_materials=ns.rough_materials, device=ns.device, irradiance_detail=ns.irradiance_detail,
        instance_copies=ns.instance_copies)
    out = ns.out.expanduser().resolve()
    if out.exists() and not out.is_dir():
        raise BakeInputError(f"{ns.out}: exists and is not a directory")
    if not 0 < ns.tile_megapixels <= 256:
        raise BakeInputError(f"--tile-megapixels {ns.tile_megapixels} is outside 0..256")
    if not 0 <= ns.midpoints <= 100_000:
        raise BakeInputError(f"--midpoints {ns.midpoints} is outside 0..100000")
    if ns.reference_samples != 0 and not 2 <= ns.reference_samples <= 65536:
        raise BakeInputError(f"--reference-samples {ns.reference_samples} is outside 2..65536 (0: automatic)")
    if ns.in_place and not ns.blend:
        raise BakeInputError("--in-place needs --blend FILE (the file to overwrite)")
    scene = load_scene(ns)
    job = BakeJob(scene, settings, out, stages=[] if ns.plan_only else ns.stages, share=ns.tile,
                  midpoints=ns.midpoints, tile_megapixels=ns.tile_megapixels, lightmap_uv=ns.lightmap_uv,
                  pack_images=not ns.external_images, reference_samples=ns.reference_samples,
                  eevee_evaluation=not ns.no_eevee_evaluation)
    reporter.eta_s = job.eta_s
    plan, data = job.plan, job.plan.to_dict()
    reporter.event("plan", summary=data["summary"], hash=data["hash"], texels=data["texels"],
                   decisions=plan.decisions(), warnings=plan.warnings, path=str(out / "plan.json"))
    if ns.plan_only:
        reporter.event("done", message=f"plan written to {out / 'plan.json'}", ok=True)
        return 0
    missing = [s for s in ns.stages if s not in IMPLEMENTED_STAGES]
    if missing:
        raise BakeInputError(f"stage(s) {', '.join(missing)} not available in this version yet; "
                             f"available: {', '.join(IMPLEMENTED_STAGES)} (or --plan-only)")
    reported = set()

    def progress(stage, fraction, message):
        """The bar shows the whole bake's progress (fraction over all stages) labelled with the current stage."""
        if stage:
            reporter.progress(stage, fraction, message)
        for finished in [s for s in job.results if s not in reported]:
            reported.add(finished)
            reporter.end_bar()
            summary, warnings = stage_summary(finished, job.results[finished], plan)
            reporter.event("stage", stage=finished, seconds=round(job.timings[finished], 3), summary=summary,
                           warnings=warnings)

    try:
        job.run(progress)
    except BaseException:
        job.cancel()  # leaves the scene as it was; finished stages stay in the bake directory
        raise
    progress("", 1.0, "")
    if "apply" in job.results:
        import bpy

        from ..blender_addon.render import quiet_stdout
        from ..blender_addon.scene_analysis import active_scene

        target = ns.blend.expanduser().resolve() if ns.in_place else out / "baked.blend"
        with active_scene(scene), quiet_stdout():
            bpy.ops.wm.save_as_mainfile(filepath=str(target), copy=not ns.in_place, compress=True)
        reporter.event("saved", path=str(target), message=f"baked scene saved to {target}")
    reporter.event("done", message=f"bake directory {out} (report: {out / 'report.html'})", ok=True)
    return 0


def main(argv=None) -> int:
    argv = sys.argv if argv is None else argv
    ns = parse_args(script_args(argv))
    reporter = Reporter(ns.json)
    try:
        return run(ns, reporter)
    except BakeInputError as exc:
        reporter.end_bar()
        if ns.json:
            reporter.event("error", message=str(exc))
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except (BakeCancelled, KeyboardInterrupt):
        reporter.end_bar()
        if ns.json:
            reporter.event("error", message="cancelled")
        print("error: cancelled; finished stages are kept and reused by the next run", file=sys.stderr)
        return 130
    except ExrError as exc:  # a bake directory file that is not what a stage expects
        reporter.end_bar()
        if ns.json:
            reporter.event("error", message=str(exc))
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # full disk, permissions: one line naming the file
        reporter.end_bar()
        if ns.json:
            reporter.event("error", message=str(exc))
        print(f"error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
