"""Refit SG axes, sharpness and amplitudes through the node group's glossy (torch; docs/design-additions.md §5).

The amplitude refit (glossy_refit) keeps the CNN's axes and sharpness, so the lobes stay where the log-space fit
put them. This one moves them too: Adam on every parameter of one material's texels at once, minimising

    sum_t  sum_v |sum_k glossy_k(v) - integral L_t(l) f(l, v) (n.l) dl|^2 / sum_v |integral ...|^2
      + LOBE_REFIT_SMOOTHNESS sum_{t,u atlas neighbours} |change_t - change_u|^2

with glossy_k sg_torch.sg_glossy (the node group's closed form), the target the exact GGX reflection of the rendered
light field (F0 = 1) over one group of glossy_refit's views per step (LOBE_REFIT_VIEW_GROUPS), and change the move
from the start values in the encoding the shader blends (unit axis, log sharpness, log amplitude). The smoothness
term is what keeps bilinear lookups right: the shader blends neighbouring texels' parameters slot by slot, and lobes
fitted texel by texel blend into wrong ones (Production spheres, roughness 0.5, FLIP of the glossy at texel centres
0.078 -> 0.056 without the term, but 0.078 -> 0.088 once blended; with it 0.057 and 0.058).
"""
from __future__ import annotations

import numpy as np
import torch

from ..shaders.sg_math import SHARPNESS_MAX, SHARPNESS_MIN
from . import glossy_refit_torch, sg_torch
from .glossy_refit import REFIT_LOBE_PIXELS, atlas_neighbour_pairs, hemisphere_views, refit_min_roughness

LOBE_REFIT_RATE = 0.02  # Adam's step on unit-axis components, log sharpness and log amplitude
LOBE_REFIT_SMOOTHNESS = 0.2  # weight of the neighbours' differing changes (1.0 held the fit back: 0.116 vs 0.100)
# Each Adam step fits one of this many interleaved groups of the views, in turn (every 8th view: 15 of the 120, on
# all 10 n.v rings), its error relative to that group's own target. Cheaper per step and a better fit than all
# views each step: paired harness (free SG4, lobes down to 0.36 pixels) glossy RMSE 0.0358 with all views, 0.0345
# with 4 groups, 0.0340 with 8, 0.0345 with 16; 0.0356 with 8 groups relative to all views' target
# (docs/design-additions.md section 29).
LOBE_REFIT_VIEW_GROUPS = 8
LOBE_REFIT_BATCH = 512  # texels per forward and backward pass (memory: ~0.2 GB at 16 SGs and 15 views)
AMPLITUDE_FLOOR = 1e-3  # of a texel's largest amplitude: log amplitudes start at least here
LOBE_REFIT_LOBE_PIXELS = REFIT_LOBE_PIXELS  # light-field pixels the GGX lobe must span: the amplitude refit's 0.36
# The lobe refit is kept unless it raises the error between texels more than this factor: that error is against
# the light field, which the path-traced reference does not follow where lobes span a pixel or two (docstring below).
LOBE_REFIT_GUARD_TOLERANCE = 1.15


def lobe_refit_min_roughness(resolution: int) -> float:
    """The least roughness the lobe refit is used at: 0.2 at R = 32, 0.28 at R = 16, as the amplitude refit. Before
    the target was integrated over each pixel it stopped at 0.75 pixels (0.29, 0.41). Production spheres, R = 32,
    16 SGs, the same CNN; FLIP against 512-spp Cycles, and the guard's error between texels (light-field target,
    pixel centres then): roughness 0.3 (a 0.81-pixel lobe) FLIP 0.067 -> 0.056 while that error rose 0.343 ->
    0.372; 0.4 (1.45 pixels) 0.061 -> 0.048, error 0.122 -> 0.118; 0.5 (2.3 pixels) error 0.086 -> 0.063. So a
    small rise of that error does not mean a worse bake (LOBE_REFIT_GUARD_TOLERANCE); a blow-up still does.
    Down to 0.36 pixels with all 120 views each step it cost 126 ms per texel at 16 SGs (courtyard's Draft bake
    70 -> 394 s); view groups and larger batches brought that down (docs/design-additions.md §28, §29)."""
    return refit_min_roughness(resolution, LOBE_REFIT_LOBE_PIXELS)


def lobe_refit_steps(images: np.ndarray, normals: np.ndarray, texels: np.ndarray, axis: np.ndarray,
                     sharpness: np.ndarray, amplitude: np.ndarray, roughness: np.ndarray, lobe_count: int,
                     steps: int, device: str = "cpu", target: np.ndarray | None = None):
    """One material's texels: light fields images (T, R, R, C), normals (T, 3), atlas texels (T, 2) [row, col],
    start SGs axis (T, N, 3), sharpness (T, N), amplitude (T, N, C), roughness (T,). SGs past lobe_count are left
    as they are (zero). `target`: their fitted_view_targets where already computed (the amplitude refit's). A
    generator: yields the fraction of steps done, returns (axis, sharpness, amplitude) as float32 arrays of the
    input's shapes."""
    dtype = torch.float32
    t, n = np.shape(sharpness)
    k = int(min(max(lobe_count, 0), n))
    result = [np.array(axis, np.float32), np.array(sharpness, np.float32), np.array(amplitude, np.float32)]
    if t == 0 or k == 0 or steps <= 0:
        return tuple(result)
    views = hemisphere_views(normals)
    if target is None:  # the amplitude refit's target where the train stage passes it
        target = glossy_refit_torch.fitted_view_targets(images, normals, roughness, device)
    target = torch.as_tensor(np.asarray(target, np.float32))

    def tensor(x):
        return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)

    groups = [slice(g, None, LOBE_REFIT_VIEW_GROUPS) for g in range(LOBE_REFIT_VIEW_GROUPS)]
    group_targets = [target[:, group].to(device=device, dtype=dtype).contiguous() for group in groups]
    group_target_norms = [(part ** 2).sum(dim=(1, 2)).clamp_min(1e-12) for part in group_targets]
    group_views = [tensor(views[:, group])[:, :, None] for group in groups]
    normal = tensor(normals)[:, None, None]
    rough, f0 = tensor(roughness)[:, None, None], torch.ones(1, dtype=dtype, device=device)
    start_axis = sg_torch.safe_normalize(tensor(axis[:, :k]))
    start_log_sharpness = torch.log(tensor(sharpness[:, :k]).clamp(SHARPNESS_MIN, SHARPNESS_MAX))
    start_amplitude = tensor(amplitude[:, :k]).clamp_min(0)
    floor = AMPLITUDE_FLOOR * start_amplitude.amax(dim=(1, 2), keepdim=True).clamp_min(1e-12)
    start_log_amplitude = torch.log(torch.maximum(start_amplitude, floor))
    params = [p.clone().requires_grad_() for p in (start_axis, start_log_sharpness, start_log_amplitude)]
    starts = (start_axis, start_log_sharpness, start_log_amplitude)
    pairs = torch.as_tensor(atlas_neighbour_pairs(np.asarray(texels)), device=device)
    optimiser = torch.optim.Adam(params, lr=LOBE_REFIT_RATE)

    def lobes(index):
        return (sg_torch.safe_normalize(params[0][index]),
                torch.exp(params[1][index]).clamp(SHARPNESS_MIN, SHARPNESS_MAX), torch.exp(params[2][index]))

    for step in range(steps):
        group = step % LOBE_REFIT_VIEW_GROUPS
        target, target_norm, view = group_targets[group], group_target_norms[group], group_views[group]
        optimiser.zero_grad()
        if len(pairs):
            a, b = pairs[:, 0], pairs[:, 1]
            smoothness = sum((((p - p0)[a] - (p - p0)[b]) ** 2).sum() for p, p0 in zip(params, starts))
            (LOBE_REFIT_SMOOTHNESS * smoothness).backward()
        for s in range(0, t, LOBE_REFIT_BATCH):
            index = slice(s, s + LOBE_REFIT_BATCH)
            lobe_axis, lobe_sharpness, lobe_amplitude = lobes(index)
            shaded = sg_torch.sg_glossy(lobe_axis[:, None], lobe_sharpness[:, None], lobe_amplitude[:, None],
                                        normal[index], view[index], rough[index], f0).sum(dim=2)
            loss = (((shaded - target[index]) ** 2).sum(dim=(1, 2)) / target_norm[index]).sum()
            loss.backward()
        optimiser.step()
        yield (step + 1) / steps
    with torch.no_grad():
        for out, value in zip(result, lobes(slice(None))):
            out[:, :k] = value.cpu().numpy()
    return tuple(result)
