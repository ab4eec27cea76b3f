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

try:
    from .atomic import atomic_output
    from .exr_io import read_exr, write_exr
    from .hair_raster import FEATURE_NAMES, OUTPUT_NAMES
except ImportError:
    from shaders.atomic import atomic_output
    from shaders.exr_io import read_exr, write_exr
    from shaders.hair_raster import FEATURE_NAMES, OUTPUT_NAMES

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
