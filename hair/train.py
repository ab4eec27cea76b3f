"""Train the hair filter on pairs from headless/hair_dataset.py and export it to ONNX.

    python -m hair.train --data hair_data/train --config base+blend --flip-weight 0.3 --steps 21000 \
        --out models/hair_base.onnx

Random 64x64 crops (flipped left-right with tangent x negated; --noise-emphasis g draws a pair with probability
proportional to its noise share to the power g, hair_pairs.noise_share: the views where more samples help most),
Adam (rate x0.3 after 70 % of the budget, x0.1 after 90 %; the budget is --budget seconds, or --steps, which gives the
same training whatever else the machine runs). Loss: the paper's (--loss, --gradient-weight);
--flip-weight adds LDR-FLIP of the composites, each training crop composited with a random hair colour, light and
grey background, validation with hair_raster.EVALUATION_LOOK. Validation loss on the validation pairs after every
epoch, the best weights kept. Checkpoints (weights_only, atomic) every epoch in --work; --resume continues from the
last one. Progress bar with ETA on stderr.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

if __name__ == "__main__" and __package__ in (None, "", "hair"):  # started as a file or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from . import pairs as hair_pairs  # noqa: E402
from ..bake_directory.atomic import atomic_output  # noqa: E402
from .unet import (CONFIGS, LOSS_NORMS, HairNetConfig, HairUNet, export_onnx, hair_loss,  # noqa: E402
                                 random_looks)

CROP = 64
LR_STEPS = ((0.7, 0.3), (0.9, 0.1))  # (share of the budget, learning-rate factor from then on)
TANGENT_X = 4  # feature index inside a sample


def load_pairs(directory, samples: int, with_noise_shares: bool = False):
    """(train inputs, train targets, validation inputs, validation targets) as float16 tensors, and with
    with_noise_shares the training pairs' noise shares (float64 tensor) after them."""
    split = {"train": ([], []), "validation": ([], [])}
    shares = []
    indices = hair_pairs.complete_indices(directory)
    if not indices:
        raise FileNotFoundError(f"no complete hair pairs in {directory}")
    for index in indices:
        features, target, meta = hair_pairs.read_pair(directory, index, samples)
        split[meta["split"]][0].append(torch.from_numpy(features).half())
        split[meta["split"]][1].append(torch.from_numpy(target).half())
        if with_noise_shares and meta["split"] == "train":
            shares.append(hair_pairs.noise_share(features, target))
    out = []
    for name in ("train", "validation"):
        xs, ys = split[name]
        out += [torch.stack(xs) if xs else None, torch.stack(ys) if ys else None]
    if with_noise_shares:
        out.append(torch.tensor(shares, dtype=torch.float64))
    return tuple(out)


def pair_weights(noise_shares: torch.Tensor, emphasis: float):
    """Drawing probabilities of the training pairs: noise share ** emphasis, normalised (None: uniform)."""
    if not emphasis:
        return None
    weights = noise_shares.clamp(min=1e-3) ** emphasis
    return weights / weights.sum()


def random_crops(inputs, targets, batch: int, generator: torch.Generator, weights=None):
    n, _, h, w = inputs.shape
    crop = min(CROP, h, w)
    pick = torch.randint(0, n, (batch,), generator=generator) if weights is None else \
        torch.multinomial(weights, batch, replacement=True, generator=generator)
    ys = torch.randint(0, h - crop + 1, (batch,), generator=generator)
    xs = torch.randint(0, w - crop + 1, (batch,), generator=generator)
    flips = torch.rand(batch, generator=generator) < 0.5
    x_batch, y_batch = [], []
    for i in range(batch):
        x = inputs[pick[i], :, ys[i]:ys[i] + crop, xs[i]:xs[i] + crop].float()
        y = targets[pick[i], :, ys[i]:ys[i] + crop, xs[i]:xs[i] + crop].float()
        if flips[i]:
            x, y = x.flip(-1), y.flip(-1)
            x[TANGENT_X::6] *= -1
        x_batch.append(x)
        y_batch.append(y)
    return torch.stack(x_batch), torch.stack(y_batch)


def validation_loss(model, inputs, targets, gradient_weight: float = 1.0, norm: str = "l2",
                    flip_weight: float = 0.0) -> float:
    if inputs is None:
        return float("nan")
    model.eval()
    total = 0.0
    with torch.no_grad():
        for i in range(len(inputs)):
            total += float(hair_loss(model(inputs[i:i + 1].float()), targets[i:i + 1].float(), gradient_weight, norm,
                                         flip_weight))
    model.train()
    return total / len(inputs)


def train(data: Path, config_name: str, budget_s: float, work: Path, resume: bool = False, batch: int = 8,
          lr: float = 1e-3, seed: int = 0, gradient_weight: float = 1.0, norm: str = "l2",
          flip_weight: float = 0.0, noise_emphasis: float = 0.0, progress=lambda fraction, message: None,
          max_steps: int | None = None) -> dict:
    """Train for budget_s seconds, or with max_steps for that many steps (budget_s is then ignored)."""
    config = HairNetConfig.named(config_name)
    torch.manual_seed(seed)
    train_x, train_y, val_x, val_y, *shares = load_pairs(data, config.samples,
                                                         with_noise_shares=bool(noise_emphasis))
    weights = pair_weights(shares[0], noise_emphasis) if shares else None
    model = HairUNet(config)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    generator = torch.Generator().manual_seed(seed)
    checkpoint = work / f"hair_{config.name}.ckpt.pt"
    state = {"step": 0, "elapsed_s": 0.0, "history": [], "best_validation": float("inf")}
    best_weights = None
    if resume and checkpoint.is_file():
        saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
        model.load_state_dict(saved["model"])
        optimizer.load_state_dict(saved["optimizer"])
        best_weights = saved["best"]
        state = json.loads(saved["state_json"])
        generator.manual_seed(seed + state["step"])
        loss_was = (state.get("gradient_weight", 1.0), state.get("loss_norm", "l2"), state.get("flip_weight", 0.0))
        if loss_was != (gradient_weight, norm, flip_weight):
            state["best_validation"] = float("inf")  # another loss: old validation values don't compare
    state["gradient_weight"], state["loss_norm"], state["flip_weight"] = gradient_weight, norm, flip_weight
    state["noise_emphasis"] = noise_emphasis
    if shares:
        state["noise_share_quartiles"] = [round(float(q), 3) for q in torch.quantile(
            shares[0], torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=torch.float64))]
    crops_per_image = max(1, train_x.shape[-1] // CROP) * max(1, train_x.shape[-2] // CROP)
    steps_per_epoch = max(1, len(train_x) * crops_per_image // batch)
    start = time.monotonic() - state["elapsed_s"]

    def budget_used() -> float:
        if max_steps is not None:
            return state["step"] / max(max_steps, 1)
        return (time.monotonic() - start) / budget_s

    while budget_used() < 1.0:
        running = 0.0
        for _ in range(steps_per_epoch):
            x, y = random_crops(train_x, train_y, batch, generator, weights)
            share = budget_used()
            for group in optimizer.param_groups:
                group["lr"] = lr * min([1.0] + [factor for at, factor in LR_STEPS if share >= at])
            optimizer.zero_grad()
            looks = random_looks(batch, generator) if flip_weight else None
            loss = hair_loss(model(x), y, gradient_weight, norm, flip_weight, looks)
            loss.backward()
            optimizer.step()
            running += loss.item()
            state["step"] += 1
            used = budget_used()
            progress(min(used, 1.0), f"step {state['step']} loss {loss.item():.5f}")
            if used >= 1.0:
                break
        val = validation_loss(model, val_x, val_y, gradient_weight, norm, flip_weight)
        state["elapsed_s"] = time.monotonic() - start
        state["history"].append({"step": state["step"], "seconds": round(state["elapsed_s"], 1),
                                 "train_loss": running / steps_per_epoch, "validation_loss": val})
        if not val >= state["best_validation"]:  # NaN validation (no pairs) keeps the latest weights
            state["best_validation"] = val
            best_weights = {k: v.clone() for k, v in model.state_dict().items()}
        work.mkdir(parents=True, exist_ok=True)
        with atomic_output(checkpoint, suffix=".tmp.pt") as tmp:
            torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                        "best": best_weights, "state_json": json.dumps(state)}, tmp)
    model.load_state_dict(best_weights)
    return {"model": model, "config": config.name, "train_pairs": len(train_x),
            "validation_pairs": 0 if val_x is None else len(val_x), **state}


def main(argv=None) -> int:
    from ..headless.bake import Reporter

    p = argparse.ArgumentParser(prog="python -m hair.train", description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="the train/ directory of a hair dataset")
    p.add_argument("--config", default="base", choices=sorted(CONFIGS))
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--budget", type=float, default=900.0, help="training seconds")
    budget.add_argument("--steps", type=int, help="training steps instead of seconds: the same run on a busy machine")
    p.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    p.add_argument("--work", type=Path, default=Path("bench_out/hair_work"), help="checkpoints")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--gradient-weight", type=float, default=1.0, help="weight of the image-gradient term")
    p.add_argument("--loss", choices=sorted(LOSS_NORMS), default="l2",
                   help="l2: the paper's squared errors; l1: absolute errors")
    p.add_argument("--flip-weight", type=float, default=0.0,
                   help="weight of an LDR-FLIP term on the composited, tone-mapped images (0: the paper's loss)")
    p.add_argument("--noise-emphasis", type=float, default=0.0,
                   help="draw pairs with probability ~ noise share ** this (0: uniform, the paper's)")
    ns = p.parse_args(argv)
    if not 0 <= ns.noise_emphasis <= 8:
        p.error("--noise-emphasis must be in 0..8")
    if ns.steps is not None and ns.steps < 1:
        p.error("--steps must be at least 1")
    if not ns.budget > 0:
        p.error("--budget must be more than 0 seconds")
    if ns.threads:
        torch.set_num_threads(ns.threads)
    reporter = Reporter(as_json=False)
    try:
        result = train(ns.data, ns.config, ns.budget, ns.work, ns.resume, lr=ns.lr, gradient_weight=ns.gradient_weight,
                       norm=ns.loss, flip_weight=ns.flip_weight, noise_emphasis=ns.noise_emphasis,
                       progress=lambda f, m: reporter.progress("train", f, m), max_steps=ns.steps)
    except (FileNotFoundError, ValueError) as error:
        reporter.end_bar()
        print(f"error: {error}", file=sys.stderr)
        return 1
    reporter.end_bar()
    export_onnx(result["model"], ns.out, metadata={"train_pairs": result["train_pairs"],
                                                   "steps": result["step"],
                                                   "best_validation_loss": f"{result['best_validation']:.6g}"})
    history = result["history"]
    first_pair = json.loads(hair_pairs.pair_paths(ns.data, hair_pairs.complete_indices(ns.data)[0])[1].read_text())
    recipe = {"command": "python -m hair.train " + " ".join(sys.argv[1:] if argv is None else argv),
              "dataset": {k: first_pair.get(k) for k in ("size", "reference_samples", "density", "samples")},
              **{k: v for k, v in result.items() if k != "model"}}
    with atomic_output(ns.out.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(recipe, indent=1))
    print(f"hair filter {result['config']}: {result['step']} steps, {len(history)} epochs, "
          f"validation loss {result['best_validation']:.5f} -> {ns.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
