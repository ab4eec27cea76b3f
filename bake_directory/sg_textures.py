"""SG parameter textures in the bake directory (pure numpy): the train stage writes, apply reads.

  sg_lightfield.exr       N SGs per texel of the light field (RGB amplitudes)
  sg_env_visibility.exr   N SGs per texel of W_E (1 or 3 amplitude channels)
The light-field file holds instead 9 L2 SH coefficients per texel (channels ``shJ.R/G/B``, metadata
``encoder: sh_l2``) when the benchmark swaps in the SH baseline; read_sg_texture refuses such a file.
Half-float, atlas-sized (row 0 = top, as texels.exr), channels ``sgJJ.axis.X/Y/Z``, ``sgJJ.sharpness``,
``sgJJ.amp.R/G/B`` (or ``sgJJ.amp.Y``). Stored amplitudes are divided by the metadata's
``amplitude_scale`` (shaders.sg_math.half_amplitude_scale) so HDR suns survive half floats. Gutters are
dilated copies of the nearest texel, so bilinear lookups at chart borders stay meaningful.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..shaders.sg_math import AMPLITUDE_MAX_HALF, half_amplitude_scale, pack_sg_half, unpack_sg_half
from .bake_plan import BakeInputError
from .exr_io import read_exr, read_exr_metadata, write_exr
from .texel_raster import dilate

SH_ENCODER = "sh_l2"
SG_FILES = {"lightfield": "sg_lightfield.exr", "env_visibility": "sg_env_visibility.exr"}
GUTTER_PASSES = 3


def channel_names(sg_count: int, amplitude_channels: int) -> list[str]:
    amps = ["R", "G", "B"] if amplitude_channels == 3 else ["Y"]
    names = []
    for j in range(sg_count):
        names += [f"sg{j:02d}.axis.X", f"sg{j:02d}.axis.Y", f"sg{j:02d}.axis.Z", f"sg{j:02d}.sharpness"]
        names += [f"sg{j:02d}.amp.{c}" for c in amps]
    return names


def scatter_dilated(atlas_shape, texels, values, empty=None) -> np.ndarray:
    """Per-texel values (T, ...) placed at atlas texels (T, 2) [row, col], gutters dilated GUTTER_PASSES rings;
    texels beyond the gutters hold `empty` (zeros when None)."""
    grid = np.zeros(tuple(atlas_shape) + values.shape[1:], np.float32)
    if empty is not None:
        grid[...] = empty
    grid[texels[:, 0], texels[:, 1]] = values
    valid = np.zeros(tuple(atlas_shape), bool)
    valid[texels[:, 0], texels[:, 1]] = True
    filled, _ = dilate({"v": grid}, valid, GUTTER_PASSES)
    return filled["v"]


def write_sg_texture(path, texels, axis, sharpness, amplitude, atlas_shape, metadata: dict) -> dict:
    """Scatter per-texel SGs (T, N, ...) at atlas texels (T, 2) into a half EXR; returns the metadata written."""
    height, width = atlas_shape
    t, n, c = amplitude.shape
    scale = half_amplitude_scale(amplitude.max(initial=0.0))
    axis_h, sharp_h, amp_h = pack_sg_half(axis, sharpness, amplitude, scale)
    per_texel = np.concatenate([axis_h.astype(np.float32), sharp_h.astype(np.float32)[..., None],
                                amp_h.astype(np.float32)], axis=-1).reshape(t, -1)
    empty = np.zeros(per_texel.shape[1], np.float32)
    empty[2::4 + c] = 1.0  # empty texels: axis +Z, sharpness minimum, amplitude 0
    filled = scatter_dilated((height, width), texels, per_texel, empty)
    meta = {**metadata, "sg_count": n, "amplitude_channels": c, "amplitude_scale": repr(scale),
            "packing": "per SG: axis xyz, sharpness, amplitude (divided by amplitude_scale)"}
    write_exr(path, filled, precision="half", channels=channel_names(n, c), metadata=meta)
    return meta


def _checked_metadata(path, plan_hash: str | None, encoder_is_sh: bool) -> dict:
    meta = read_exr_metadata(path)
    if plan_hash is not None and meta.get("plan_hash") != plan_hash:
        raise BakeInputError(f"{path}: made for another plan; run the train stage again")
    if (meta.get("encoder") == SH_ENCODER) != encoder_is_sh:
        raise BakeInputError(f"{path}: holds {meta.get('encoder', 'SG')} parameters, not "
                             f"{'SH coefficients' if encoder_is_sh else 'SGs'}")
    return meta


def is_sh_texture(path) -> bool:
    return read_exr_metadata(path).get("encoder") == SH_ENCODER


def read_sg_texture(path, plan_hash: str | None = None):
    """(axis (H, W, N, 3), sharpness (H, W, N), amplitude (H, W, N, C), metadata), sanitised and rescaled."""
    meta = _checked_metadata(path, plan_hash, encoder_is_sh=False)
    n, c = int(meta["sg_count"]), int(meta["amplitude_channels"])
    data, _, _ = read_exr(path, channels=channel_names(n, c), dtype=np.float16)
    h, w, _ = data.shape
    per = data.reshape(h, w, n, 4 + c)
    axis, sharpness, amplitude = unpack_sg_half(per[..., 0:3], per[..., 3], per[..., 4:], float(meta["amplitude_scale"]))
    return axis, sharpness, amplitude, meta


def write_sh_texture(path, texels, coefficients, atlas_shape, metadata: dict) -> dict:
    """Scatter per-texel SH L2 coefficients (T, 9, C) into a half EXR (divided by amplitude_scale like SG
    amplitudes; coefficients may be negative); returns the metadata written."""
    t, k, c = coefficients.shape
    scale = half_amplitude_scale(np.abs(coefficients).max(initial=0.0))
    stored = np.clip(np.nan_to_num(coefficients / scale), -AMPLITUDE_MAX_HALF, AMPLITUDE_MAX_HALF)
    filled = scatter_dilated(atlas_shape, texels, stored.reshape(t, -1).astype(np.float32))
    meta = {**metadata, "encoder": SH_ENCODER, "sh_count": k, "amplitude_channels": c, "amplitude_scale": repr(scale),
            "packing": "per texel: SH L2 coefficients j = 0..8 (training.baselines.sh_basis order), per channel"}
    write_exr(path, filled, precision="half", channels=sh_channel_names(k, c), metadata=meta)
    return meta


def read_sh_texture(path, plan_hash: str | None = None):
    """(coefficients (H, W, 9, C), metadata), rescaled."""
    meta = _checked_metadata(path, plan_hash, encoder_is_sh=True)
    k, c = int(meta["sh_count"]), int(meta["amplitude_channels"])
    data, _, _ = read_exr(path, channels=sh_channel_names(k, c))
    h, w, _ = data.shape
    return data.reshape(h, w, k, c) * np.float32(float(meta["amplitude_scale"])), meta


def sh_channel_names(count: int, channels: int) -> list[str]:
    return [f"sh{j}.{ch}" for j in range(count) for ch in (["R", "G", "B"] if channels == 3 else ["Y"])]


def bytes_per_texel(sg_count: int, amplitude_channels: int) -> int:
    return 2 * sg_count * (4 + amplitude_channels)


def sg_texture_path(out_dir, kind: str) -> Path:
    return Path(out_dir) / SG_FILES[kind]


def pack_tiles(layout, tiles: dict, atlas_shape) -> np.ndarray:
    """The packed RGBA image (row 0 = top) of a node_group.SGTextureLayout: tiles[(name, j)] is (H, W, 4)."""
    height, width = atlas_shape
    columns, rows = layout.grid
    image = np.zeros((rows * height, columns * width, 4), np.float32)
    for key in layout.tiles:
        col, row_from_bottom = layout.tile_offset(*key)
        top = (rows - 1 - row_from_bottom) * height
        image[top:top + height, col * width:(col + 1) * width] = tiles[key]
    return image
