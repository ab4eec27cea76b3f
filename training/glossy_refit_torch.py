"""The refits' target, the amplitude refit and the guards' errors in torch, on the training device: twins of
glossy_refit's numpy (whose module docstring says what is fitted; tests/test_glossy_refit_torch.py holds each pair
equal).

The target, the GGX reflection of each texel's light field towards 120 views (pixel_integrated_weights), is most of
both refits' time on the CPU; on a GPU it and the amplitude refit's projected coordinate descent run on the device,
a whole batch of texels at once. Same float precision as the numpy: float32 weights, float64 for the closed form's
responses and the solve.
"""
from __future__ import annotations

import numpy as np
import torch

from ..shaders.octahedral import pixel_directions, pixel_solid_angles
from ..shaders.sg_math import ggx_alpha as ggx_alpha_numpy
from . import sg_torch
from .glossy_refit import (REFIT_RIDGE, REFIT_RIDGE_FLOOR, REFIT_SWEEPS, WINDOW_BATCH, WINDOW_PIXELS,
                           hemisphere_views, lobe_supersampling, run_to_end)

DEVICE_BATCH = {"cpu": 32, "cuda": 1024}  # texels per step (memory on CUDA: ~0.5 GB of weights at R = 32)


def device_batch(device) -> int:
    return DEVICE_BATCH.get(torch.device(device).type, 32)


def _tensor(x, device, dtype=torch.float32):
    return torch.tensor(np.asarray(x), dtype=dtype, device=device)  # a copy: numpy views may be read-only


def pixel_integrated_weights(normals, views, roughness, resolution: int, device="cpu") -> torch.Tensor:
    """(T, V, R^2) float32 on `device`: glossy_refit.pixel_integrated_weights (the same window and fine grids)."""
    normals, views = _tensor(normals, device), _tensor(views, device)
    t = len(views)
    rough_numpy = np.broadcast_to(np.asarray(roughness, np.float32), (t,))
    rough = _tensor(rough_numpy, device)
    directions = _tensor(pixel_directions(resolution, np.float32).reshape(-1, 3), device)
    solid_numpy = pixel_solid_angles(resolution).reshape(-1)
    solid_angles = _tensor(solid_numpy, device)
    weights = sg_torch.ggx_brdf_cos_white(directions[None, None], views[:, :, None], normals[:, None, None],
                                          rough[:, None, None]) * solid_angles
    supersampling = lobe_supersampling(rough_numpy, resolution)
    if supersampling.max() == 1:
        return weights
    pixel_angle = np.sqrt(solid_numpy.max())
    mirror = 2 * (normals[:, None] * views).sum(-1, keepdim=True) * normals[:, None] - views
    reach = WINDOW_PIXELS * (pixel_angle + 2 * ggx_alpha_numpy(rough_numpy.astype(np.float64)))
    window = _tensor(np.cos(np.minimum(reach, np.pi)), device)
    for factor in np.unique(supersampling[supersampling > 1]):
        texels = torch.as_tensor(np.flatnonzero(supersampling == factor), device=device)
        fine = pixel_directions(resolution * factor, np.float32).reshape(resolution, factor, resolution, factor, 3)
        fine = _tensor(fine.transpose(0, 2, 1, 3, 4).reshape(-1, factor * factor, 3), device)
        fine_angles = pixel_solid_angles(resolution * factor).reshape(resolution, factor, resolution, factor)
        fine_angles = _tensor(fine_angles.transpose(0, 2, 1, 3).reshape(-1, factor * factor), device)
        near = torch.einsum("pk,tvk->tvp", directions, mirror[texels]) >= window[texels, None, None]
        tt, vv, pp = torch.nonzero(near, as_tuple=True)
        tt = texels[tt]
        step = max(WINDOW_BATCH // int(factor * factor), 1)
        for s in range(0, len(tt), step):
            i, v, p = tt[s:s + step], vv[s:s + step], pp[s:s + step]
            fine_weights = sg_torch.ggx_brdf_cos_white(fine[p], views[i, v][:, None], normals[i][:, None],
                                                       rough[i][:, None])
            weights[i, v, p] = (fine_weights * fine_angles[p]).sum(dim=1)
    return weights


def reflected_radiance(images, normals, views, roughness, device="cpu") -> torch.Tensor:
    """(T, V, C) float32 on `device`: glossy_refit.reflected_radiance."""
    images = _tensor(images, device)
    t, resolution, _, channels = images.shape
    weights = pixel_integrated_weights(normals, views, roughness, resolution, device)
    return torch.einsum("tvp,tpc->tvc", weights, images.reshape(t, -1, channels))


def reflected_radiance_batched(images, normals, views, roughness, device="cpu") -> torch.Tensor:
    """reflected_radiance over any number of texels, `device_batch` texels at a time (the weights' memory)."""
    batch = device_batch(device)
    parts = [reflected_radiance(images[s:s + batch], normals[s:s + batch], views[s:s + batch],
                                np.broadcast_to(np.asarray(roughness), (len(images),))[s:s + batch], device)
             for s in range(0, len(images), batch)]
    return torch.cat(parts) if parts else torch.zeros((0, np.shape(views)[1], np.shape(images)[-1]), device=device)


def closed_form_responses(axis, sharpness, normals, views, roughness) -> torch.Tensor:
    """(T, V, N) float64: glossy_refit.closed_form_responses (sg_glossy with unit amplitude, F0 = 1)."""
    unit = torch.ones(sharpness.shape + (1,), dtype=sharpness.dtype, device=sharpness.device)[:, None]
    f0 = torch.ones(1, dtype=sharpness.dtype, device=sharpness.device)
    return sg_torch.sg_glossy(axis[:, None], sharpness[:, None], unit, normals[:, None, None], views[:, :, None],
                              roughness[:, None, None], f0)[..., 0]


def nonnegative_quadratic_minimum(gram, rhs, start, sweeps: int = REFIT_SWEEPS) -> torch.Tensor:
    """glossy_refit.nonnegative_quadratic_minimum: projected Gauss-Seidel over a batch (B, N, N), (B, N, C)."""
    x = start.clamp_min(0).clone()
    diagonal = torch.diagonal(gram, dim1=1, dim2=2)
    usable = diagonal > 1e-9 * diagonal.amax(dim=1, keepdim=True).clamp_min(1e-300)
    inverse = torch.where(usable, 1.0 / torch.where(usable, diagonal, torch.ones_like(diagonal)), 0.0)
    for _ in range(sweeps):
        for n in range(gram.shape[1]):
            residual = torch.einsum("bm,bmc->bc", gram[:, n], x) - rhs[:, n]
            x[:, n] = (x[:, n] - residual * inverse[:, n, None]).clamp_min(0)
    return x


def fitted_view_targets(images, normals, roughness, device="cpu") -> np.ndarray:
    """glossy_refit.fitted_view_targets on the training device (numpy on the CPU), as float64 numpy."""
    if torch.device(device).type == "cpu":
        from .glossy_refit import fitted_view_targets as numpy_targets

        return numpy_targets(images, normals, roughness)
    return reflected_radiance_batched(images, normals, hemisphere_views(normals), roughness,
                                      device).double().cpu().numpy()


def refit_steps(images, normals, axis, sharpness, amplitude, roughness, lobe_counts=None, ridge: float = REFIT_RIDGE,
                device="cpu", targets=None):
    """glossy_refit.refit_steps on `device`, `device_batch` texels a step: a generator of the fraction done that
    returns the amplitudes (T, N, C) as float32 numpy."""
    t, n = np.shape(sharpness)
    result = np.array(amplitude, np.float64)
    roughness = np.broadcast_to(np.asarray(roughness, np.float64), (t,))
    used = np.ones((t, n), bool) if lobe_counts is None else np.arange(n)[None] < np.asarray(lobe_counts)[:, None]
    batch = device_batch(device)
    for start in range(0, t, batch):
        index = np.arange(start, min(start + batch, t))
        views = hemisphere_views(normals[index])
        target = reflected_radiance(images[index], normals[index], views, roughness[index], device).double() \
            if targets is None else _tensor(targets[index], device, torch.float64)
        responses = closed_form_responses(*(_tensor(x, device, torch.float64) for x in (
            axis[index], sharpness[index], normals[index], views, roughness[index])))
        responses = responses * _tensor(used[index], device, torch.float64)[:, None, :]
        gram = torch.einsum("bvn,bvm->bnm", responses, responses)
        rhs = torch.einsum("bvn,bvc->bnc", responses, target)
        own = torch.diagonal(gram, dim1=1, dim2=2)
        pull = ridge * torch.maximum(own, REFIT_RIDGE_FLOOR * own.amax(dim=1, keepdim=True))
        start_amplitude = _tensor(result[index], device, torch.float64)
        gram = gram + torch.diag_embed(pull)
        rhs = rhs + pull[..., None] * start_amplitude
        result[index] = nonnegative_quadratic_minimum(gram, rhs, start_amplitude).cpu().numpy()
        yield index[-1] / max(t - 1, 1)
    return result.astype(np.float32)


def refit_amplitudes(*args, **kwargs) -> np.ndarray:
    """refit_steps run to the end."""
    return run_to_end(refit_steps(*args, **kwargs))


def amplitude_refit_steps(*args, device="cpu", **kwargs):
    """The amplitude refit on the training device: glossy_refit's numpy on the CPU (2.5x faster there than this
    torch twin at 2 threads), the torch twin on a GPU."""
    if torch.device(device).type == "cpu":
        from .glossy_refit import refit_steps as numpy_refit_steps

        return numpy_refit_steps(*args, **kwargs)
    return refit_steps(*args, device=device, **kwargs)


def interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, a, b, device="cpu") -> float:
    """glossy_refit.interpolated_shaded_error on `device` (the refits' guards, measured before and after each
    refit: on a GPU machine their numpy took most of the refits' time)."""
    from .glossy_refit import between_texel_batches

    error = norm = 0.0
    for light_field, normal, views, midpoint_roughness, blended in between_texel_batches(
            images, normals, axis, sharpness, amplitude, roughness, a, b, device_batch(device)):
        target = reflected_radiance(light_field, normal, views, midpoint_roughness, device).double()
        responses = closed_form_responses(*(_tensor(x, device, torch.float64) for x in (
            blended[0], blended[1], normal, views, midpoint_roughness)))
        shaded = torch.einsum("bvn,bnc->bvc", responses, _tensor(blended[2], device, torch.float64))
        error += float(((shaded - target) ** 2).sum())
        norm += float((target ** 2).sum())
    return float(np.sqrt(error / max(norm, 1e-300)))


def shaded_error(images, normals, axis, sharpness, amplitude, roughness, device="cpu") -> float:
    """glossy_refit.shaded_error on `device`."""
    each = np.arange(len(images))
    return interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, each, each, device)


def error_functions(device):
    """(shaded_error, interpolated_shaded_error) for the training device: glossy_refit's numpy on the CPU, the
    torch twins on a GPU."""
    if torch.device(device).type == "cpu":
        from . import glossy_refit

        return glossy_refit.shaded_error, glossy_refit.interpolated_shaded_error
    return (lambda *args: shaded_error(*args, device=device),
            lambda *args: interpolated_shaded_error(*args, device=device))
