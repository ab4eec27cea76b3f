"""The environment's global SGs (what the node group convolves with each texel's lobe, times W_E).

Two steps, because the two kinds of light in a real HDRI want different losses:
  1. Compact sources are taken out one at a time (`compact_sources`): lamps and the sun however small their share
     of the power first, then bright patches holding 2 % of it, brightest first in each. Each becomes one SG at the
     power-weighted centroid of what stands above its surroundings, with the sharpness of that power's angular
     spread and the amplitude that keeps its power. A log loss barely sees them (a lamp a hundred times brighter
     than the room is a few pixels of log error), yet a glossy floor's reflection of them can hold most of the
     light it reflects.
  2. The rest of the map, with the sources subtracted, is fitted by the light fields' log loss (sg_fit), by
     gradient descent from directions spread evenly over the sphere.

Measured on Blender's shipped interior HDRI (demo:materials' world), glossy reflections of the fitted SGs against
quadrature of the full-resolution map: docs/design-additions.md sections 42 and 44.
"""
from __future__ import annotations

import math

import numpy as np

from ..bake_directory.image_metrics import LUMINANCE
from ..shaders.octahedral import downsample_octahedral, pixel_directions, pixel_solid_angles
from ..shaders.sg_math import SHARPNESS_MAX, SHARPNESS_MIN, sg_integral

ENV_FIT_RESOLUTION = 32  # octahedral; a finer rendered map is averaged down to it
SOURCE_MOST = 4  # compact sources taken out at most
# What a source is, tier by tier: (the least share of the environment's power it holds, the least sharpness of its
# moment-matched SG). First lamps and the sun however small (sharpness 150: about 5 degrees rms), then bright
# patches holding 2 % of the power (a sun behind haze, a window; section 42's rule): the log loss under-fits both.
SOURCE_TIERS = ((0.005, 150.0), (0.02, 0.0))
SOURCE_RADIUS_PIXELS = 2.5  # a source's neighbourhood; its surroundings are the ring out to SURROUND_PIXELS
SURROUND_PIXELS = 4.0
REST_STEPS = 600


def compact_sources(radiance: np.ndarray, most: int = SOURCE_MOST, tiers=SOURCE_TIERS):
    """[(axis (3,), sharpness, amplitude (3,))] for the compact sources of an (R, R, 3) octahedral map, and the map
    with them taken out (clipped at 0). Each tier of `tiers` (SOURCE_TIERS) takes sources brightest first while
    `most` allows: a small lamp comes before a bright window."""
    resolution = radiance.shape[0]
    directions = pixel_directions(resolution).reshape(-1, 3)
    solid = pixel_solid_angles(resolution).reshape(-1)
    rest = np.maximum(np.asarray(radiance, np.float64).reshape(-1, 3), 0.0)
    total = float((rest @ LUMINANCE * solid).sum())
    sources = []
    for min_share, min_sharpness in tiers:
        if total <= 0:
            break
        found, rest = _take_sources(rest, most - len(sources), min_share * total, min_sharpness, directions, solid)
        sources += found
    return sources, np.maximum(rest, 0.0).reshape(radiance.shape)


def _take_sources(rest, most, min_power, min_sharpness, directions, solid):
    """Up to `most` sources of at least `min_power` above their surroundings and `min_sharpness`, brightest first.
    The compact tier (min_sharpness > 0) looks past the peaks it cannot take, a broad one with its surroundings (else
    its flanks, whose excess over a median is one-sided, would look sharp); the patch tier stops at the first peak
    holding too little (section 42's rule, unchanged)."""
    pixel_angle = math.sqrt(4 * math.pi) / math.sqrt(len(rest))
    near_solid_angle = 2 * math.pi * (1 - math.cos(SOURCE_RADIUS_PIXELS * pixel_angle))
    look_past = min_sharpness > 0
    passed = np.zeros(len(rest), bool)
    sources = []
    while len(sources) < most:
        luminance = rest @ LUMINANCE
        index = int(np.argmax(np.where(passed, -1.0, luminance)))
        if passed[index] or luminance[index] * near_solid_angle < min_power:
            break  # the peak's brightness over a cap the neighbourhood's size holds too little: none left
        cosine = directions @ directions[index]
        near = cosine > math.cos(SOURCE_RADIUS_PIXELS * pixel_angle)
        ring = (cosine > math.cos(SURROUND_PIXELS * pixel_angle)) & ~near
        surroundings = np.median(rest[ring], axis=0) if ring.any() else np.zeros(3)
        excess = np.maximum(rest[near] - surroundings, 0.0)
        weight = excess @ LUMINANCE * solid[near]
        if weight.sum() < min_power:
            if not look_past:
                break
            passed |= near
            continue
        axis = (directions[near] * weight[:, None]).sum(axis=0)
        axis /= np.linalg.norm(axis)
        spread = float((weight * (1.0 - directions[near] @ axis)).sum() / weight.sum())
        # moment matching: E[1 - cos] of a sharp SG is 1 / sharpness (the spread taken as at least a twentieth of a
        # pixel's area)
        sharpness = float(np.clip(1.0 / max(spread, 0.05 * pixel_angle ** 2), SHARPNESS_MIN, SHARPNESS_MAX))
        if sharpness < min_sharpness:
            passed |= near | ring
            continue
        lobe = np.exp(sharpness * (directions @ axis - 1.0))
        # the lobe's exact integral (pixel centres would sample a lobe narrower than a pixel at random)
        amplitude = (excess * solid[near, None]).sum(axis=0) / sg_integral(np.array(sharpness), np.ones(1))
        rest = rest - amplitude[None] * lobe[:, None]
        rest[near] = np.maximum(rest[near], 0.0)
        if look_past:
            passed |= near
        sources.append((axis, sharpness, amplitude))
    return sources, rest


def _fit_rest(radiance: np.ndarray, count: int, steps: int, device: str):
    """`count` SGs fitted to an (R, R, 3) map by the light fields' log loss over the whole sphere (sg_fit's
    lightfield_loss with a zero normal), from directions spread evenly over the sphere."""
    import torch

    from ..shaders.quadrature import GOLDEN_ANGLE
    from .sg_fit import LOG_SHARPNESS_MAX, LOG_SHARPNESS_MIN, lightfield_loss

    resolution = radiance.shape[0]
    generator = torch.Generator().manual_seed(0)
    torch_kw = dict(dtype=torch.float64, device=device)
    directions = torch.tensor(pixel_directions(resolution)[None], **torch_kw)
    solid = torch.tensor(pixel_solid_angles(resolution), **torch_kw)
    target = torch.tensor(radiance[None], **torch_kw)
    whole_sphere = torch.zeros(1, 3, **torch_kw)
    # shaders.quadrature.fibonacci_sphere turned by half a golden angle: the start section 42 was measured from
    i = np.arange(count) + 0.5
    z, phi = 1 - 2 * i / count, i * GOLDEN_ANGLE
    start = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    start += 1e-3 * torch.randn(count, 3, generator=generator, dtype=torch.float64).numpy()
    axis = torch.tensor(start, requires_grad=True, **torch_kw)
    log_sharpness = torch.full((count,), math.log(max(count / 2.0, 1.0)), requires_grad=True, **torch_kw)
    mean = np.maximum(radiance.reshape(-1, 3).mean(axis=0), 1e-4)
    log_amplitude = torch.tensor(np.log(np.tile(0.5 * mean, (count, 1))), requires_grad=True, **torch_kw)
    optimiser = torch.optim.Adam([axis, log_sharpness, log_amplitude], lr=3e-2)

    def parameters():
        return (axis / axis.norm(dim=1, keepdim=True), torch.exp(log_sharpness.clamp(LOG_SHARPNESS_MIN, LOG_SHARPNESS_MAX)),
                torch.exp(log_amplitude))

    for _ in range(steps):
        loss, _ = lightfield_loss(tuple(x[None] for x in parameters()), target, whole_sphere, directions, solid)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        return [(a.cpu().numpy(), float(s), m.cpu().numpy()) for a, s, m in zip(*parameters())]


def fit_map(radiance: np.ndarray) -> np.ndarray:
    """The map the fit works on: finite, and averaged down to ENV_FIT_RESOLUTION where it is finer."""
    radiance = np.nan_to_num(np.asarray(radiance, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if radiance.shape[0] > ENV_FIT_RESOLUTION:
        radiance = downsample_octahedral(radiance, ENV_FIT_RESOLUTION)
    return radiance


def fit_environment(radiance: np.ndarray, count: int, steps: int = REST_STEPS, device: str = "cpu"):
    """[(axis, sharpness, rgb amplitude)] * count for an (R, R, 3) octahedral map of the environment (through
    fit_map): its compact sources first, then the rest (module docstring)."""
    sources, rest = compact_sources(fit_map(radiance), most=min(SOURCE_MOST, count - 1))
    return sources + _fit_rest(rest, count - len(sources), steps, device)
