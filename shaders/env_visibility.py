"""Illumination-weighted environment visibility W_E (Paper I section 5, DESIGN section 3), in numpy.

Per texel and reflection direction w (an octahedral pixel):
    W_E(w) = sum_i K(w, w_i) (L_E V)(w_i) / sum_i K(w, w_i) L_E(w_i) m(w_i)
with K the GGX lobe of the texel's roughness as an SG about w (NDF sharpness 2/alpha^2, warped to the
reflection domain at normal incidence: divided by 4) times the pixel solid angle, (L_E V) the texel's
environment-only image (the render stage: each pixel's visibility V, rendered against a white world with
geometry black and nothing below the horizon, times that pixel of L_E), L_E the unoccluded environment and
m the fraction of each pixel above the texel's horizon (the same fraction the render's hemisphere cut
keeps). Unoccluded texels get exactly 1; W_E is clipped to [0, 1].
The kernel depends on roughness only: one (P, P) matrix product per distinct roughness.
"""
from __future__ import annotations

import functools

import numpy as np

from .octahedral import oct_decode, pixel_directions, pixel_solid_angles
from .sg_math import clamp_roughness, ndf_sg

HORIZON_SUBSAMPLES = 8  # per pixel side, for the above-horizon fraction m
ROUGHNESS_GROUP_STEP = 1e-3  # texels whose roughness differs by less share a kernel


def reflection_kernel(resolution: int, roughness: float) -> np.ndarray:
    """(P, P) matrix K[w, w_i] = exp(lam (w . w_i - 1)) * solid_angle(w_i), lam = NDF sharpness / 4."""
    _, sharpness, _ = ndf_sg(np.zeros(3), clamp_roughness(np.asarray(roughness, np.float64)))
    lam = float(sharpness) / 4.0
    d = pixel_directions(resolution).reshape(-1, 3)
    return np.exp(lam * (d @ d.T - 1.0)) * pixel_solid_angles(resolution).reshape(1, -1)


@functools.lru_cache(maxsize=8)
def _pixel_subsample_directions(resolution: int) -> np.ndarray:
    """(P, s*s, 3) directions of an s x s grid inside each pixel, uniform in octahedral coordinates as the
    render's box filter samples them (s = HORIZON_SUBSAMPLES)."""
    s = HORIZON_SUBSAMPLES
    offsets = (np.arange(s) + 0.5) / s
    centres = ((np.arange(resolution)[:, None] + offsets[None, :]) / resolution * 2 - 1).ravel()  # (R*s,)
    u, v = np.meshgrid(centres, centres, indexing="xy")
    d = oct_decode(np.stack([u, v], axis=-1))  # (R*s, R*s, 3)
    d = d.reshape(resolution, s, resolution, s, 3).transpose(0, 2, 1, 3, 4).reshape(resolution * resolution, s * s, 3)
    d.setflags(write=False)
    return d


def above_horizon_fraction(normals: np.ndarray, resolution: int) -> np.ndarray:
    """(T, P) fraction of each octahedral pixel (uniform in octahedral coordinates, as the render's box
    filter samples it) whose directions lie above the plane of the texel's normal."""
    d = _pixel_subsample_directions(int(resolution))
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    unique, inverse = np.unique(np.round(normals, 6), axis=0, return_inverse=True)  # planes share one normal
    out = np.empty((len(unique), d.shape[0]))
    step = max(1, (1 << 24) // d[..., 0].size)  # normals per chunk: its (normals, P, s*s) array stays near 128 MiB
    for start in range(0, len(unique), step):
        cosine = np.einsum("psc,tc->tps", d, unique[start:start + step])
        # sub-samples exactly on the horizon (they exist: the fold diagonal passes through pixel corners)
        # count one half, as the continuous area does
        out[start:start + step] = (0.5 + 0.5 * np.sign(np.where(np.abs(cosine) < 1e-12, 0.0, cosine))).mean(axis=-1)
    return out[inverse.reshape(-1)]


def _apply_kernel(kernel, images):
    """sum_i kernel[w, i] images[t, i, c] as one BLAS matrix product -> (T, P, C)."""
    t, p, c = images.shape
    flat = images.transpose(1, 0, 2).reshape(p, t * c)
    return (kernel @ flat).reshape(p, t, c).transpose(1, 0, 2)


def glossy_prefilter(images: np.ndarray, resolution: int, roughness: float) -> np.ndarray:
    """(T, P, C) radiance (T, P, C) averaged over the GGX lobe of `roughness` about each reflection direction
    (the kernel above, normalised): what a glossy surface of that roughness reflects, before Fresnel and shadowing."""
    kernel = reflection_kernel(resolution, roughness)
    kernel /= kernel.sum(axis=1, keepdims=True)
    return _apply_kernel(kernel, np.asarray(images, np.float64).reshape(len(images), resolution * resolution, -1))


def env_visibility(occluded: np.ndarray, unoccluded: np.ndarray, normals: np.ndarray, roughness: np.ndarray,
                   resolution: int) -> np.ndarray:
    """W_E (T, P, C) from occluded (T, P, C) = L_E V per texel and unoccluded (P, C) = L_E."""
    occluded = np.nan_to_num(np.asarray(occluded, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    occluded = np.maximum(occluded, 0.0)
    unoccluded = np.maximum(np.nan_to_num(np.asarray(unoccluded, np.float64), nan=0.0, posinf=0.0), 0.0)
    mask = above_horizon_fraction(normals, resolution)
    result = np.ones(occluded.shape)
    keys = np.round(np.asarray(roughness, np.float64) / ROUGHNESS_GROUP_STEP).astype(np.int64)
    for key in np.unique(keys):
        members = np.flatnonzero(keys == key)
        kernel = reflection_kernel(resolution, key * ROUGHNESS_GROUP_STEP)
        numerator = _apply_kernel(kernel, occluded[members])
        denominator = _apply_kernel(kernel, mask[members][..., None] * unoccluded[None])
        tiny = 1e-12 * max(float(denominator.max(initial=0.0)), 1e-30)
        ratio = np.where(denominator > tiny, numerator / np.maximum(denominator, tiny), 1.0)
        result[members] = np.clip(ratio, 0.0, 1.0)
    return result
