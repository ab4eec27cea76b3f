"""Image error metrics on tone-mapped renders (pure numpy + the flip-evaluator package).

Tone mapping (both images alike): Reinhard x / (1 + x) per channel of linear radiance, then sRGB encoding;
RMSE and PSNR on those [0, 1] values; FLIP (NVIDIA's perceptual difference, LDR mode) on the same images.
"""
from __future__ import annotations

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights of linear RGB


def tonemap(linear: np.ndarray) -> np.ndarray:
    x = np.maximum(np.nan_to_num(np.asarray(linear, np.float64)[..., :3], nan=0.0, posinf=1e30), 0.0)
    mapped = x / (1.0 + x)
    return np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * np.power(mapped, 1 / 2.4) - 0.055)


def rmse(a: np.ndarray, b: np.ndarray, mask=None) -> float:
    diff = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        diff = diff[mask]
    return float(np.sqrt(diff.mean())) if diff.size else 0.0


def psnr(a: np.ndarray, b: np.ndarray, mask=None) -> float:
    error = rmse(a, b, mask)
    return float("inf") if error == 0 else float(20 * np.log10(1.0 / error))


def rmse_against_converged(rmse_to_reference: float, reference_noise_rmse: float) -> float:
    """The RMSE a test image would have against the converged reference, from its RMSE against a noisy reference
    and that reference's noise RMSE (unbiased from two independent halves: RMSE(half A, half B) / 2). The
    reference's noise is independent of the test image, so mean squares add: E|t - r|^2 = |t - c|^2 + E|r - c|^2.
    0 where the noise explains all of the difference."""
    return float(np.sqrt(max(rmse_to_reference ** 2 - reference_noise_rmse ** 2, 0.0)))


def flip(reference_ldr: np.ndarray, test_ldr: np.ndarray):
    """(mean FLIP, per-pixel FLIP map (H, W)) of two sRGB-encoded [0, 1] images."""
    import flip_evaluator

    flip_map, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(reference_ldr, np.float32),
                                                np.ascontiguousarray(test_ldr, np.float32), "LDR",
                                                inputsRGB=True, applyMagma=False)
    flip_map = np.asarray(flip_map, np.float64)
    return float(mean), flip_map.reshape(flip_map.shape[0], flip_map.shape[1], -1)[..., 0]


def heat(error: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """A (H, W) error as an RGB heat map (black -> red -> yellow -> white)."""
    e = np.asarray(error, np.float64)
    top = vmax if vmax is not None else max(float(np.percentile(e, 99)), 1e-12)
    t = np.clip(e / top, 0, 1)[..., None]
    return np.clip(np.concatenate([3 * t, 3 * t - 1, 3 * t - 2], axis=-1), 0, 1)
