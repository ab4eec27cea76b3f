"""Refit each texel's SG amplitudes through the node group's glossy closed form (numpy; docs/design-additions.md §5).

The CNN fits the light field in log space: it keeps 86-96 % of the rendered energy (Jensen's bias on noisy renders)
and weighs dim and bright pixels alike. What a viewer sees is the node group's glossy, sg_math.sg_glossy of each
SG, and that is linear in the amplitudes. So, with the CNN's axes and sharpness kept, the amplitudes a >= 0 of a
texel minimise, per colour channel,

    sum_v | sum_k a_k glossy_k(v) - integral L(l) f(l, v) (n.l) dl |^2  +  ridge sum_k D_kk (a_k - a_cnn,k)^2

over REFIT_VIEW_COSINES x REFIT_VIEW_AZIMUTHS view directions on the texel's hemisphere: glossy_k the closed form of
SG k with unit amplitude, f the exact GGX BRDF of the texel's roughness (Schlick Fresnel with F0 = 1: the
material's colour scales both sides alike), L the rendered light field (constant over each pixel, as its box filter
renders it, so f (n.l) is integrated over each pixel: reflected_radiance), D_kk SG k's own weight. The closed form's own errors (its Laplace approximation, the horizon) are fitted away with the light
field's. The ridge keeps amplitudes near the CNN's where the views cannot tell lobes apart: without it, or with
few views, lobes seen only at untried views blow up (measured on held-out views: error 40x at roughness 0.2).
"""
from __future__ import annotations

import functools

import numpy as np

from shaders.octahedral import pixel_directions, pixel_solid_angles
from shaders.sg_math import ggx_brdf_cos, midpoint_parameters, orthonormal_tangents, sg_glossy, unit_midpoint

REFIT_VIEW_COSINES = tuple(np.linspace(0.1, 1.0, 10))  # n.v of the fitted views
REFIT_VIEW_AZIMUTHS = 12
HELD_OUT_VIEW_COSINES = (0.15, 0.35, 0.6, 0.85, 1.0)  # the views the reported error uses (never fitted)
HELD_OUT_VIEW_AZIMUTHS = 7
REFIT_RIDGE = 1.0  # times each SG's own weight, towards the CNN's amplitude
REFIT_SWEEPS = 200  # projected coordinate-descent sweeps, warm-started from the CNN's amplitudes
REFIT_BATCH = 32  # texels per vectorised step
REFIT_LOBE_PIXELS = 0.5  # refit only where the GGX lobe spans at least this many light-field pixels
ERROR_TEXELS_PER_MATERIAL = 128  # texels (evenly picked) the reported error of a material uses
UNIT_F0 = np.ones(1)
TARGET_LOBE_SUBPIXELS = 3.5  # the target splits pixels until the GGX lobe spans this many sub-pixels
TARGET_MAX_SUBDIVISION = 8  # sub-pixels per pixel side at most
TARGET_WINDOW_PIXELS = 81  # pixels nearest the mirror direction that are split; the rest keep their centre
TARGET_CHUNK_SAMPLES = 1 << 20  # sub-directions evaluated per vectorised step (~0.3 GB of temporaries)


def ggx_lobe_pixels(roughness, resolution: int):
    """Light-field pixels (about sqrt(4 pi) / R radians each) the GGX lobe (about alpha = roughness^2 radians)
    spans."""
    return np.square(roughness) * resolution / np.sqrt(4 * np.pi)


def refit_min_roughness(resolution: int, lobe_pixels: float = REFIT_LOBE_PIXELS) -> float:
    """The least roughness the refit is used at: the GGX lobe spans `lobe_pixels` light-field pixels. This gives
    0.24 at R = 32, 0.33 at R = 16. Sharper lobes would need more than TARGET_MAX_SUBDIVISION sub-pixels per side
    for an accurate target (target_subdivision). The train stage keeps a material's refit only where it lowers the
    held-out error."""
    return float(np.sqrt(lobe_pixels * np.sqrt(4 * np.pi) / resolution))


def target_subdivision(roughness: float, resolution: int) -> int:
    """Sub-pixels per pixel side the target integrates f (n.l) over, so the lobe spans TARGET_LOBE_SUBPIXELS of
    them: 2 at roughness 0.5, 3 at 0.4, 5 at 0.3 (R = 32). Measured against 8 x 8 on Production spheres texels, the
    target's error is then 0.3-0.5 %; at pixel centres alone it is 1.7 % at roughness 0.5, 6 % at 0.4, 22 % at 0.3
    and 61 % at 0.2."""
    lobe = float(ggx_lobe_pixels(max(float(roughness), 1e-3), resolution))
    return int(np.clip(np.ceil(TARGET_LOBE_SUBPIXELS / lobe - 1e-9), 1, TARGET_MAX_SUBDIVISION))


@functools.lru_cache(maxsize=8)
def _sub_pixels(resolution: int, subdivision: int):
    """(P, S^2, 3) sub-pixel centre directions of each light-field pixel and (P, S^2) their exact solid angles
    (they sum to the pixel's)."""
    r, s = resolution, subdivision
    directions = pixel_directions(r * s).reshape(r, s, r, s, 3).transpose(0, 2, 1, 3, 4).reshape(r * r, s * s, 3)
    solid_angles = pixel_solid_angles(r * s).reshape(r, s, r, s).transpose(0, 2, 1, 3).reshape(r * r, s * s)
    return directions, solid_angles


def hemisphere_views(normals: np.ndarray, cosines=REFIT_VIEW_COSINES, azimuths: int = REFIT_VIEW_AZIMUTHS):
    """(T, V, 3) unit view directions about each normal: every n.v of `cosines` at `azimuths` azimuths (rotated
    by n.v radians per ring, so rings do not line up)."""
    normals = np.asarray(normals, np.float64)
    tangent, bitangent = orthonormal_tangents(normals)
    views = []
    for cosine in cosines:
        sine = np.sqrt(max(1.0 - cosine * cosine, 0.0))
        for angle in np.arange(azimuths) * 2 * np.pi / azimuths + cosine:
            views.append(cosine * normals + sine * (np.cos(angle) * tangent + np.sin(angle) * bitangent))
    return np.stack(views, axis=1)


def reflected_radiance(images: np.ndarray, normals: np.ndarray, views: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """(T, V, C) radiance each texel's GGX surface (F0 = 1) reflects towards `views` (T, V, 3) from its rendered
    light field (T, R, R, C), each pixel's radiance constant over its solid angle: the exact BRDF times n.l,
    integrated over each pixel. The TARGET_WINDOW_PIXELS pixels nearest the mirror direction are split into
    target_subdivision(least roughness)^2 sub-pixels; the others, where the lobe is smooth across a pixel, take
    their centre times their solid angle."""
    t, resolution, _, channels = images.shape
    normals = np.asarray(normals, np.float64)
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    light = np.asarray(images, np.float64).reshape(t, -1, channels)
    directions = pixel_directions(resolution).reshape(-1, 3)
    weighted = ggx_brdf_cos(directions[None, None], views[:, :, None], normals[:, None, None],
                            roughness[:, None, None], UNIT_F0)[..., 0]
    weighted *= pixel_solid_angles(resolution).reshape(1, 1, -1)
    result = np.einsum("tvp,tpc->tvc", weighted, light)
    subdivision = target_subdivision(roughness.min(), resolution) if t else 1
    if subdivision == 1:
        return result
    sub_directions, sub_solid_angles = _sub_pixels(resolution, subdivision)
    window = min(TARGET_WINDOW_PIXELS, len(directions))
    views = np.asarray(views, np.float64)
    mirror = 2 * np.einsum("tvx,tx->tv", views, normals)[..., None] * normals[:, None] - views
    nearest = np.argpartition(-np.einsum("tvx,px->tvp", mirror, directions), window - 1, axis=-1)[..., :window]
    rows = np.broadcast_to(np.arange(t)[:, None], views.shape[:2]).reshape(-1)  # the texel of each (texel, view)
    nearest, flat_views = nearest.reshape(len(rows), window), views.reshape(-1, 3)
    flat_result, flat_weighted = result.reshape(-1, channels), weighted.reshape(len(rows), -1)
    step = max(1, TARGET_CHUNK_SAMPLES // (window * subdivision ** 2))
    for start in range(0, len(rows), step):
        chunk = slice(start, start + step)
        near, texel = nearest[chunk], rows[chunk]
        split = ggx_brdf_cos(sub_directions[near], flat_views[chunk, None, None], normals[texel, None, None],
                             roughness[texel, None, None], UNIT_F0)[..., 0]
        integrated = np.einsum("rks,rks->rk", split, sub_solid_angles[near])
        correction = integrated - np.take_along_axis(flat_weighted[chunk], near, axis=-1)
        flat_result[chunk] += np.einsum("rk,rkc->rc", correction, light[texel[:, None], near])
    return result


def closed_form_responses(axis, sharpness, normals, views, roughness) -> np.ndarray:
    """(T, V, N) the node group's glossy (sg_glossy, F0 = 1) of each SG with unit amplitude."""
    unit = np.ones(np.shape(sharpness) + (1,))[:, None]
    return sg_glossy(np.asarray(axis, np.float64)[:, None], np.asarray(sharpness, np.float64)[:, None], unit,
                     np.asarray(normals, np.float64)[:, None, None], views[:, :, None],
                     np.asarray(roughness, np.float64)[:, None, None], UNIT_F0)[..., 0]


def nonnegative_quadratic_minimum(gram: np.ndarray, rhs: np.ndarray, start: np.ndarray,
                                  sweeps: int = REFIT_SWEEPS) -> np.ndarray:
    """argmin_{x >= 0} x.G x - 2 r.x for a batch: gram (B, N, N) symmetric positive semi-definite, rhs and start
    (B, N, C). Projected Gauss-Seidel (coordinate descent), vectorised over the batch and channels; a coordinate
    whose diagonal is below 1e-9 of the largest (an unused SG, or one no view sees: rounding would make its steps
    diverge) keeps its start value."""
    x = np.maximum(np.array(start, np.float64), 0.0)
    diagonal = np.einsum("bnn->bn", gram)
    usable = diagonal > 1e-9 * np.maximum(diagonal.max(axis=1, keepdims=True), 1e-300)
    inverse = np.where(usable, 1.0 / np.where(usable, diagonal, 1.0), 0.0)
    for _ in range(sweeps):
        for n in range(gram.shape[1]):
            residual = np.einsum("bm,bmc->bc", gram[:, n], x) - rhs[:, n]
            x[:, n] = np.maximum(x[:, n] - residual * inverse[:, n, None], 0.0)
    return x


def run_to_end(steps):
    """The return value of a generator that yields progress."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def refit_amplitudes(*args, **kwargs) -> np.ndarray:
    """refit_steps run to the end."""
    return run_to_end(refit_steps(*args, **kwargs))


def target_steps(images: np.ndarray, normals: np.ndarray, roughness: np.ndarray):
    """The refits' target, (T, V, C): reflected_radiance of each texel's light field towards its hemisphere_views.
    Texels are batched in order of roughness, so a batch's subdivision suits its texels. A generator: yields the
    fraction of texels done after each batch, returns the targets."""
    t, channels = len(images), np.shape(images)[-1]
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    targets = np.zeros((t, len(REFIT_VIEW_COSINES) * REFIT_VIEW_AZIMUTHS, channels))
    order = np.argsort(roughness, kind="stable")
    for start in range(0, t, REFIT_BATCH):
        index = order[start:start + REFIT_BATCH]
        targets[index] = reflected_radiance(images[index], normals[index], hemisphere_views(normals[index]),
                                            roughness[index])
        yield min(start + REFIT_BATCH, t) / t
    return targets


def refit_steps(images: np.ndarray, normals: np.ndarray, axis: np.ndarray, sharpness: np.ndarray,
                amplitude: np.ndarray, roughness: np.ndarray, lobe_counts: np.ndarray | None = None,
                ridge: float = REFIT_RIDGE, targets: np.ndarray | None = None):
    """Amplitudes (T, N, C) >= 0 fitted through the closed form (module docstring), from rendered light fields
    images (T, R, R, C), normals (T, 3), the CNN's axis (T, N, 3), sharpness (T, N), amplitude (T, N, C) and each
    texel's roughness (T,). SGs past a texel's lobe count (T,) stay zero. `targets` are target_steps' (computed
    here when not given). A generator: yields the fraction of texels done after each batch, returns the
    amplitudes."""
    t, n = np.shape(sharpness)
    result = np.array(amplitude, np.float64)
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    used = np.ones((t, n), bool) if lobe_counts is None else np.arange(n)[None] < np.asarray(lobe_counts)[:, None]
    for start in range(0, t, REFIT_BATCH):
        index = np.arange(start, min(start + REFIT_BATCH, t))
        views = hemisphere_views(normals[index])
        target = targets[index] if targets is not None else \
            reflected_radiance(images[index], normals[index], views, roughness[index])
        responses = closed_form_responses(axis[index], sharpness[index], normals[index], views, roughness[index])
        responses *= used[index][:, None, :]
        gram = np.einsum("bvn,bvm->bnm", responses, responses)
        rhs = np.einsum("bvn,bvc->bnc", responses, target)
        pull = ridge * np.einsum("bnn->bn", gram)
        gram[:, np.arange(n), np.arange(n)] += pull
        rhs += pull[..., None] * result[index]
        result[index] = nonnegative_quadratic_minimum(gram, rhs, result[index])
        yield index[-1] / max(t - 1, 1)
    return result.astype(np.float32)


def shaded_error(images, normals, axis, sharpness, amplitude, roughness) -> float:
    """Relative RMSE, over held-out views (HELD_OUT_VIEW_*), between the node group's glossy of the SGs and the
    exact GGX reflection of the rendered light fields: the error a viewer of the baked surface sees, before
    interpolation between texels (interpolated_shaded_error of each texel with itself)."""
    each = np.arange(len(images))
    return interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, each, each)


def atlas_neighbour_pairs(texels: np.ndarray) -> np.ndarray:
    """(P, 2) rows (a, b) of `texels` ((T, 2) atlas [row, col]) that are right or down neighbours in the atlas: the
    texels a bilinear lookup blends."""
    index = {(int(r), int(c)): i for i, (r, c) in enumerate(texels)}
    pairs = [(i, index[(r + dr, c + dc)]) for (r, c), i in index.items() for dr, dc in ((0, 1), (1, 0))
             if (r + dr, c + dc) in index]
    return np.array(pairs, np.int64).reshape(-1, 2)


def interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, a, b) -> float:
    """Relative RMSE, over held-out views, halfway between texels a and b (index arrays): the node group's glossy
    of the blended SGs (midpoint_parameters, as its bilinear lookup gives them) against the exact GGX reflection of
    the two light fields' mean, at the renormalised mean normal. What a viewer sees between texels: SGs fitted
    texel by texel can each be right and still blend into wrong lobes."""
    rough = np.broadcast_to(np.asarray(roughness, np.float64), (len(images),))
    axis, sharpness, amplitude = (np.asarray(x, np.float64) for x in (axis, sharpness, amplitude))
    error = norm = 0.0
    for start in range(0, len(a), REFIT_BATCH):
        i, j = a[start:start + REFIT_BATCH], b[start:start + REFIT_BATCH]
        normal = unit_midpoint(normals[i], normals[j])
        views = hemisphere_views(normal, HELD_OUT_VIEW_COSINES, HELD_OUT_VIEW_AZIMUTHS)
        midpoint_roughness = 0.5 * (rough[i] + rough[j])
        target = reflected_radiance(0.5 * (np.asarray(images[i], np.float64) + images[j]), normal, views,
                                    midpoint_roughness)
        blended_axis, blended_sharpness, blended_amplitude = midpoint_parameters(axis, sharpness, amplitude, i, j)
        responses = closed_form_responses(blended_axis, blended_sharpness, normal, views, midpoint_roughness)
        shaded = np.einsum("bvn,bnc->bvc", responses, blended_amplitude)
        error += float(((shaded - target) ** 2).sum())
        norm += float((target ** 2).sum())
    return float(np.sqrt(error / max(norm, 1e-300)))
