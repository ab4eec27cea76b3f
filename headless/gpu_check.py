"""The training's speed on a CUDA GPU against this CPU, in one run (`make gpu-check`).

    python -m headless.gpu_check --export DIR --out FILE.npz     # here: a rendered bake's light fields, numpy only
    python headless/gpu_check.py --data FILE.npz [--seconds 30]  # anywhere with torch (CUDA or not) and numpy

The device machines have torch with CUDA but no Blender and no OpenEXR (docs/design-additions.md §17): the first
command turns a bake directory's rendered light fields (a `room` Draft bake: `make gpu-check` makes one) into one
.npz of plain arrays (loaded without pickle), which a run carries there. The second measures, from one seed, the CPU
at --cpu-threads threads (2: the CI machine's cores) and, when torch sees it, CUDA:
  training    the light-field CNN on the bake's data for --seconds (plateau stop off): on the CPU with its 256-texel
              steps, on CUDA in each CUDA_VARIANTS set-up (the last is the bake's default): epochs and steps per
              second, final loss, the ratio to the CPU's epochs per second and the seconds to reach its final loss;
  plateau     the default plateau rule on the fastest device: when it stops and its loss against the budget's run;
  production  epochs of the same CNN on a Production-sized light field (R = 32, --production-texels texels: the
              bake's light fields upsampled and repeated; --production-cpu-texels of them on the CPU): texels/s;
  refits      the lobe and amplitude refits on --refit-texels texels as the train stage runs them on each device.
It prints a table and writes --report (JSON). A device it cannot use, or a CUDA measurement that fails, is named
with the reason, never skipped in silence. Targets (issue: the GPU path): CUDA at least 20x the 2-core CPU's
epochs per second, refits faster than on the CPU, no slower CPU.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ in (None, "", "headless"):  # started as a file or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

import numpy as np  # noqa: E402

DATA_KEYS = ("images", "normals", "texels", "roughness", "lobe_counts")


def export_lightfields(bake_dir: Path, out: Path) -> dict:
    """The light fields of a rendered bake directory's SG texels, their normals, atlas texels, roughness and lobe
    counts, as one .npz (float16 images). Needs OpenEXR (this project's venv)."""
    from ..bake_directory.bake_plan import BakePlan
    from ..bake_directory.lightfield_tiles import read_images
    from ..bake_directory.texel_maps import channels, read_texel_maps, texels_of_objects
    from ..training.train_stage import texel_lobe_counts, texel_roughness

    plan = BakePlan.from_dict(json.loads((bake_dir / "plan.json").read_text()))
    atlas, info = read_texel_maps(bake_dir, plan.stage_hash("capture"))
    texels, images = read_images(bake_dir / "lightfield", plan.stage_hash("render"))
    mine = texels_of_objects(atlas, info, texels, plan.sg_objects)
    texels, images = texels[mine], images[mine]
    arrays = {"images": images.astype(np.float16), "normals": channels(atlas, "Ng.X", 3)[texels[:, 0], texels[:, 1]],
              "texels": texels, "roughness": texel_roughness(atlas, info, texels, plan),
              "lobe_counts": texel_lobe_counts(atlas, info, texels, plan, plan.max_sg_count or 16)}
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    return {"texels": len(texels), "resolution": int(images.shape[1]), "file": str(out),
            "megabytes": round(out.stat().st_size / 1e6, 1)}


def load_data(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as data:
        missing = [k for k in DATA_KEYS if k not in data]
        if missing:
            raise SystemExit(f"error: {path}: not a gpu-check export (missing {', '.join(missing)})")
        return {k: data[k] for k in DATA_KEYS}


def devices() -> tuple[list[str], dict]:
    """The devices to measure and, for CUDA where it cannot be used, the reason."""
    import torch

    if torch.cuda.is_available():
        return ["cpu", "cuda"], {"cuda": torch.cuda.get_device_name(0)}
    return ["cpu"], {"cuda": "not measured: torch sees no CUDA device here"}


# The training set-ups measured on CUDA, each against the CPU's run (TrainConfig fields; the last is the default).
CUDA_VARIANTS = {
    "steps of 256 texels, eager": {"cuda_batch_pixels": 0, "cuda_graphs": False},
    "whole-atlas steps, eager": {"cuda_graphs": False},
    "whole-atlas steps, rate 3e-3, CUDA graph": {"cuda_batch_learning_rate": 3e-3},
    "whole-atlas steps, rate 1e-2, CUDA graph": {"cuda_batch_learning_rate": 1e-2},
    "whole-atlas steps, CUDA graph (default)": {},
}


def _sync(device: str):
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def train_for(data: dict, device: str, seconds: float, seed: int = 0, epochs: int | None = None,
              plateau: bool = False, **config) -> dict:
    """The CNN on `data` for `seconds` of training, or exactly `epochs` epochs (plateau stop off unless `plateau`;
    `config`: more TrainConfig fields): epochs, rate, the loss curve."""
    from ..training.sg_fit import LightFieldData, TrainConfig, Trainer

    lobes = data["lobe_counts"]
    light = LightFieldData.from_numpy(data["images"].astype(np.float32), data["normals"], device=device,
                                      lobe_counts=None if lobes.min() == lobes.max() else lobes)
    if not plateau:
        config["plateau_epochs"] = 10**9
    trainer = Trainer(light, TrainConfig(sg_count=int(lobes.max()), time_budget_s=seconds, device=device, seed=seed,
                                         **config))
    _sync(device)
    start = time.perf_counter()
    state = trainer.train(save_checkpoint=False, epochs=epochs)
    _sync(device)
    wall = time.perf_counter() - start
    steps = state.epoch * math.ceil(len(light.images) / trainer.batch_texels)
    return {"device": device, "texels": len(light.images), "batch_texels": trainer.batch_texels,
            "epochs": state.epoch, "steps": steps, "seconds": round(wall, 2),
            "epochs_per_s": round(state.epoch / wall, 3), "steps_per_s": round(steps / wall, 1),
            "final_loss": state.losses[-1] if state.losses else None, "stopped_because": state.stopped_because,
            "cuda_graph": trainer._graph is not None, "graph_error": trainer.graph_error,
            "curve": [[round(s, 3), float(v)] for s, v in zip(state.seconds, state.losses)]}


def seconds_to_loss(curve: list, loss: float) -> float | None:
    """The first time on `curve` ([seconds, loss] per epoch) at or below `loss`; None if never."""
    return next((s for s, v in curve if v <= loss), None)


def production_sized(data: dict, texels: int, resolution: int = 32) -> dict:
    """A light field of Production's size: the bake's images upsampled to `resolution` and repeated to `texels`."""
    images = data["images"]
    factor = max(1, resolution // images.shape[1])
    up = np.repeat(np.repeat(images, factor, axis=1), factor, axis=2)
    pick = np.arange(texels) % len(up)
    return {"images": up[pick], "normals": data["normals"][pick], "texels": data["texels"][pick],
            "roughness": data["roughness"][pick], "lobe_counts": data["lobe_counts"][pick]}


def refit_timings(data: dict, device: str, texels: int, steps: int) -> dict:
    """Seconds of the two refits on `device` with the code the train stage runs there: the lobe refit (torch; its
    target numpy on the CPU, torch on CUDA) and the amplitude refit (numpy on the CPU, its torch twin on CUDA), each
    computing the target itself (the train stage computes it once for both)."""
    from ..training.glossy_lobe_fit import lobe_refit_steps
    from ..training.glossy_refit_torch import amplitude_refit_steps
    from ..training.sg_fit import LightFieldData, TrainConfig, Trainer

    pick = np.arange(min(texels, len(data["images"])))
    images = data["images"][pick].astype(np.float32)
    normals, roughness, lobes = data["normals"][pick], data["roughness"][pick], data["lobe_counts"][pick]
    count = int(lobes.max())
    trainer = Trainer(LightFieldData.from_numpy(images, normals), TrainConfig(sg_count=count, time_budget_s=1.0))
    axis, sharpness, amplitude = trainer.parameters_numpy()  # an untrained CNN's SGs: the refits' cost is the same
    row = {"device": device, "texels": len(pick), "lobe_refit_steps": steps}
    for name, run in (("lobe_refit_s", lambda: lobe_refit_steps(images, normals, data["texels"][pick], axis,
                                                                 sharpness, amplitude, roughness, count, steps,
                                                                 device=device)),
                      ("amplitude_refit_s", lambda: amplitude_refit_steps(images, normals, axis, sharpness, amplitude,
                                                                          roughness, lobes, device=device))):
        _sync(device)
        start = time.perf_counter()
        for _ in run():  # a generator of the fraction done
            pass
        _sync(device)
        row[name] = round(time.perf_counter() - start, 2)
    return row


def run_check(data: dict, seconds: float, production_texels: int, refit_texels: int, refit_steps: int,
              cpu_threads: int = 2, production_cpu_texels: int = 2048, plateau: bool = True) -> dict:
    import torch

    if cpu_threads:
        torch.set_num_threads(cpu_threads)  # the CPU rows as on a 2-core machine, whatever this one has
    measured, names = devices()
    report = {"torch": torch.__version__, "devices": {**names, "cpu": f"{torch.get_num_threads()} threads"},
              "training": [], "production": [], "refits": []}
    cpu = train_for(data, "cpu", seconds)
    cpu["variant"] = "steps of 256 texels (the CPU's)"
    report["training"].append(cpu)
    report["failed"] = []  # a CUDA measurement that raised: its error, and the others still run

    def attempt(what, measure):
        try:
            return measure()
        except (RuntimeError, MemoryError) as error:  # torch's CUDA errors are RuntimeErrors
            report["failed"].append(f"{what}: {type(error).__name__}: {error}")
            return None

    if "cuda" in measured:
        for name, config in CUDA_VARIANTS.items():
            row = attempt(f"training, {name}", lambda config=config: train_for(data, "cuda", seconds, **config))
            if row:
                row["variant"] = name
                row["epochs_per_s_over_cpu"] = round(row["epochs_per_s"] / max(cpu["epochs_per_s"], 1e-9), 2)
                row["seconds_to_cpu_final_loss"] = seconds_to_loss(row["curve"], cpu["final_loss"])
                report["training"].append(row)
    if plateau:  # the default plateau rule, on the fastest device, against the whole budget's run there
        device = measured[-1]
        row = attempt("plateau", lambda: train_for(data, device, seconds, plateau=True))
        budget_row = report["training"][-1]
        if row and budget_row["device"] == device:
            row["variant"] = "plateau stop on (the bake's default)"
            row["loss_over_budget_run"] = round(row["final_loss"] / max(budget_row["final_loss"], 1e-12), 4)
            report["plateau"] = {k: v for k, v in row.items() if k != "curve"}
    if production_texels:
        for device in measured:
            texels = min(production_texels, production_cpu_texels) if device == "cpu" else production_texels
            row = attempt(f"production, {device}", lambda device=device, texels=texels: train_for(
                production_sized(data, texels), device, math.inf, epochs=1 if device == "cpu" else 3))
            if row:
                row["texels_per_s"] = round(row["epochs"] * row["texels"] / max(row["seconds"], 1e-9), 1)
                report["production"].append({k: v for k, v in row.items() if k != "curve"})
        if len(report["production"]) > 1:
            report["production"][-1]["texels_per_s_over_cpu"] = round(
                report["production"][-1]["texels_per_s"] / max(report["production"][0]["texels_per_s"], 1e-9), 2)
    if refit_texels and refit_steps:
        for device in measured:
            row = attempt(f"refits, {device}", lambda device=device: refit_timings(data, device, refit_texels,
                                                                                   refit_steps))
            if row:
                report["refits"].append(row)
    return report


def print_report(report: dict):
    print(f"torch {report['torch']}; devices: " + "; ".join(f"{k}: {v}" for k, v in report["devices"].items()))
    for row in report["training"]:
        extra = ""
        if "epochs_per_s_over_cpu" in row:
            reach = row["seconds_to_cpu_final_loss"]
            extra = (f", {row['epochs_per_s_over_cpu']}x the CPU's epochs/s (target >= 20), the CPU's final loss "
                     + (f"after {reach} s" if reach is not None else "never reached"))
            if row["graph_error"]:
                extra += f" [{row['graph_error']}]"
        print(f"training   {row['device']:<5} {row['variant']}: {row['texels']} texels, {row['batch_texels']} a step: "
              f"{row['epochs']} epochs in {row['seconds']} s ({row['epochs_per_s']} epochs/s, {row['steps_per_s']} "
              f"steps/s), final loss {row['final_loss']:.5f}{extra}")
    if "plateau" in report:
        row = report["plateau"]
        print(f"plateau    {row['device']:<5} stopped by {row['stopped_because']} after {row['seconds']} s, "
              f"{row['epochs']} epochs: loss {row['final_loss']:.5f} = {row['loss_over_budget_run']}x the budget run's")
    for row in report["production"]:
        ratio = f", {row['texels_per_s_over_cpu']}x the CPU" if "texels_per_s_over_cpu" in row else ""
        print(f"production {row['device']:<5} {row['texels']} texels at R = 32, {row['batch_texels']} a step: "
              f"{row['epochs']} epochs in {row['seconds']} s ({row['texels_per_s']} texels/s{ratio})")
    for row in report["refits"]:
        print(f"refits     {row['device']:<5} {row['texels']} texels: lobe refit {row['lobe_refit_steps']} steps "
              f"{row['lobe_refit_s']} s, amplitude refit {row['amplitude_refit_s']} s")
    for failure in report["failed"]:
        print(f"FAILED     {failure}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="headless/gpu_check.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--export", type=Path, metavar="BAKE_DIR", help="write the light fields of this rendered bake "
                   "directory to --out (needs OpenEXR) and stop")
    p.add_argument("--out", type=Path, help="the .npz --export writes")
    p.add_argument("--data", type=Path, help="a .npz made by --export")
    p.add_argument("--seconds", type=float, default=30.0, help="training seconds per device (Draft's budget: 30)")
    p.add_argument("--production-texels", type=int, default=40379, help="texels of the Production-sized light "
                   "field (room at Production: 40379; 0: skip)")
    p.add_argument("--refit-texels", type=int, default=512)
    p.add_argument("--refit-steps", type=int, default=150, help="lobe-refit steps (every preset: 150)")
    p.add_argument("--production-cpu-texels", type=int, default=2048, help="texels of the CPU's Production-sized "
                   "epoch (its texels per second; a whole one takes minutes)")
    p.add_argument("--cpu-threads", type=int, default=2, help="torch threads of the CPU rows (0: torch's own)")
    p.add_argument("--no-plateau", action="store_true", help="skip the plateau-stop run")
    p.add_argument("--report", type=Path, help="write the measurements as JSON here")
    ns = p.parse_args(argv)
    if ns.export:
        if not ns.out:
            p.error("--export needs --out FILE.npz")
        print(json.dumps(export_lightfields(ns.export, ns.out)))
        return 0
    if not ns.data:
        p.error("give --data FILE.npz (made by --export)")
    if not ns.data.is_file():
        p.error(f"--data {ns.data}: no such file")
    if not (math.isfinite(ns.seconds) and ns.seconds > 0):
        p.error("--seconds must be a positive number")
    report = run_check(load_data(ns.data), ns.seconds, ns.production_texels, ns.refit_texels, ns.refit_steps,
                       ns.cpu_threads, ns.production_cpu_texels, not ns.no_plateau)
    print_report(report)
    if ns.report:
        from ..bake_directory.bake_plan import write_json_atomic

        write_json_atomic(ns.report, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
