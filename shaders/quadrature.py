"""Sphere quadratures for checking closed forms (float64, numpy only).

* ``fibonacci_sphere(n)``: equal-weight points, good for smooth integrands.
* ``adaptive_sphere_quadrature(frame, peaks)``: product Gauss-Legendre in a chart
  v = cos(b) sin(a) x + sin(b) y + cos(b) cos(a) z, dw = cos(b) da db, with panel breakpoints
  packed geometrically around each peak (direction and widths along x and y) and on the horizon
  of z. It resolves lobes with sharpness 1e-4 .. 1e6 and the 1e8:1 anisotropy of grazing ASGs.
"""
from __future__ import annotations

import numpy as np

GOLDEN_ANGLE = np.pi * (3 - np.sqrt(5))


def fibonacci_sphere(n: int):
    """n directions (n, 3) with equal weights 4 pi / n."""
    i = np.arange(n, dtype=np.float64)
    z = 1 - (2 * i + 1) / n
    r = np.sqrt(np.maximum(1 - z * z, 0))
    phi = GOLDEN_ANGLE * i
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    return dirs, np.full(n, 4 * np.pi / n)


def _breakpoints(lo, hi, centres_and_widths, extra=()):
    pts = {lo, hi, *[e for e in extra if lo < e < hi]}
    for c, w in centres_and_widths:
        w = max(float(w), 1e-9)
        if lo <= c <= hi:
            pts.add(c)
        k = w / 8
        while k < (hi - lo):
            for s in (-1, 1):
                p = c + s * k
                if lo < p < hi:
                    pts.add(p)
            k *= 2
    return np.array(sorted(pts))


def _gauss_panels(breaks, order):
    x, w = np.polynomial.legendre.leggauss(order)
    a, b = breaks[:-1, None], breaks[1:, None]
    nodes = (a + b) / 2 + (b - a) / 2 * x[None]
    weights = (b - a) / 2 * w[None]
    return nodes.ravel(), weights.ravel()


def frame_from_z(z, x_hint=None):
    z = np.asarray(z, dtype=np.float64)
    z = z / np.linalg.norm(z)
    if x_hint is None or np.linalg.norm(np.cross(z, x_hint)) < 1e-9:
        x_hint = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.asarray(x_hint, dtype=np.float64) - np.dot(x_hint, z) * z
    x /= np.linalg.norm(x)
    return x, np.cross(z, x), z


def adaptive_sphere_quadrature(frame, peaks=(), min_points=1_000_000, hemisphere=False):
    """Directions (n, 3) and weights (n,) integrating over the sphere (or the z hemisphere).

    frame: (x, y, z) orthonormal. peaks: iterable of (direction, width_x, width_y) in radians,
    widths measured along the frame's x and y. At least ``min_points`` nodes are returned."""
    x, y, z = (np.asarray(a, dtype=np.float64) for a in frame)
    a_lo, a_hi = (-np.pi / 2, np.pi / 2) if hemisphere else (-np.pi, np.pi)
    ca, cb = [], []
    for d, wx, wy in peaks:
        d = np.asarray(d, dtype=np.float64)
        b = float(np.arcsin(np.clip(d @ y, -1, 1)))
        a = float(np.arctan2(d @ x, d @ z))
        ca.append((a, wx / max(np.cos(b), 1e-3)))
        cb.append((b, wy))
    # The horizon of z (a = +-pi/2) and the chart's seam are kinks: make them panel edges.
    a_breaks = _breakpoints(a_lo, a_hi, ca, extra=(-np.pi / 2, np.pi / 2, 0.0))
    b_breaks = _breakpoints(-np.pi / 2, np.pi / 2, cb, extra=(0.0,))
    order = 8
    while (len(a_breaks) - 1) * (len(b_breaks) - 1) * order * order < min_points:
        order += 2
    an, aw = _gauss_panels(a_breaks, order)
    bn, bw = _gauss_panels(b_breaks, order)
    A, B = np.meshgrid(an, bn, indexing="ij")
    W = aw[:, None] * bw[None, :] * np.cos(B)
    cosb = np.cos(B)
    dirs = (cosb * np.sin(A))[..., None] * x + np.sin(B)[..., None] * y + (cosb * np.cos(A))[..., None] * z
    return dirs.reshape(-1, 3), W.ravel()


def sg_width(sharpness):
    """Angular 1-sigma width of exp(lam (cos - 1)): 1/sqrt(lam), capped at pi."""
    return float(min(np.pi, 1 / np.sqrt(max(sharpness, 1e-12))))
