"""The training's speed on a CUDA GPU against this CPU, in one run (`make gpu-check`).

    python -m headless.gpu_check --export DIR --out FILE.npz     # here: a rendered bake's light fields, numpy only
    python headless/gpu_check.py --data FILE.npz [--seconds 30]  # anywhere with torch (CUDA or not) and numpy

The device machines have torch with CUDA but no Blender and no OpenEXR (docs/design-additions.md §17): the first
command turns a bake directory's rendered light fields (a `room` Draft bake: `make gpu-check` makes one) into one
.npz of plain arrays (loaded without pickle), which a run carries there. The second measures, on the CPU and on
CUDA when torch sees it, each for the same seconds from the same seed:
  training    the light-field CNN on the bake's data (plateau stop off): epochs, epochs per second, final loss; for
              CUDA the seconds to reach the CPU run's final loss;
  production  one epoch of the same CNN on a Production-sized light field (R = 32, --production-texels texels: the
              bake's light fields upsampled and repeated), texels per second;
  refits      the lobe refit (torch) on --refit-texels texels for --refit-steps steps on each device; the amplitude
              refit (numpy, the CPU only) on the same texels.
It prints a table and writes --report (JSON). A device it cannot use is named with the reason, never skipped in
silence. Targets (issue: the GPU path): CUDA at least 20x the 2-core CPU's epochs per second, refits faster than
on the CPU; the CPU at least 216 epochs in 30 s on room Draft.
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


def _sync(device: str):
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def train_for(data: dict, device: str, seconds: float, seed: int = 0, epochs: int | None = None) -> dict:
    """The CNN on `data` for `seconds` of training, or exactly `epochs` epochs (plateau stop off): epochs, rate, the
    loss curve."""
    from ..training.sg_fit import LightFieldData, TrainConfig, Trainer

    lobes = data["lobe_counts"]
    light = LightFieldData.from_numpy(data["images"].astype(np.float32), data["normals"], device=device,
                                      lobe_counts=None if lobes.min() == lobes.max() else lobes)
    trainer = Trainer(light, TrainConfig(sg_count=int(lobes.max()), time_budget_s=seconds, device=device, seed=seed,
                                         plateau_epochs=10**9))
    _sync(device)
    start = time.perf_counter()
    state = trainer.train(save_checkpoint=False, epochs=epochs)
    _sync(device)
    wall = time.perf_counter() - start
    return {"device": device, "texels": len(light.images), "epochs": state.epoch, "seconds": round(wall, 2),
            "epochs_per_s": round(state.epoch / wall, 3), "final_loss": state.losses[-1] if state.losses else None,
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
    """Seconds of the lobe refit (torch, on `device`) and, on the CPU, of the amplitude refit (numpy)."""
    from ..training.glossy_lobe_fit import lobe_refit_steps
    from ..training.glossy_refit import refit_amplitudes
    from ..training.sg_fit import LightFieldData, TrainConfig, Trainer

    pick = np.arange(min(texels, len(data["images"])))
    images = data["images"][pick].astype(np.float32)
    normals, roughness, lobes = data["normals"][pick], data["roughness"][pick], data["lobe_counts"][pick]
    count = int(lobes.max())
    trainer = Trainer(LightFieldData.from_numpy(images, normals), TrainConfig(sg_count=count, time_budget_s=1.0))
    axis, sharpness, amplitude = trainer.parameters_numpy()  # an untrained CNN's SGs: the refits' cost is the same
    row = {"device": device, "texels": len(pick), "lobe_refit_steps": steps}
    _sync(device)
    start = time.perf_counter()
    for _ in lobe_refit_steps(images, normals, data["texels"][pick], axis, sharpness, amplitude, roughness, count,
                              steps, device=device):  # a generator of the fraction done
        pass
    _sync(device)
    row["lobe_refit_s"] = round(time.perf_counter() - start, 2)
    if device == "cpu":
        start = time.perf_counter()
        refit_amplitudes(images, normals, axis, sharpness, amplitude, roughness, lobes)
        row["amplitude_refit_s"] = round(time.perf_counter() - start, 2)
    else:
        row["amplitude_refit_s"] = None  # numpy: it runs on the CPU whatever the training device
    return row


def run_check(data: dict, seconds: float, production_texels: int, refit_texels: int, refit_steps: int) -> dict:
    import torch

    measured, names = devices()
    report = {"torch": torch.__version__, "devices": {**names, "cpu": f"{torch.get_num_threads()} threads"},
              "training": [], "production": [], "refits": []}
    for device in measured:
        report["training"].append(train_for(data, device, seconds))
    cpu = report["training"][0]
    for row in report["training"][1:]:
        row["epochs_per_s_over_cpu"] = round(row["epochs_per_s"] / max(cpu["epochs_per_s"], 1e-9), 2)
        row["seconds_to_cpu_final_loss"] = seconds_to_loss(row["curve"], cpu["final_loss"])
    if production_texels:
        big = production_sized(data, production_texels)
        for device in measured:
            row = train_for(big, device, math.inf, epochs=1)
            row["texels_per_s"] = round(row["epochs"] * row["texels"] / max(row["seconds"], 1e-9), 1)
            report["production"].append({k: v for k, v in row.items() if k != "curve"})
    if refit_texels and refit_steps:
        for device in measured:
            report["refits"].append(refit_timings(data, device, refit_texels, refit_steps))
    return report


def print_report(report: dict):
    print(f"torch {report['torch']}; devices: " + "; ".join(f"{k}: {v}" for k, v in report["devices"].items()))
    for row in report["training"]:
        extra = ""
        if "epochs_per_s_over_cpu" in row:
            reach = row["seconds_to_cpu_final_loss"]
            extra = (f", {row['epochs_per_s_over_cpu']}x the CPU's rate (target >= 20), CPU's final loss reached "
                     + (f"after {reach} s" if reach is not None else "never"))
        print(f"training   {row['device']:<5} {row['texels']} texels: {row['epochs']} epochs in {row['seconds']} s "
              f"({row['epochs_per_s']} epochs/s), final loss {row['final_loss']:.5f}{extra}")
    for row in report["production"]:
        print(f"production {row['device']:<5} {row['texels']} texels at R = 32: {row['epochs']} epochs in "
              f"{row['seconds']} s ({row['texels_per_s']} texels/s)")
    for row in report["refits"]:
        amplitude = row["amplitude_refit_s"]
        print(f"refits     {row['device']:<5} {row['texels']} texels: lobe refit {row['lobe_refit_steps']} steps "
              f"{row['lobe_refit_s']} s" + (f", amplitude refit (numpy) {amplitude} s" if amplitude is not None else
                                            ", amplitude refit: numpy, on the CPU"))


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
    report = run_check(load_data(ns.data), ns.seconds, ns.production_texels, ns.refit_texels, ns.refit_steps)
    print_report(report)
    if ns.report:
        from ..bake_directory.bake_plan import write_json_atomic

        write_json_atomic(ns.report, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
