"""Hair training pairs on disk (pure numpy): one EXR and one JSON per pair, the JSON written last.

    DIR/pair_00042.exr   s0.color_factor ... s3.tangent_y   stochastic input, 4 samples x 6 features
                         target.color_factor, target.highlight, target.alpha   Cycles reference (straight)
    DIR/pair_00042.json  style, camera, light, split, seconds; its presence marks the pair complete

Generation is resumable: a pair with both files is never made again, a pair with only an EXR is redone.
Every tenth pair (index % 10 == 9) is validation; held-out styles live in their own directory.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..bake_directory.atomic import atomic_output
from ..bake_directory.exr_io import read_exr, write_exr
from .raster import EVALUATION_LOOK, FEATURE_NAMES, OUTPUT_NAMES, composite

PAIR_SAMPLES = 4
VALIDATION_EVERY = 10


def split_of(index: int) -> str:
    return "validation" if index % VALIDATION_EVERY == VALIDATION_EVERY - 1 else "train"


def pair_paths(directory, index: int) -> tuple[Path, Path]:
    stem = Path(directory) / f"pair_{index:05d}"
    return stem.with_suffix(".exr"), stem.with_suffix(".json")


def input_channels(samples: int = PAIR_SAMPLES) -> list[str]:
    return [f"s{s}.{name}" for s in range(samples) for name in FEATURE_NAMES]


TARGET_CHANNELS = [f"target.{name}" for name in OUTPUT_NAMES]


def is_complete(directory, index: int) -> bool:
    exr, meta = pair_paths(directory, index)
    return exr.is_file() and meta.is_file()


def write_pair(directory, index: int, features: np.ndarray, target: np.ndarray, meta: dict) -> None:
    """features (S, 6, H, W), target (3, H, W); EXR (half) first, then the JSON that marks completion."""
    samples = features.shape[0]
    stacked = np.concatenate([features.reshape(-1, *features.shape[2:]), target], axis=0)
    exr, json_path = pair_paths(directory, index)
    write_exr(exr, np.moveaxis(stacked, 0, -1), precision="half",
              channels=input_channels(samples) + TARGET_CHANNELS)
    with atomic_output(json_path) as tmp:
        tmp.write_text(json.dumps({"index": index, "split": split_of(index), "samples": samples, **meta},
                                  indent=1))


def read_pair(directory, index: int, samples: int = PAIR_SAMPLES) -> tuple[np.ndarray, np.ndarray, dict]:
    """(input (6*samples, H, W), target (3, H, W), meta) as float32."""
    exr, json_path = pair_paths(directory, index)
    meta = json.loads(json_path.read_text())
    pixels, _, _ = read_exr(exr, channels=input_channels(samples) + TARGET_CHANNELS)
    planes = np.moveaxis(pixels, -1, 0).astype(np.float32)
    return planes[:-3], planes[-3:], meta


def complete_indices(directory) -> list[int]:
    directory = Path(directory)
    found = []
    for meta in sorted(directory.glob("pair_*.json")):
        index = int(meta.stem.split("_")[1])
        if is_complete(directory, index):
            found.append(index)
    return found


def noise_share(features: np.ndarray, target: np.ndarray) -> float:
    """How much of the unfiltered input's error is sampling noise, in [0, 1]: the variance of the mean of its
    samples over its squared error against the target, both of the composite in the bench's look
    (hair_raster.EVALUATION_LOOK) in linear radiance. features (6*S, H, W) as read_pair gives them. More samples
    remove only this share (16 instead of 4: 3/4 of it), so a view with a high share is one where unfiltered
    16 spp gains most over 4. Linear, not tone-mapped: from 4 covered-or-not samples a pixel's tone-mapped
    variance is too noisy an estimate (0.4-1.0 on unbiased views, against 0.9-1.2 linear)."""
    per_sample = len(FEATURE_NAMES)
    samples = features.shape[0] // per_sample
    if samples < 2:
        raise ValueError("the noise share needs at least 2 samples per pixel")
    hair_color, light, grey = EVALUATION_LOOK
    background = np.full(features.shape[1:] + (3,), grey)
    # Plain stochastic transparency composites as the mean of its samples' composites (each sample covered or not).
    images = []
    for s in range(samples):
        colour, highlight, alpha = features[s * per_sample:s * per_sample + 3].astype(np.float64)
        covered = alpha > 0
        images.append(composite(np.stack([np.where(covered, colour, 1.0), np.where(covered, highlight, 0.0),
                                          covered.astype(np.float64)]), hair_color, background, light))
    images = np.stack(images)
    noise = float(images.var(axis=0, ddof=1).sum()) / samples
    error = float(((images.mean(axis=0) - composite(target.astype(np.float64), hair_color, background,
                                                     light)) ** 2).sum())
    return min(1.0, noise / error) if error > 0 else 0.0
