"""LDR-FLIP (Andersson et al., "FLIP: A Difference Evaluator for Alternating Images", HPG 2020) in torch, as a
differentiable loss. The bench and the evaluation score images with the `flip-evaluator` package
(bake_directory/image_metrics.flip); this twin follows the same published algorithm and is tested against it.

Images are (B, 3, H, W) sRGB-encoded values in [0, 1]. Steps: sRGB -> linear -> XYZ -> YCxCz; each opponent
channel blurred by its contrast-sensitivity filter; back to linear RGB clipped to [0, 1]; CIELAB with the Hunt
adjustment; HyAB distance, raised to qc and mapped to [0, 1]. Edges and points of the normalised Y channel
(first and second Gaussian derivatives) give the feature difference df; the error is colour_error ** (1 - df).
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

PIXELS_PER_DEGREE = 0.7 * 3840 / 0.7 * math.pi / 180  # flip-evaluator's default observer: 4K, 0.7 m wide, 0.7 m away
QC, QF, PC, PT = 0.7, 0.5, 0.4, 0.95
EPS = 1e-15  # keeps square roots and powers differentiable at 0
# Contrast sensitivity: (a1, b1, a2, b2) of each opponent channel's sum of two Gaussians (achromatic, red-green,
# blue-yellow).
CSF = ((1.0, 0.0047, 0.0, 1e-5), (1.0, 0.0053, 0.0, 1e-5), (34.1, 0.04, 13.5, 0.025))
FEATURE_WIDTH = 0.082  # degrees, peak to trough of the edge detector
WHITE_D65 = (0.950428545, 1.0, 1.088900371)
RGB_TO_XYZ = ((10135552 / 24577794, 8788810 / 24577794, 4435075 / 24577794),
              (2613072 / 12288897, 8788810 / 12288897, 887015 / 12288897),
              (1425312 / 73733382, 8788810 / 73733382, 70074185 / 73733382))


def _matrix(values, like):
    return torch.tensor(values, dtype=like.dtype, device=like.device)


def _apply(matrix, image):
    return torch.einsum("ij,bjhw->bihw", matrix, image)


def srgb_to_linear(image):
    return torch.where(image > 0.04045, ((image.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4, image / 12.92)


def linear_to_ycxcz(linear):
    xyz = _apply(_matrix(RGB_TO_XYZ, linear), linear) / _matrix(WHITE_D65, linear).view(1, 3, 1, 1)
    x, y, z = xyz[:, 0:1], xyz[:, 1:2], xyz[:, 2:3]
    return torch.cat([116 * y - 16, 500 * (x - y), 200 * (y - z)], dim=1)


def ycxcz_to_linear(ycxcz):
    y = (ycxcz[:, 0:1] + 16) / 116
    xyz = torch.cat([y + ycxcz[:, 1:2] / 500, y, y - ycxcz[:, 2:3] / 200], dim=1)
    xyz = xyz * _matrix(WHITE_D65, ycxcz).view(1, 3, 1, 1)
    return _apply(torch.linalg.inv(_matrix(RGB_TO_XYZ, ycxcz).double()).to(ycxcz.dtype), xyz)


def linear_to_hunt_lab(linear):
    """CIELAB (D65) with a and b scaled by L/100 (the Hunt effect)."""
    xyz = _apply(_matrix(RGB_TO_XYZ, linear), linear) / _matrix(WHITE_D65, linear).view(1, 3, 1, 1)
    delta = 6 / 29
    f = torch.where(xyz > delta ** 3, xyz.clamp(min=delta ** 3) ** (1 / 3), xyz / (3 * delta ** 2) + 4 / 29)
    lightness = 116 * f[:, 1:2] - 16
    a, b = 500 * (f[:, 0:1] - f[:, 1:2]), 200 * (f[:, 1:2] - f[:, 2:3])
    return torch.cat([lightness, 0.01 * lightness * a, 0.01 * lightness * b], dim=1)


def hyab(first, second):
    delta = first - second
    return torch.sqrt((delta[:, 0:1] ** 2).clamp(min=EPS)) + torch.sqrt((delta[:, 1:3] ** 2).sum(1, keepdim=True)
                                                                         .clamp(min=EPS))


@functools.lru_cache(maxsize=8)  # built once per viewing condition, not per training step
def csf_kernels(pixels_per_degree: float, dtype=torch.float64):
    """The opponent channels' spatial filters, separably: (gaussians (2, 3, K) 1-D, weights (2, 3)); channel c is
    filtered by sum_t weights[t, c] * g[t, c](x) g[t, c](y), which sums to 1 over the common radius."""
    widest = max(max(b1, b2) for _, b1, _, b2 in CSF)
    radius = int(math.ceil(3 * math.sqrt(widest / (2 * math.pi ** 2)) * pixels_per_degree))
    step = torch.arange(-radius, radius + 1, dtype=torch.float64) / pixels_per_degree
    gaussians = torch.stack([torch.stack([torch.exp(-math.pi ** 2 * step ** 2 / b) for b in (b1, b2)])
                             for _, b1, _, b2 in CSF], dim=1)
    weights = torch.tensor([[a1 * math.sqrt(math.pi / b1), a2 * math.sqrt(math.pi / b2)] for a1, b1, a2, b2 in CSF],
                           dtype=torch.float64).T
    weights = weights / (weights * gaussians.sum(-1) ** 2).sum(0)
    return gaussians.to(dtype), weights.to(dtype)


@functools.lru_cache(maxsize=8)
def feature_kernels(pixels_per_degree: float, dtype=torch.float64):
    """1-D (gaussian, first derivative, second derivative) of the edge and point detectors: the 2-D edge kernel
    along x is derivative(x) gaussian(y), with positive weights summing to 1 and negative ones to -1."""
    sd = 0.5 * FEATURE_WIDTH * pixels_per_degree
    radius = int(math.ceil(3 * sd))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    gaussian = torch.exp(-x ** 2 / (2 * sd * sd))
    out = [gaussian / gaussian.sum()]
    for d in (-x * gaussian, (x ** 2 / (sd * sd) - 1) * gaussian):
        out.append(torch.where(d < 0, d / -d[d < 0].sum(), d / d[d > 0].sum()))
    return tuple(k.to(dtype) for k in out)


def _separable(image, along_x, along_y):
    """Depthwise 2-D filter of (B, C, H, W) by along_x (C, K) (x) along_y (C, K), edges replicated."""
    channels, size = along_x.shape
    radius = size // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    rows = F.conv2d(padded, along_x.view(channels, 1, 1, size).to(image), groups=channels)
    return F.conv2d(rows, along_y.view(channels, 1, size, 1).to(image), groups=channels)


@functools.lru_cache(maxsize=1)
def _largest_colour_distance() -> float:
    """HyAB ** qc between Hunt-adjusted green and blue: FLIP's cmax."""
    green = linear_to_hunt_lab(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).view(1, 3, 1, 1))
    blue = linear_to_hunt_lab(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1))
    return float(hyab(green, blue)) ** QC


def flip_map(test_srgb: torch.Tensor, reference_srgb: torch.Tensor,
             pixels_per_degree: float = PIXELS_PER_DEGREE) -> torch.Tensor:
    """(B, 1, H, W) per-pixel LDR-FLIP of two (B, 3, H, W) sRGB images in [0, 1]."""
    test = linear_to_ycxcz(srgb_to_linear(test_srgb.clamp(0, 1)))
    reference = linear_to_ycxcz(srgb_to_linear(reference_srgb.clamp(0, 1)))
    gaussians, weights = csf_kernels(pixels_per_degree)

    def perceived(ycxcz):
        blurred = sum(weights[t].to(ycxcz).view(1, 3, 1, 1) * _separable(ycxcz, gaussians[t], gaussians[t])
                      for t in range(2))
        return linear_to_hunt_lab(ycxcz_to_linear(blurred).clamp(0, 1))

    cmax = _largest_colour_distance()
    distance = hyab(perceived(reference), perceived(test)) ** QC
    colour = torch.where(distance < PC * cmax, PT / (PC * cmax) * distance,
                         PT + (distance - PC * cmax) / (cmax - PC * cmax) * (1 - PT))

    gaussian, first, second = feature_kernels(pixels_per_degree)
    across = torch.stack([first, gaussian, second, gaussian])
    along = torch.stack([gaussian, first, gaussian, second])

    def edges_points(ycxcz):
        responses = _separable(((ycxcz[:, 0:1] + 16) / 116).expand(-1, 4, -1, -1), across, along)
        edges = torch.sqrt((responses[:, 0:2] ** 2).sum(1, keepdim=True).clamp(min=EPS))
        points = torch.sqrt((responses[:, 2:4] ** 2).sum(1, keepdim=True).clamp(min=EPS))
        return edges, points

    (edge_t, point_t), (edge_r, point_r) = edges_points(test), edges_points(reference)
    feature = torch.maximum((edge_r - edge_t).abs(), (point_r - point_t).abs()).clamp(min=EPS)
    feature = (feature / math.sqrt(2)) ** QF
    return colour ** (1 - feature)


def flip_loss(test_srgb: torch.Tensor, reference_srgb: torch.Tensor,
              pixels_per_degree: float = PIXELS_PER_DEGREE) -> torch.Tensor:
    """Mean LDR-FLIP: what bake_directory.image_metrics.flip reports, differentiable."""
    return flip_map(test_srgb, reference_srgb, pixels_per_degree).mean()
