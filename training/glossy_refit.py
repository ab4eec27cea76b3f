"""Refit each texel's SG amplitudes through the node group's glossy closed form (numpy; docs/design-additions.md §5).

The CNN fits the light field in log space: it keeps 86-96 % of the rendered energy (Jensen's bias on noisy renders)
and weighs dim and bright pixels alike. What a viewer sees is the node group's glossy, sg_math.sg_glossy of each
SG, and that is linear in the amplitudes. So, with the CNN's axes and sharpness kept, the amplitudes a >= 0 of a
texel minimise, per colour channel,

    sum_v | sum_k a_k glossy_k(v) - integral L(l) f(l, v) (n.l) dl |^2  +  ridge sum_k W_k (a_k - a_cnn,k)^2

over REFIT_VIEW_COSINES x REFIT_VIEW_AZIMUTHS view directions on the texel's hemisphere: glossy_k the closed form of
SG k with unit amplitude, f the exact GGX BRDF of the texel's roughness (Schlick Fresnel with F0 = 1: the material's
colour scales both sides alike), L the rendered light field (each pixel constant over its solid angle:
pixel_integrated_weights), W_k SG k's own weight D_kk, at least REFIT_RIDGE_FLOOR of the texel's largest (a lobe
below the horizon, which the views hardly see, went from 1 to 1317 on the demo spheres without that floor). The
closed form's own errors (its Laplace approximation, the horizon) are fitted away with the light field's. The ridge
keeps amplitudes near the CNN's where the views cannot tell lobes apart: without it, or with few views, lobes seen
only at untried views blow up (measured on held-out views: error 40x at roughness 0.2).
"""
from __future__ import annotations

import numpy as np

from ..bake_directory.bake_plan import REFIT_LOBE_PIXELS, refit_min_roughness  # noqa: F401 (the refits' bound)
from ..shaders.octahedral import pixel_directions, pixel_solid_angles
from ..shaders.sg_math import (ggx_alpha, ggx_brdf_cos_white, midpoint_parameters, orthonormal_tangents,
                             sg_glossy, sg_sum_eval, unit_midpoint)

REFIT_VIEW_COSINES = tuple(np.linspace(0.1, 1.0, 10))  # n.v of the fitted views
REFIT_VIEW_AZIMUTHS = 12
HELD_OUT_VIEW_COSINES = (0.15, 0.35, 0.6, 0.85, 1.0)  # the views the reported error uses (never fitted)
HELD_OUT_VIEW_AZIMUTHS = 7
REFIT_RIDGE = 1.0  # times each SG's own weight (see REFIT_RIDGE_FLOOR), towards the CNN's amplitude
REFIT_RIDGE_FLOOR = 0.01  # the pull is at least this share of the texel's largest: lobes the views hardly see stay put
REFIT_SWEEPS = 200  # projected coordinate-descent sweeps, warm-started from the CNN's amplitudes
REFIT_BATCH = 32  # texels per vectorised step
ENCODING_SPLIT_BATCH = 8  # texels per step of encoding_error_split (memory: V x (8 R)^2 per texel)
ERROR_TEXELS_PER_MATERIAL = 128  # texels (evenly picked) the reported error of a material uses
UNIT_F0 = np.ones(1)


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
    light field (T, R, R, C), each pixel's radiance constant over its solid angle (pixel_integrated_weights)."""
    t, resolution, _, channels = images.shape
    weights = pixel_integrated_weights(normals, views, roughness, resolution)
    return np.einsum("tvp,tpc->tvc", weights, np.asarray(images, np.float64).reshape(t, -1, channels))


LOBE_FINE_PIXELS = 2.0  # fine pixels across the GGX lobe in pixel_integrated_weights
MAX_SUPERSAMPLING = 8  # fine pixels per light-field pixel side, at most
WINDOW_PIXELS = 2.0  # light-field pixels (and lobe widths) about the mirror direction that are integrated finely
WINDOW_BATCH = 1 << 22  # fine directions per step of the window's integration (memory: a few hundred MB)


def lobe_width_in_pixels(roughness, resolution: int) -> np.ndarray:
    """Width of the GGX lobe (about alpha = roughness^2 radians) in light-field pixels (about sqrt(4 pi) / R)."""
    return np.asarray(ggx_alpha(np.asarray(roughness, np.float64))) * resolution / np.sqrt(4 * np.pi)


def lobe_supersampling(roughness, resolution: int) -> np.ndarray:
    """Fine pixels per light-field pixel side that put LOBE_FINE_PIXELS across the lobe: 1 where it already spans
    that many, up to MAX_SUPERSAMPLING."""
    wanted = np.ceil(LOBE_FINE_PIXELS / np.maximum(lobe_width_in_pixels(roughness, resolution), 1e-6))
    return np.clip(wanted, 1, MAX_SUPERSAMPLING).astype(np.int64)


def pixel_integrated_weights(normals: np.ndarray, views: np.ndarray, roughness: np.ndarray,
                             resolution: int) -> np.ndarray:
    """(T, V, R^2) weights w with sum_p w_p L_p the GGX reflection (F0 = 1) towards each view of a light field
    constant over each pixel: w_p the BRDF times n.l integrated over pixel p. Pixel-centre quadrature aliases once
    the lobe spans a pixel or two (the refits then fit where the centres happen to fall), so pixels within
    WINDOW_PIXELS pixels and lobe widths of the mirror direction are integrated on a grid lobe_supersampling times
    finer; beyond, the BRDF's tail is smooth over a pixel and its centre is used (the window changes the weights
    by ~2e-3 of their sum, tests/test_glossy_refit.py). In float32, twice as fast: its rounding is far below the
    quadrature's error."""
    dtype = np.float32
    normals, views = np.asarray(normals, dtype), np.asarray(views, dtype)
    t = len(views)
    rough = np.broadcast_to(np.asarray(roughness, dtype), (t,))
    directions = pixel_directions(resolution, dtype).reshape(-1, 3)
    solid_angles = pixel_solid_angles(resolution).reshape(-1)
    weights = ggx_brdf_cos_white(directions[None, None], views[:, :, None], normals[:, None, None],
                                 rough[:, None, None]) * solid_angles.astype(dtype)
    supersampling = lobe_supersampling(rough, resolution)
    if supersampling.max() == 1:
        return weights
    pixel_angle = np.sqrt(solid_angles.max())
    mirror = 2 * np.einsum("tk,tvk->tv", normals, views)[..., None] * normals[:, None] - views
    reach = WINDOW_PIXELS * (pixel_angle + 2 * ggx_alpha(rough.astype(np.float64)))  # reflected lobe: ~2 alpha
    window = np.cos(np.minimum(reach, np.pi))
    for factor in np.unique(supersampling[supersampling > 1]):
        texels = np.flatnonzero(supersampling == factor)
        fine = pixel_directions(resolution * factor, dtype).reshape(resolution, factor, resolution, factor, 3)
        fine = fine.transpose(0, 2, 1, 3, 4).reshape(-1, factor * factor, 3)
        fine_angles = pixel_solid_angles(resolution * factor).reshape(resolution, factor, resolution, factor)
        fine_angles = fine_angles.transpose(0, 2, 1, 3).reshape(-1, factor * factor).astype(dtype)
        near = np.einsum("pk,tvk->tvp", directions, mirror[texels]) >= window[texels, None, None]
        tt, vv, pp = np.nonzero(near)
        tt = texels[tt]
        step = max(WINDOW_BATCH // (factor * factor), 1)
        for s in range(0, len(tt), step):
            i, v, p = tt[s:s + step], vv[s:s + step], pp[s:s + step]
            fine_weights = ggx_brdf_cos_white(fine[p], views[i, v][:, None], normals[i][:, None], rough[i][:, None])
            weights[i, v, p] = (fine_weights * fine_angles[p]).sum(axis=1)
    return weights


def reflected_radiance_of_pixels(radiance: np.ndarray, normals: np.ndarray, views: np.ndarray, roughness: np.ndarray,
                                 resolution: int) -> np.ndarray:
    """(T, V, C) GGX reflection (F0 = 1) of radiance (T, P, C) given at the P = resolution^2 octahedral pixel
    centres: the exact BRDF summed over the centres times their solid angles (encoding_error_split's whole-sphere
    fine grid; the refits use pixel_integrated_weights)."""
    directions = pixel_directions(resolution).reshape(-1, 3)
    weighted = ggx_brdf_cos_white(directions[None, None], views[:, :, None], np.asarray(normals)[:, None, None],
                                  np.asarray(roughness, np.float64)[:, None, None])
    weighted *= pixel_solid_angles(resolution).reshape(1, 1, -1)
    return np.einsum("tvp,tpc->tvc", weighted, radiance)


ENCODING_SPLIT_SUPERSAMPLING = 8  # fine pixels per light-field pixel side: resolves roughness 0.2 at R = 16


def encoding_error_split(images, normals, axis, sharpness, amplitude, roughness,
                         supersampling: int = ENCODING_SPLIT_SUPERSAMPLING) -> dict:
    """Where the reflected-radiance error of a texel's SGs comes from, over held-out views (relative RMSE against
    the exact GGX reflection of the light field, each light-field pixel constant over its solid angle):
      fit          the SGs themselves, reflected exactly (quadrature on a grid `supersampling` times finer);
      closed_form  the node group's closed form against that exact reflection of the same SGs;
      total        the closed form against the light field's reflection (what shaded_error measures, on the
                   whole sphere's fine grid instead of pixel_integrated_weights' window).
    The fit and closed-form parts add up to at most the total's error (triangle inequality), not exactly."""
    t, resolution, _, channels = images.shape
    fine = resolution * supersampling
    directions = pixel_directions(fine).reshape(-1, 3)
    rough = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    axis, sharpness, amplitude = (np.asarray(x, np.float64) for x in (axis, sharpness, amplitude))
    sums = dict.fromkeys(("fit", "closed_form", "total", "norm"), 0.0)
    for start in range(0, t, ENCODING_SPLIT_BATCH):
        i = np.arange(start, min(start + ENCODING_SPLIT_BATCH, t))
        views = hemisphere_views(normals[i], HELD_OUT_VIEW_COSINES, HELD_OUT_VIEW_AZIMUTHS)
        constant = np.asarray(images[i], np.float64).repeat(supersampling, 1).repeat(supersampling, 2)
        target = reflected_radiance_of_pixels(constant.reshape(len(i), -1, channels), normals[i], views, rough[i], fine)
        radiance = sg_sum_eval(directions[None], axis[i][:, None], sharpness[i][:, None], amplitude[i][:, None])
        sgs = reflected_radiance_of_pixels(radiance, normals[i], views, rough[i], fine)
        closed = np.einsum("tvn,tnc->tvc", closed_form_responses(axis[i], sharpness[i], normals[i], views, rough[i]),
                           amplitude[i])
        sums["fit"] += float(((sgs - target) ** 2).sum())
        sums["closed_form"] += float(((closed - sgs) ** 2).sum())
        sums["total"] += float(((closed - target) ** 2).sum())
        sums["norm"] += float((target ** 2).sum())
    norm = max(sums.pop("norm"), 1e-300)
    return {k: float(np.sqrt(v / norm)) for k, v in sums.items()}


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
    """A generator's return value, what it yields (its progress) dropped."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def refit_amplitudes(*args, **kwargs) -> np.ndarray:
    """refit_steps run to the end."""
    return run_to_end(refit_steps(*args, **kwargs))


def fitted_view_targets(images: np.ndarray, normals: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """(T, V, C) the GGX reflection of each texel's light field towards its fitted views (hemisphere_views): the
    target both refits fit, computed once for both (it is most of their time on the CPU)."""
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (len(images),))
    parts = [reflected_radiance(images[s:s + REFIT_BATCH], normals[s:s + REFIT_BATCH],
                                hemisphere_views(normals[s:s + REFIT_BATCH]), roughness[s:s + REFIT_BATCH])
             for s in range(0, len(images), REFIT_BATCH)]
    return np.concatenate(parts) if parts else np.zeros((0, len(REFIT_VIEW_COSINES) * REFIT_VIEW_AZIMUTHS,
                                                         np.shape(images)[-1]))


def refit_steps(images: np.ndarray, normals: np.ndarray, axis: np.ndarray, sharpness: np.ndarray,
                amplitude: np.ndarray, roughness: np.ndarray, lobe_counts: np.ndarray | None = None,
                ridge: float = REFIT_RIDGE, targets: np.ndarray | None = None):
    """Amplitudes (T, N, C) >= 0 fitted through the closed form (module docstring), from rendered light fields
    images (T, R, R, C), normals (T, 3), the CNN's axis (T, N, 3), sharpness (T, N), amplitude (T, N, C) and each
    texel's roughness (T,). SGs past a texel's lobe count (T,) stay zero. `targets`: fitted_view_targets of these
    texels where already computed. A generator: yields the fraction of texels done after each batch, returns the
    amplitudes."""
    t, n = np.shape(sharpness)
    result = np.array(amplitude, np.float64)
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    used = np.ones((t, n), bool) if lobe_counts is None else np.arange(n)[None] < np.asarray(lobe_counts)[:, None]
    for start in range(0, t, REFIT_BATCH):
        index = np.arange(start, min(start + REFIT_BATCH, t))
        views = hemisphere_views(normals[index])
        target = reflected_radiance(images[index], normals[index], views, roughness[index]) if targets is None \
            else np.asarray(targets[index], np.float64)
        responses = closed_form_responses(axis[index], sharpness[index], normals[index], views, roughness[index])
        responses *= used[index][:, None, :]
        gram = np.einsum("bvn,bvm->bnm", responses, responses)
        rhs = np.einsum("bvn,bvc->bnc", responses, target)
        own = np.einsum("bnn->bn", gram)
        pull = ridge * np.maximum(own, REFIT_RIDGE_FLOOR * own.max(axis=1, keepdims=True))
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
    error = norm = 0.0
    for light_field, normal, views, midpoint_roughness, blended in between_texel_batches(
            images, normals, axis, sharpness, amplitude, roughness, a, b, REFIT_BATCH):
        target = reflected_radiance(light_field, normal, views, midpoint_roughness)
        responses = closed_form_responses(blended[0], blended[1], normal, views, midpoint_roughness)
        shaded = np.einsum("bvn,bnc->bvc", responses, blended[2])
        error += float(((shaded - target) ** 2).sum())
        norm += float((target ** 2).sum())
    return float(np.sqrt(error / max(norm, 1e-300)))


def between_texel_batches(images, normals, axis, sharpness, amplitude, roughness, a, b, batch: int):
    """interpolated_shaded_error's inputs, `batch` pairs at a time: the two light fields' mean, the renormalised
    mean normal, the held-out views about it, the mean roughness and the blended SGs (axis, sharpness, amplitude)."""
    rough = np.broadcast_to(np.asarray(roughness, np.float64), (len(images),))
    axis, sharpness, amplitude = (np.asarray(x, np.float64) for x in (axis, sharpness, amplitude))
    for start in range(0, len(a), batch):
        i, j = a[start:start + batch], b[start:start + batch]
        normal = unit_midpoint(normals[i], normals[j])
        yield (0.5 * (np.asarray(images[i], np.float64) + images[j]), normal,
               hemisphere_views(normal, HELD_OUT_VIEW_COSINES, HELD_OUT_VIEW_AZIMUTHS), 0.5 * (rough[i] + rough[j]),
               midpoint_parameters(axis, sharpness, amplitude, i, j))
