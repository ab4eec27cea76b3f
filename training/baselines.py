"""Baselines the CNN is measured against, on the same light fields and the same error metrics (numpy/scipy).

  * fixed-axis SGs: N axes on a Fibonacci sphere, one shared sharpness (chosen by search), RGB amplitudes by
    non-negative least squares per texel (the SG9/SG12 of production lightmappers);
  * L2 spherical harmonics (9 coefficients per channel) by least squares.
Both are fitted in linear radiance over the texel's upper hemisphere, weighted by pixel solid angle, as
production bakers do; both interpolate linearly (their coefficients are what a texture filter blends).
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ..shaders.octahedral import pixel_directions, pixel_solid_angles
from ..shaders.quadrature import fibonacci_sphere

FIXED_SG_SHARPNESS_CANDIDATES = (1.0, 2.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)


def _design(resolution, normals):
    """Directions (P, 3), sqrt-weights (T, P): solid angle times the upper hemisphere."""
    d = pixel_directions(resolution).reshape(-1, 3)
    w = pixel_solid_angles(resolution).reshape(1, -1) * (np.asarray(normals, np.float64) @ d.T > 0)
    return d, np.sqrt(w)


def sh_basis(d: np.ndarray) -> np.ndarray:
    """Real SH up to l = 2 at unit directions (..., 3) -> (..., 9)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([0.282095 + 0 * x, 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y,
                     1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)], -1)


def fit_sh_l2(images: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Least-squares L2 SH coefficients (T, 9, C), with a tiny ridge so hemisphere-only data stays stable."""
    t, r, _, c = images.shape
    d, sw = _design(r, normals)
    basis = sh_basis(d)  # (P, 9)
    coeffs = np.empty((t, 9, c))
    for k in range(t):
        a = basis * sw[k][:, None]
        b = images[k].reshape(-1, c) * sw[k][:, None]
        gram = a.T @ a + 1e-6 * np.eye(9)
        coeffs[k] = np.linalg.solve(gram, a.T @ b)
    return coeffs


def eval_sh(coeffs: np.ndarray, resolution: int) -> np.ndarray:
    basis = sh_basis(pixel_directions(resolution))  # (R, R, 9)
    return np.einsum("rck,tkn->trcn", basis, coeffs).astype(np.float32)


def fixed_sg_lobes(count: int, sharpness: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    axes = fibonacci_sphere(count)[0]
    d = pixel_directions(resolution).reshape(-1, 3)
    return axes, np.exp(sharpness * (d @ axes.T - 1.0))  # (P, N)


def fit_fixed_sg(images: np.ndarray, normals: np.ndarray, count: int = 12, sharpness: float | None = None):
    """Amplitudes (T, N, C) >= 0 of `count` fixed lobes by NNLS; returns (axes, sharpness, amplitudes)."""
    t, r, _, c = images.shape
    if sharpness is None:
        probe = np.linspace(0, t - 1, num=min(t, 64)).astype(int)
        errors = []
        for candidate in FIXED_SG_SHARPNESS_CANDIDATES:
            _, _, amps = fit_fixed_sg(images[probe], normals[probe], count, candidate)
            prediction = eval_fixed_sg(fibonacci_sphere(count)[0], candidate, amps, r)
            _, sw = _design(r, normals[probe])
            errors.append(np.sum(((prediction - images[probe]).reshape(len(probe), -1, c) * sw[..., None]) ** 2))
        sharpness = FIXED_SG_SHARPNESS_CANDIDATES[int(np.argmin(errors))]
    axes, lobes = fixed_sg_lobes(count, sharpness, r)
    _, sw = _design(r, normals)
    amplitudes = np.empty((t, count, c))
    for k in range(t):
        a = lobes * sw[k][:, None]
        b = images[k].reshape(-1, c) * sw[k][:, None]
        for ch in range(c):
            amplitudes[k, :, ch] = nnls(a, b[:, ch], maxiter=50 * count)[0]
    return axes, float(sharpness), amplitudes


def eval_fixed_sg(axes, sharpness, amplitudes, resolution: int) -> np.ndarray:
    d = pixel_directions(resolution)
    lobes = np.exp(sharpness * (d @ np.asarray(axes).T - 1.0))  # (R, R, N)
    return np.einsum("rcn,tnk->trck", lobes, amplitudes).astype(np.float32)


def bytes_per_texel_fixed_sg(count: int, channels: int = 3) -> int:
    return 2 * count * channels  # axes and sharpness are shared constants


def bytes_per_texel_sh_l2(channels: int = 3) -> int:
    return 2 * 9 * channels
