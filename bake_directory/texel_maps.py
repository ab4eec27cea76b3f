"""The capture stage's texel maps as files: channel layout, flags, reading with a plan check, pictures.

Pure numpy (no bpy): the render stage, training and tests read texel maps through this module.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .bake_plan import BakeInputError
from .bake_report import save_png
from .exr_io import read_exr

TEXELS_FILE, TEXELS_JSON = "texels.exr", "texels.json"
TEXEL_CHANNELS = [
    "P.X", "P.Y", "P.Z",  # world position of the sample (after push-out), metres
    "Ng.X", "Ng.Y", "Ng.Z",  # geometric normal, outward
    "N.X", "N.Y", "N.Z",  # shading normal
    "roughness", "metallic", "base.R", "base.G", "base.B", "F0.R", "F0.G", "F0.B",
    "valid",  # 1: render this texel's light field; 0: gutter, empty or buried
    "flags",  # FLAG_* bits
    "object_id", "material_id",  # 1-based indices into texels.json tables; 0 = none
    "texel_size",  # world-space edge length of the texel footprint, metres
    "ray_offset",  # origin offset along Ng for rays leaving this texel, metres
]
CHANNEL = {name: i for i, name in enumerate(TEXEL_CHANNELS)}
FLAG_COVERED, FLAG_CENTRE_INSIDE, FLAG_PUSHED_OUT, FLAG_BURIED, FLAG_GUTTER = 1, 2, 4, 8, 16
CAPTURE_PICTURES = ("capture_position.png", "capture_normal.png", "capture_validity.png")


def channels(atlas: np.ndarray, first: str, count: int = 1) -> np.ndarray:
    """Slice `count` consecutive channels starting at `first`, e.g. channels(atlas, "P.X", 3)."""
    start = CHANNEL[first]
    return atlas[..., start] if count == 1 else atlas[..., start:start + count]


def read_texel_maps(out_dir, plan_hash: str | None = None):
    """(atlas (H, W, C) float32, texels.json dict); refuses maps made for another plan."""
    out_dir = Path(out_dir)
    info_path = out_dir / TEXELS_JSON
    if not info_path.is_file():
        raise BakeInputError(f"{out_dir}: no texel maps ({TEXELS_JSON}); run the capture stage first")
    info = json.loads(info_path.read_text())
    atlas, _, metadata = read_exr(out_dir / TEXELS_FILE, channels=TEXEL_CHANNELS)
    if metadata.get("plan_hash") != info.get("plan_hash"):
        raise BakeInputError(f"{out_dir}: {TEXELS_FILE} and {TEXELS_JSON} come from different bakes")
    if plan_hash is not None and info.get("plan_hash") != plan_hash:
        raise BakeInputError(f"{out_dir}: texel maps were captured for another plan; run the capture stage again")
    return atlas, info


def texels_of_objects(atlas: np.ndarray, info: dict, texels: np.ndarray, names) -> np.ndarray:
    """(T,) True for the texels (T, 2) of the named objects."""
    ids = [o["id"] for o in info["objects"] if o["name"] in set(names)]
    return np.isin(channels(atlas, "object_id")[texels[:, 0], texels[:, 1]].astype(np.int64), ids)


def smooth_over_texels(atlas: np.ndarray, texels: np.ndarray, values: np.ndarray, sigma: float = 0.7,
                       normal_power: float = 8.0) -> np.ndarray:
    """(T, C) `values` of the texels (T, 2) averaged over their 3 x 3 atlas neighbours on the same object, weighted
    by exp(-d^2 / (2 (sigma * texel size)^2)) of the world distance d and (n . n')^normal_power of the geometric
    normals: Monte Carlo noise falls, creases and other objects stay apart. On the Draft spheres' floor it takes the
    irradiance's error against a 256-spp render from 10.1 % to 6.0 % (docs/design-additions.md)."""
    height, width = atlas.shape[:2]
    rows, cols = texels[:, 0], texels[:, 1]
    index = np.full((height, width), -1, np.int64)
    index[rows, cols] = np.arange(len(texels))
    position, normal = channels(atlas, "P.X", 3), channels(atlas, "Ng.X", 3)
    object_id, size = channels(atlas, "object_id"), channels(atlas, "texel_size")
    scale = np.maximum(sigma * size[rows, cols], 1e-12)
    total, weights = np.zeros(values.shape, np.float64), np.zeros(len(texels))
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = np.clip(rows + dr, 0, height - 1), np.clip(cols + dc, 0, width - 1)
            other = index[r, c]
            same = (other >= 0) & (r == rows + dr) & (c == cols + dc) & (object_id[r, c] == object_id[rows, cols])
            distance2 = ((position[r, c] - position[rows, cols]) ** 2).sum(-1) / scale**2
            facing = np.maximum((normal[r, c] * normal[rows, cols]).sum(-1), 0.0) ** normal_power
            weight = np.where(same, np.exp(-0.5 * distance2) * facing, 0.0)
            total += weight[:, None] * values[np.maximum(other, 0)]
            weights += weight
    return total / np.maximum(weights, 1e-30)[:, None]


def adjacent_texel_pairs(atlas: np.ndarray) -> np.ndarray:
    """(M, 4) [row, col, row2, col2]: every horizontally or vertically adjacent pair of valid texels of one object,
    the pairs a bilinear lookup blends (the held-out midpoints and the interpolation term of training use them)."""
    valid = channels(atlas, "valid") > 0
    object_id = channels(atlas, "object_id")
    pairs = []
    for dr, dc in ((0, 1), (1, 0)):
        a = valid[:valid.shape[0] - dr, :valid.shape[1] - dc]
        b = valid[dr:, dc:]
        same = object_id[:object_id.shape[0] - dr, :object_id.shape[1] - dc] == object_id[dr:, dc:]
        r, c = np.nonzero(a & b & same)
        pairs.append(np.stack([r, c, r + dr, c + dc], axis=-1))
    return np.concatenate(pairs).astype(np.int64)


def save_capture_pictures(out_dir, atlas: np.ndarray) -> list[Path]:
    """Position, normal and validity pictures of the atlas (nearest-neighbour enlarged PNGs)."""
    out_dir = Path(out_dir)
    valid = channels(atlas, "valid") > 0
    flags = channels(atlas, "flags").astype(np.int64)
    known = (flags & (FLAG_COVERED | FLAG_GUTTER)) > 0
    position = channels(atlas, "P.X", 3).astype(np.float64)
    lo, hi = position[known].min(axis=0), position[known].max(axis=0)
    position_rgb = np.where(known[..., None], (position - lo) / np.maximum(hi - lo, 1e-12), 0.0)
    normal_rgb = np.where(known[..., None], 0.5 + 0.5 * channels(atlas, "N.X", 3), 0.0)
    validity = np.zeros(valid.shape + (3,))
    validity[(flags & FLAG_GUTTER) > 0] = (0.35, 0.35, 0.35)  # dilated gutter
    validity[valid] = (1.0, 1.0, 1.0)  # centre inside a triangle
    validity[valid & ((flags & FLAG_CENTRE_INSIDE) == 0)] = (0.55, 0.75, 1.0)  # partly covered (conservative)
    validity[(flags & FLAG_PUSHED_OUT) > 0] = (1.0, 0.6, 0.0)
    validity[(flags & FLAG_BURIED) > 0] = (0.9, 0.0, 0.0)
    return [save_png(out_dir / name, image)
            for name, image in zip(CAPTURE_PICTURES, (position_rgb, normal_rgb, validity))]
