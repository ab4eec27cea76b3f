"""Octahedral map (Meyer et al. 2010) in world space, +Z (Blender up) at the centre.

Pixel (row, col) of an R x R map has its centre at u = ((col + 1/2) / R) * 2 - 1 and
v = ((row + 1/2) / R) * 2 - 1; row 0 is v = -1 (the first row stored in an array/EXR).
Solid angles are exact: each pixel is clipped at the fold lines and integrated as planar
polygons on the octahedron (Van Oosterom & Strackee), so they sum to 4 pi to rounding.
"""
from __future__ import annotations

import functools

import numpy as np


def _sign_nonzero(x):
    return np.where(x >= 0, 1.0, -1.0).astype(np.result_type(x, np.float32))


def oct_encode(d):
    """Unit directions (..., 3) -> octahedral coordinates (..., 2) in [-1, 1]^2."""
    d = np.asarray(d)
    l1 = np.maximum(np.abs(d).sum(axis=-1, keepdims=True), 1e-30)
    p = d / l1
    u, v, z = p[..., 0], p[..., 1], p[..., 2]
    fu = (1 - np.abs(v)) * _sign_nonzero(u)
    fv = (1 - np.abs(u)) * _sign_nonzero(v)
    lower = z < 0
    return np.stack([np.where(lower, fu, u), np.where(lower, fv, v)], axis=-1)


def oct_decode(uv):
    """Octahedral coordinates (..., 2) -> unit directions (..., 3)."""
    uv = np.asarray(uv)
    u, v = uv[..., 0], uv[..., 1]
    z = 1 - np.abs(u) - np.abs(v)
    lower = z < 0
    x = np.where(lower, (1 - np.abs(v)) * _sign_nonzero(u), u)
    y = np.where(lower, (1 - np.abs(u)) * _sign_nonzero(v), v)
    p = np.stack([x, y, z], axis=-1)
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


def pixel_centers_uv(resolution: int, dtype=np.float64):
    """(R, R, 2) octahedral coordinates of pixel centres, indexed [row, col]."""
    c = ((np.arange(resolution, dtype=dtype) + 0.5) / resolution) * 2 - 1
    u, v = np.meshgrid(c, c, indexing="xy")
    return np.stack([u, v], axis=-1)


def pixel_directions(resolution: int, dtype=np.float64):
    """(R, R, 3) world directions of the pixel centres."""
    return oct_decode(pixel_centers_uv(resolution, dtype))


def uv_to_pixel(uv, resolution: int):
    """Octahedral coordinates -> integer (row, col) of the pixel that contains them."""
    uv = np.asarray(uv)
    idx = np.floor((uv + 1) * 0.5 * resolution).astype(np.int64)
    idx = np.clip(idx, 0, resolution - 1)
    return idx[..., 1], idx[..., 0]


def direction_to_pixel(d, resolution: int):
    return uv_to_pixel(oct_encode(d), resolution)


# --- exact solid angles -------------------------------------------------------------------------
def _regions():
    """The 8 triangles of [-1,1]^2 on which decoding is affine: (half-planes a.u + b.v <= c, lift)."""
    out = []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            quadrant = [(-sx, 0.0, 0.0), (0.0, -sy, 0.0)]  # sx*u >= 0, sy*v >= 0
            inner = quadrant + [(sx, sy, 1.0)]  # sx*u + sy*v <= 1
            outer = quadrant + [(-sx, -sy, -1.0)]  # sx*u + sy*v >= 1

            def lift_inner(u, v, sx=sx, sy=sy):
                return np.stack([u, v, 1 - sx * u - sy * v], axis=-1)

            def lift_outer(u, v, sx=sx, sy=sy):
                return np.stack([sx * (1 - sy * v), sy * (1 - sx * u), 1 - sx * u - sy * v], axis=-1)

            out.append((inner, lift_inner))
            out.append((outer, lift_outer))
    return out


def _triangle_solid_angle(a, b, c):
    """Solid angle of the planar triangle (a, b, c) seen from the origin (Van Oosterom & Strackee)."""
    la, lb, lc = (np.linalg.norm(p, axis=-1) for p in (a, b, c))
    num = np.abs(np.sum(a * np.cross(b, c), axis=-1))
    den = la * lb * lc + np.sum(a * b, -1) * lc + np.sum(a * c, -1) * lb + np.sum(b * c, -1) * la
    return 2 * np.arctan2(num, den)


def _clip_polygon(poly, a, b, c):
    """Sutherland-Hodgman: keep the part of a convex polygon with a*u + b*v <= c."""
    out = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        fp = a * p[0] + b * p[1] - c
        fq = a * q[0] + b * q[1] - c
        if fp <= 0:
            out.append(p)
        if (fp < 0 < fq) or (fq < 0 < fp):
            t = fp / (fp - fq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _polygon_solid_angle(poly, lift):
    if len(poly) < 3:
        return 0.0
    pts = lift(np.array([p[0] for p in poly]), np.array([p[1] for p in poly]))
    return float(_triangle_solid_angle(pts[0], pts[1:-1], pts[2:]).sum())


@functools.lru_cache(maxsize=16)
def _pixel_solid_angles_cached(resolution: int) -> np.ndarray:
    edges = np.linspace(-1.0, 1.0, resolution + 1)
    u0, v0 = np.meshgrid(edges[:-1], edges[:-1], indexing="xy")
    u1, v1 = np.meshgrid(edges[1:], edges[1:], indexing="xy")
    corners_u = np.stack([u0, u1, u1, u0], axis=-1)
    corners_v = np.stack([v0, v0, v1, v1], axis=-1)
    omega = np.full((resolution, resolution), np.nan)
    regions = _regions()
    tol = 1e-12
    for halfplanes, lift in regions:
        inside = np.ones_like(u0, dtype=bool)
        for a, b, c in halfplanes:
            inside &= np.all(a * corners_u + b * corners_v <= c + tol, axis=-1)
        todo = inside & np.isnan(omega)
        if np.any(todo):
            p = [lift(corners_u[todo][:, k], corners_v[todo][:, k]) for k in range(4)]
            omega[todo] = _triangle_solid_angle(p[0], p[1], p[2]) + _triangle_solid_angle(p[0], p[2], p[3])
    for row, col in zip(*np.nonzero(np.isnan(omega))):
        square = [(edges[col], edges[row]), (edges[col + 1], edges[row]),
                  (edges[col + 1], edges[row + 1]), (edges[col], edges[row + 1])]
        total = 0.0
        for halfplanes, lift in regions:
            poly = square
            for a, b, c in halfplanes:
                poly = _clip_polygon(poly, a, b, c)
                if not poly:
                    break
            total += _polygon_solid_angle(poly, lift)
        omega[row, col] = total
    omega.setflags(write=False)
    return omega


def pixel_solid_angles(resolution: int) -> np.ndarray:
    """(R, R) solid angle of every pixel, in steradians (float64, sums to 4 pi)."""
    if resolution < 1:
        raise ValueError(f"octahedral resolution must be >= 1, got {resolution}")
    return _pixel_solid_angles_cached(int(resolution))


def upper_hemisphere_mask(resolution: int, normal, dtype=bool):
    """(..., R, R) True where the pixel centre direction is above the plane of `normal` (..., 3)."""
    dirs = pixel_directions(resolution)
    return (np.einsum("ijk,...k->...ij", dirs, np.asarray(normal, dtype=np.float64)) > 0).astype(dtype)


def downsample_octahedral(image: np.ndarray, resolution: int) -> np.ndarray:
    """(R k, R k, C) -> (R, R, C), the mean of each k x k block: exact for maps rendered with a box pixel filter,
    since an octahedral pixel is a square in the map's coordinates that its k x k sub-pixels tile."""
    size = image.shape[0]
    if size % resolution:
        raise ValueError(f"an octahedral map of {size} pixels does not average down to {resolution}")
    k = size // resolution
    return image.reshape(resolution, k, resolution, k, -1).mean(axis=(1, 3))
