"""Texel rasterisation, overlap detection, gutter dilation and atlas packing (pure numpy)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sg_lightfield.bake_directory.texel_raster import centre_overlap_count, dilate, rasterize, shelf_pack


def _point_in_triangle(p, tri):
    a, b, c = tri
    d = lambda u, v, w: (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])  # noqa: E731
    s = np.array([d(a, b, p), d(b, c, p), d(c, a, p)])
    return np.all(s >= 0, axis=0) | np.all(s <= 0, axis=0)


@pytest.mark.parametrize("seed", range(6))
def test_conservative_coverage_matches_supersampled_overlap(seed):
    """Every texel a triangle touches is covered (dense supersampling finds no miss) and every covered
    texel really overlaps a triangle (its sample point lies on the triangle, inside the texel)."""
    rng = np.random.default_rng(seed)
    tris = rng.uniform(0, 12, size=(4, 3, 2))
    raster = rasterize(tris, 12, 12)
    fine = (np.arange(12 * 16) + 0.5) / 16
    xs, ys = np.meshgrid(fine, fine)
    touched = np.zeros((12, 12), bool)
    for tri in tris:
        inside = _point_in_triangle(np.stack([xs, ys]), tri)
        np.logical_or.at(touched, (ys[inside].astype(int), xs[inside].astype(int)), True)
    assert np.all(raster.covered[touched])
    rows, cols = np.nonzero(raster.covered)
    sample = np.einsum("nk,nkc->nc", raster.barycentric[rows, cols], tris[raster.triangle[rows, cols]])
    assert np.all(raster.barycentric[rows, cols] >= -1e-12)
    np.testing.assert_allclose(raster.barycentric[rows, cols].sum(-1), 1.0)
    centre = np.stack([cols + 0.5, rows + 0.5], axis=-1)
    assert np.all(np.abs(sample - centre).max(axis=-1) <= 0.5 + 1e-9)  # the sample is inside the texel
    np.testing.assert_allclose(np.linalg.norm(sample - centre, axis=-1), raster.distance[rows, cols], atol=1e-9)
    inside = raster.centre_inside[rows, cols]
    assert np.all(raster.distance[rows, cols][inside] == 0)


def test_a_sliver_thinner_than_a_texel_still_gets_texels():
    sliver = np.array([[[0.2, 0.5], [9.8, 0.52], [0.2, 0.51]]])
    raster = rasterize(sliver, 10, 2)
    assert raster.covered[0].all() and not raster.covered[1].any()
    assert not raster.centre_inside.any()


def test_degenerate_and_non_finite_triangles_are_skipped():
    tris = np.array([[[1, 1], [3, 3], [5, 5]], [[np.nan, 0], [1, 1], [2, 0]]], float)
    assert not rasterize(tris, 8, 8).covered.any()


def test_centre_overlap_detects_a_duplicated_layout_not_shared_edges():
    square = np.array([[[0, 0], [8, 0], [8, 8]], [[0, 0], [8, 8], [0, 8]]], float)
    assert centre_overlap_count(square, 8, 8).max() == 1  # the diagonal passes through texel centres
    assert (centre_overlap_count(np.concatenate([square, square + 0.25]), 8, 8) > 1).mean() > 0.8


def test_dilate_copies_neighbours_never_averages():
    valid = np.zeros((5, 5), bool)
    valid[2, 1], valid[2, 3] = True, True
    values = {"id": np.zeros((5, 5))}
    values["id"][2, 1], values["id"][2, 3] = 7, 9
    out, reached = dilate(values, valid, 1)
    assert reached[1:4, 0:5].all() and not reached[0].any()
    assert set(np.unique(out["id"][reached])) <= {7.0, 9.0}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 40), st.integers(1, 40)), min_size=1, max_size=25))
def test_shelf_pack_never_overlaps_and_keeps_borders(sizes):
    positions, width, height = shelf_pack(sizes, border=1)
    occupied = np.zeros((height, width), np.int64)
    for (x, y), (w, h) in zip(positions, sizes):
        assert x >= 1 and y >= 1 and x + w + 1 <= width and y + h + 1 <= height
        occupied[y - 1:y + h + 1, x - 1:x + w + 1] += 1
    assert occupied.max() == 1


def test_shelf_pack_refuses_an_absurd_atlas():
    with pytest.raises(ValueError, match="max side"):
        shelf_pack([(20000, 10)], max_side=16384)


def test_smoothing_the_irradiance_lowers_noise_and_keeps_objects_and_creases_apart():
    """A 10 x 10 atlas: object 1 is a floor (top half, normal +Z) meeting a wall (rows 5-9, normal +X) at a crease;
    object 2 sits beside it in the atlas. Noisy values per part: smoothing lowers the noise and never mixes parts."""
    from sg_lightfield.bake_directory.texel_maps import CHANNEL, TEXEL_CHANNELS, smooth_over_texels

    atlas = np.zeros((10, 10, len(TEXEL_CHANNELS)), np.float32)
    rows, cols = np.mgrid[0:10, 0:10]
    atlas[..., CHANNEL["P.X"]], atlas[..., CHANNEL["P.Y"]] = 0.1 * cols, 0.1 * rows
    atlas[..., CHANNEL["Ng.Z"]] = np.where(rows < 5, 1.0, 0.0)
    atlas[..., CHANNEL["Ng.X"]] = np.where(rows < 5, 0.0, 1.0)
    atlas[..., CHANNEL["object_id"]] = np.where(cols < 6, 1, 2)
    atlas[..., CHANNEL["texel_size"]] = 0.1
    texels = np.stack([rows.ravel(), cols.ravel()], -1)
    part = np.where(cols >= 6, 2, np.where(rows < 5, 0, 1)).ravel()
    truth = np.array([1.0, 4.0, 9.0])[part][:, None] * np.ones(3)
    noisy = truth * (1 + 0.2 * np.random.default_rng(0).standard_normal(truth.shape))
    smoothed = smooth_over_texels(atlas, texels, noisy)
    for k in range(3):
        mine = part == k
        assert np.abs(smoothed[mine] - truth[mine]).std() < 0.75 * np.abs(noisy[mine] - truth[mine]).std()
        # no part is pulled towards another, even at the borders (a 2.25x or 9x brighter part next to it)
        assert np.abs(smoothed[mine] / truth[mine] - 1).max() <= np.abs(noisy[mine] / truth[mine] - 1).max()
    flat = np.ones_like(truth)
    np.testing.assert_allclose(smooth_over_texels(atlas, texels, flat), flat)  # weights are normalised
