"""Texel rasterisation in lightmap UV space (pure numpy; the capture stage feeds it from bpy).

Coordinates: atlas pixel space with x = u * W and y = (1 - v) * H, so array row 0 is the top row,
as in EXR and PNG files; texel (row r, column c) covers [c, c+1] x [r, r+1] and its centre is
(c + 0.5, r + 0.5).

Rasterisation is conservative: a texel belongs to every triangle its square overlaps (exact
separating-axis test). Each texel takes one sample point: its centre when a triangle contains it,
otherwise the point of the nearest overlapping triangle closest to the centre, so the sample
always lies on the surface.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Triangles with less UV area than this (in texels^2) cannot be rasterised meaningfully.
MIN_UV_AREA_TEXELS = 1e-12
# A pair of candidate texels per triangle beyond this means the UVs are absurd (a sliver spanning the
# whole atlas is fine; 2e8 candidates is ~10 GB of temporaries).
MAX_CANDIDATES = 200_000_000


@dataclass
class Raster:
    """Per-texel result of rasterising triangles; arrays are (H, W) or (H, W, 3)."""

    triangle: np.ndarray  # int64, -1 where no triangle overlaps
    barycentric: np.ndarray  # float64 (H, W, 3), weights of the sample point
    centre_inside: np.ndarray  # bool, the texel centre lies inside its triangle
    distance: np.ndarray  # float64, texel-centre to sample distance in texels (0 when inside)

    @property
    def covered(self) -> np.ndarray:
        return self.triangle >= 0


def signed_areas(tri: np.ndarray) -> np.ndarray:
    """Signed areas of 2D triangles (T, 3, 2); positive for counter-clockwise corners."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _usable_triangles(tri_px: np.ndarray):
    """The triangles worth rasterising (finite, more than MIN_UV_AREA_TEXELS of area): their indices, corners,
    edge vectors (corner k to k+1) and orientation signs."""
    signed = signed_areas(tri_px)
    usable = (np.abs(signed) > MIN_UV_AREA_TEXELS) & np.all(np.isfinite(tri_px.reshape(-1, 6)), axis=1)
    index = np.flatnonzero(usable)
    tri_px = tri_px[index]
    return index, tri_px, np.roll(tri_px, -1, axis=1) - tri_px, np.sign(signed[index])


def _inward_normal(edges, sign, tri, k):
    """Normal of edge k of each candidate's triangle, pointing into the triangle (not unit length)."""
    e = edges[tri, k]
    return sign[tri, None] * np.stack([-e[:, 1], e[:, 0]], axis=-1)


def _candidate_pairs(tri_px: np.ndarray, width: int, height: int):
    lo = np.floor(tri_px.min(axis=1)).astype(np.int64)
    hi = np.floor(tri_px.max(axis=1)).astype(np.int64)
    lo = np.clip(lo, 0, [width - 1, height - 1])
    hi = np.clip(hi, 0, [width - 1, height - 1])
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    counts = nx * ny
    total = int(counts.sum())
    if total > MAX_CANDIDATES:
        raise ValueError(f"UV triangles cover {total} candidate texels; the layout or density is absurd")
    tri = np.repeat(np.arange(len(tri_px)), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    col = lo[tri, 0] + local % nx[tri]
    row = lo[tri, 1] + local // nx[tri]
    return tri, row, col


def _closest_point_barycentric(p, a, b, c):
    """Barycentric weights of the point of triangle abc closest to p (2D, vectorised), and distance."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    denom = d00 * d11 - d01 * d01
    safe = np.where(np.abs(denom) > 0, denom, 1.0)
    w1 = (d11 * d20 - d01 * d21) / safe
    w2 = (d00 * d21 - d01 * d20) / safe
    bary = np.stack([1 - w1 - w2, w1, w2], axis=-1)
    inside = np.all(bary >= 0, axis=-1)
    best_bary = bary.copy()
    best_dist = np.zeros(len(p))
    outside = ~inside
    if np.any(outside):
        q, corners = p[outside], (a[outside], b[outside], c[outside])
        dists, barys = [], []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            e = corners[j] - corners[i]
            t = np.clip(((q - corners[i]) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-300), 0.0, 1.0)
            point = corners[i] + t[:, None] * e
            dists.append(np.linalg.norm(q - point, axis=-1))
            w = np.zeros((len(q), 3))
            w[:, i], w[:, j] = 1 - t, t
            barys.append(w)
        nearest = np.argmin(np.stack(dists), axis=0)
        best_bary[outside] = np.stack(barys)[nearest, np.arange(len(q))]
        best_dist[outside] = np.stack(dists)[nearest, np.arange(len(q))]
    return best_bary, best_dist, inside


def _clipped_centroid(triangle, cx, cy):
    """Centroid of triangle ∩ texel square centred at (cx, cy) (Sutherland-Hodgman); None if empty."""
    polygon = [tuple(p) for p in triangle]
    for axis, bound, keep_below in ((0, cx + 0.5, True), (0, cx - 0.5, False), (1, cy + 0.5, True),
                                    (1, cy - 0.5, False)):
        inside = (lambda q: q[axis] <= bound) if keep_below else (lambda q: q[axis] >= bound)
        clipped = []
        for i, current in enumerate(polygon):
            previous = polygon[i - 1]
            if inside(current) != inside(previous):
                t = (bound - previous[axis]) / (current[axis] - previous[axis])
                clipped.append(tuple(previous[k] + t * (current[k] - previous[k]) for k in range(2)))
            if inside(current):
                clipped.append(current)
        polygon = clipped
        if not polygon:
            return None
    points = np.array(polygon)
    x, y = points[:, 0], points[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = cross.sum() / 2
    if abs(area) < 1e-14:
        return points.mean(axis=0)
    return np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * area)


def _barycentric(p, a, b, c):
    v0, v1, v2 = b - a, c - a, p - a
    denom = v0[0] * v1[1] - v1[0] * v0[1]
    w1 = (v2[0] * v1[1] - v1[0] * v2[1]) / denom
    w2 = (v0[0] * v2[1] - v2[0] * v0[1]) / denom
    return np.clip(np.array([1 - w1 - w2, w1, w2]), 0.0, 1.0)


def rasterize(tri_px: np.ndarray, width: int, height: int) -> Raster:
    """Conservatively rasterise triangles (T, 3, 2) given in atlas pixel coordinates."""
    tri_px = np.asarray(tri_px, dtype=np.float64).reshape(-1, 3, 2)
    triangle = np.full((height, width), -1, np.int64)
    barycentric = np.zeros((height, width, 3))
    centre_inside = np.zeros((height, width), bool)
    distance = np.full((height, width), np.inf)
    result = Raster(triangle, barycentric, centre_inside, distance)
    index, tri_px, edges, sign = _usable_triangles(tri_px)
    if len(index) == 0:
        return result
    tri, row, col = _candidate_pairs(tri_px, width, height)
    if len(tri) == 0:
        return result
    centre = np.stack([col + 0.5, row + 0.5], axis=-1)
    # Separating axes: x and y (bounding boxes) and the three edge normals, pointing inwards.
    tmin, tmax = tri_px.min(axis=1)[tri], tri_px.max(axis=1)[tri]
    overlap = (col < tmax[:, 0]) & (col + 1 > tmin[:, 0]) & (row < tmax[:, 1]) & (row + 1 > tmin[:, 1])
    for k in range(3):
        normal = _inward_normal(edges, sign, tri, k)
        reach = 0.5 * (np.abs(normal[:, 0]) + np.abs(normal[:, 1]))
        overlap &= ((centre - tri_px[tri, k]) * normal).sum(-1) + reach > 0
    tri, row, col, centre = tri[overlap], row[overlap], col[overlap], centre[overlap]
    corners = tri_px[tri]
    bary, dist, inside = _closest_point_barycentric(centre, corners[:, 0], corners[:, 1], corners[:, 2])
    # The nearest point can lie outside the texel when a triangle only clips its corner: then sample the
    # centroid of the part of the triangle inside the texel instead.
    sample = np.einsum("nk,nkc->nc", bary, corners)
    for i in np.flatnonzero(np.abs(sample - centre).max(axis=-1) > 0.5):
        point = _clipped_centroid(corners[i], *centre[i])
        if point is not None:
            bary[i] = _barycentric(point, *corners[i])
            bary[i] /= bary[i].sum()
            dist[i] = np.linalg.norm(np.einsum("k,kc->c", bary[i], corners[i]) - centre[i])
    # One triangle per texel: the nearest (distance 0 = contains the centre); ties go to the lowest index.
    order = np.lexsort((tri, dist, row * width + col))
    flat = (row * width + col)[order]
    first = np.ones(len(flat), bool)
    first[1:] = flat[1:] != flat[:-1]
    pick = order[first]
    r, c = row[pick], col[pick]
    triangle[r, c] = index[tri[pick]]
    barycentric[r, c] = bary[pick]
    centre_inside[r, c] = inside[pick]
    distance[r, c] = dist[pick]
    return result


def centre_overlap_count(tri_px: np.ndarray, width: int, height: int) -> np.ndarray:
    """How many triangles contain each texel centre (H, W); > 1 means the UV layout overlaps."""
    tri_px = np.asarray(tri_px, dtype=np.float64).reshape(-1, 3, 2)
    count = np.zeros((height, width), np.int64)
    _, tri_px, edges, sign = _usable_triangles(tri_px)
    if len(tri_px) == 0:
        return count
    tri, row, col = _candidate_pairs(tri_px, width, height)
    centre = np.stack([col + 0.5, row + 0.5], axis=-1)
    inside = np.ones(len(tri), bool)
    for k in range(3):
        normal = _inward_normal(edges, sign, tri, k)
        side = ((centre - tri_px[tri, k]) * normal).sum(-1)
        # Half-open rule so a centre on an edge shared by two triangles counts once.
        inside &= (side > 0) | ((side == 0) & ((normal[:, 1] > 0) | ((normal[:, 1] == 0) & (normal[:, 0] > 0))))
    np.add.at(count, (row[inside], col[inside]), 1)
    return count


def dilate(values: dict[str, np.ndarray], valid: np.ndarray, passes: int):
    """Fill up to `passes` rings of invalid texels around valid ones with a copy of a valid neighbour.

    Copies (never averages): a position or object id averaged across a chart seam means nothing.
    Returns the filled arrays and the mask of texels that received a value."""
    filled = valid.copy()
    out = {k: v.copy() for k, v in values.items()}
    h, w = valid.shape
    offsets = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
    for _ in range(passes):
        newly = np.zeros_like(filled)
        source = np.full((h, w, 2), -1, np.int64)
        for dr, dc in offsets:
            shifted = np.zeros_like(filled)
            src_r = slice(max(dr, 0), h + min(dr, 0))
            dst_r = slice(max(-dr, 0), h + min(-dr, 0))
            src_c = slice(max(dc, 0), w + min(dc, 0))
            dst_c = slice(max(-dc, 0), w + min(-dc, 0))
            shifted[dst_r, dst_c] = filled[src_r, src_c]
            take = shifted & ~filled & ~newly
            rr, cc = np.nonzero(take)
            source[rr, cc] = np.stack([rr + dr, cc + dc], axis=-1)
            newly |= take
        rr, cc = np.nonzero(newly)
        if len(rr) == 0:
            break
        sr, sc = source[rr, cc, 0], source[rr, cc, 1]
        for key in out:
            out[key][rr, cc] = out[key][sr, sc]
        filled |= newly
    return out, filled


def _shelf_pack_at(padded, order, width):
    positions = [None] * len(padded)
    x = y = shelf_height = used_width = 0
    for i in order:
        w, h = padded[i]
        if x + w > width:
            x, y, shelf_height = 0, y + shelf_height, 0
        positions[i] = (x, y)
        x += w
        used_width = max(used_width, x)
        shelf_height = max(shelf_height, h)
    return positions, used_width, y + shelf_height


def shelf_pack(sizes: list[tuple[int, int]], border: int = 1, max_side: int = 16384):
    """Place rectangles (w, h) without overlap in one atlas: shelves, tallest first, at the atlas width
    (from the widest rectangle to all in one row) that gives the smallest area.

    Returns (positions [(x, y)], width, height); each rectangle keeps `border` free texels around it.
    Raises ValueError when the atlas would exceed `max_side`."""
    if not sizes:
        return [], 0, 0
    padded = [(w + 2 * border, h + 2 * border) for w, h in sizes]
    order = sorted(range(len(sizes)), key=lambda i: (-padded[i][1], -padded[i][0], i))
    narrowest, widest = max(w for w, _ in padded), sum(w for w, _ in padded)
    best = None
    for width in np.unique(np.linspace(narrowest, widest, num=min(widest - narrowest + 1, 128)).astype(int)):
        positions, used_w, used_h = _shelf_pack_at(padded, order, int(width))
        key = (used_w * used_h, max(used_w, used_h))
        if best is None or key < best[0]:
            best = (key, positions, used_w, used_h)
    _, positions, width, height = best
    if max(width, height) > max_side:
        raise ValueError(f"atlas would be {width} x {height} texels (max side {max_side})")
    return [(x + border, y + border) for x, y in positions], width, height
