"""Spherical-Gaussian math in torch: differentiable twin of ``shaders/sg_math.py``.

Same names, shapes, conventions and clamps as the numpy reference (tests hold them equal). Every
branch is written so that gradients stay finite: clamps come before divisions, square roots and
logs, and ``torch.where`` never selects between a finite value and a branch whose gradient is NaN.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..shaders.sg_math import (  # the one place the clamps are defined
    AMPLITUDE_MAX_HALF,
    AXIS_EPS,
    CLAMPED_COSINE_LEGENDRE,
    DIELECTRIC_FRESNEL_IOR,
    GGX_NDF_LOBES,
    GLOSSY_NDF_LOBES,
    HORIZON_EXPONENT_MAX,
    HORIZON_LOGISTIC,
    IRRADIANCE_SERIES_MAX_SHARPNESS,
    LOCAL_WARP_ITERATIONS,
    NDOTV_MIN,
    ROUGHNESS_MIN,
    SHARPNESS_MAX,
    SHARPNESS_MIN,
    SMALL_X,
    TINY_SQUARED_LENGTH,
)

__all__ = [
    "AMPLITUDE_MAX_HALF", "SHARPNESS_MIN", "SHARPNESS_MAX", "ROUGHNESS_MIN", "NDOTV_MIN",
    "dot", "safe_normalize", "orthonormal_tangents", "one_minus_exp_neg2x_over_x",
    "sg_eval", "sg_integral", "sg_inner_product", "clamp_roughness", "ggx_alpha", "ndf_sg", "ASG",
    "reflection_frame", "warp_ndf_to_asg", "asg_eval", "sg_asg_convolve", "fresnel_dielectric",
    "fresnel_dielectric_weight", "fresnel",
    "smith_lambda_ggx", "smith_g2_ggx", "ggx_ndf", "ggx_brdf_cos_white", "microfacet_factor", "normalize_or_zero",
    "horizon_fraction",
    "sg_glossy", "sg_glossy_mirror_warp", "bessel_i_scaled",
    "sg_irradiance_series", "sg_irradiance_fitted", "sg_irradiance", "sanitize_sg_params", "sg_sum_eval",
]


def dot(a, b):
    return (a * b).sum(dim=-1)


def safe_normalize(v, eps=AXIS_EPS):
    length = torch.sqrt(torch.clamp_min(dot(v, v), eps * eps)).unsqueeze(-1)
    fallback = torch.zeros_like(v)
    fallback[..., 2] = 1
    return torch.where(length > eps, v / length, fallback)


def orthonormal_tangents(z):
    sign = torch.where(z[..., 2] >= 0, 1.0, -1.0).to(z.dtype)
    a = -1.0 / (sign + z[..., 2])
    b = z[..., 0] * z[..., 1] * a
    x = torch.stack([1 + sign * z[..., 0] ** 2 * a, sign * b, -sign * z[..., 0]], dim=-1)
    y = torch.stack([b, sign + z[..., 1] ** 2 * a, -z[..., 1]], dim=-1)
    return x, y


def one_minus_exp_neg2x_over_x(x):
    safe = torch.clamp_min(x, SMALL_X)
    return torch.where(x > SMALL_X, -torch.expm1(-2 * safe) / safe, 2 - 2 * x)


def sg_eval(v, axis, sharpness, amplitude):
    cos = torch.clamp(dot(v, axis), -1, 1)
    return amplitude * torch.exp(sharpness * (cos - 1)).unsqueeze(-1)


def sg_integral(sharpness, amplitude):
    return 2 * math.pi * amplitude * one_minus_exp_neg2x_over_x(sharpness).unsqueeze(-1)


def sg_inner_product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2):
    combined = sharpness1.unsqueeze(-1) * axis1 + sharpness2.unsqueeze(-1) * axis2
    d = torch.sqrt(torch.clamp_min(dot(combined, combined), TINY_SQUARED_LENGTH))
    scale = 2 * math.pi * torch.exp(d - sharpness1 - sharpness2) * one_minus_exp_neg2x_over_x(d)
    return amplitude1 * amplitude2 * scale.unsqueeze(-1)


def clamp_roughness(roughness):
    return torch.clamp(roughness, ROUGHNESS_MIN, 1.0)


def ggx_alpha(roughness):
    return clamp_roughness(roughness) ** 2


def ndf_sg(normal, roughness):
    a2 = ggx_alpha(roughness) ** 2
    return normal, 2.0 / a2, 1.0 / (math.pi * a2)


@dataclass
class ASG:
    z: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor
    sharpness_x: torch.Tensor
    sharpness_y: torch.Tensor
    amplitude: torch.Tensor


def reflection_frame(normal, view):
    ndotv = torch.clamp(dot(normal, view), NDOTV_MIN, 1.0)
    z = safe_normalize(2 * ndotv.unsqueeze(-1) * normal - view)
    x_raw = torch.linalg.cross(normal, z, dim=-1)
    tx, _ = orthonormal_tangents(z)
    has_plane = dot(x_raw, x_raw) > 1e-12
    x = torch.where(has_plane.unsqueeze(-1), safe_normalize(x_raw), tx)
    y = torch.linalg.cross(z, x, dim=-1)
    return z, x, y, ndotv


def warp_ndf_to_asg(normal, view, roughness, lobe=(1.0, 1.0)):
    _, lam_d, mu_d = ndf_sg(normal, roughness)
    lam_d, mu_d = lam_d * lobe[1], mu_d * lobe[0]
    z, x, y, ndotv = reflection_frame(normal, view)
    lam_d = torch.broadcast_to(lam_d, ndotv.shape)
    return ASG(z, x, y, lam_d / (8 * ndotv**2), lam_d / 8, torch.broadcast_to(mu_d, ndotv.shape))


def asg_eval(v, asg: ASG):
    a = dot(v, asg.x)
    b = dot(v, asg.y)
    return asg.amplitude * torch.clamp_min(dot(v, asg.z), 0) * torch.exp(
        -asg.sharpness_x * a * a - asg.sharpness_y * b * b)


def sg_asg_convolve(axis, sharpness, amplitude, asg: ASG):
    nu = sharpness / 2
    sx = nu * asg.sharpness_x / (nu + asg.sharpness_x)
    sy = nu * asg.sharpness_y / (nu + asg.sharpness_y)
    scale = math.pi / (torch.sqrt(nu + asg.sharpness_x) * torch.sqrt(nu + asg.sharpness_y))
    a = dot(axis, asg.x)
    b = dot(axis, asg.y)
    shape = torch.clamp_min(dot(axis, asg.z), 0) * torch.exp(-sx * a * a - sy * b * b)
    return amplitude * (asg.amplitude * scale * shape).unsqueeze(-1)


def fresnel_dielectric(cos_theta, eta):
    c = torch.clamp(cos_theta, 0, 1)
    g = torch.sqrt(eta * eta - 1 + c * c)
    a, b = (g - c) / (g + c), (c * (g + c) - 1) / (c * (g - c) + 1)
    return 0.5 * a * a * (1 + b * b)


def fresnel_dielectric_weight(cos_theta):
    f0 = ((DIELECTRIC_FRESNEL_IOR - 1) / (DIELECTRIC_FRESNEL_IOR + 1)) ** 2
    return (fresnel_dielectric(cos_theta, DIELECTRIC_FRESNEL_IOR) - f0) / (1 - f0)


def fresnel(f0, cos_theta, metallic=0.0):
    schlick = (1 - torch.clamp(cos_theta, 0, 1)) ** 5
    dielectric = fresnel_dielectric_weight(cos_theta)
    return f0 + (1 - f0) * (dielectric + metallic * (schlick - dielectric)).unsqueeze(-1)


def smith_lambda_ggx(cos_theta, alpha):
    c2 = torch.clamp(cos_theta, NDOTV_MIN, 1.0) ** 2
    return 0.5 * (torch.sqrt(1 + alpha**2 * (1 - c2) / c2) - 1)


def smith_g2_ggx(ndotl, ndotv, alpha):
    return 1 / (1 + smith_lambda_ggx(ndotl, alpha) + smith_lambda_ggx(ndotv, alpha))


def ggx_ndf(ndoth, alpha):
    a2 = alpha**2
    c = torch.clamp(ndoth, 0, 1)
    return a2 / (math.pi * ((c * c) * (a2 - 1) + 1) ** 2)


def ggx_brdf_cos_white(light, view, normal, roughness):
    """sg_math.ggx_brdf_cos_white: D G / (4 n.v) where n.l > 0, else 0 (the refits' integrand, F0 = 1)."""
    alpha = ggx_alpha(roughness)
    ndotl, ndotv_signed, vdotv = dot(normal, light), dot(normal, view), dot(view, view)
    ndotv = torch.clamp(ndotv_signed, NDOTV_MIN, 1)
    ldotv = dot(light, view)
    length = torch.sqrt(torch.clamp_min(dot(light, light) + 2 * ldotv + vdotv, AXIS_EPS * AXIS_EPS))
    ndoth = torch.where(length <= AXIS_EPS, normal[..., 2], (ndotl + ndotv_signed) / length)
    d = ggx_ndf(ndoth, alpha)
    g = smith_g2_ggx(torch.clamp_min(ndotl, NDOTV_MIN), ndotv, alpha)
    return torch.where(ndotl > 0, d * g / (4 * ndotv), 0.0)


def sg_glossy_mirror_warp(axis, sharpness, amplitude, normal, view, roughness, f0, metallic=0.0):
    asgs = [warp_ndf_to_asg(normal, view, roughness, lobe) for lobe in GGX_NDF_LOBES]
    conv = sum(sg_asg_convolve(axis, sharpness, amplitude, asg) for asg in asgs)
    z = asgs[0].z
    ndotv = torch.clamp(dot(normal, view), NDOTV_MIN, 1)
    return conv * microfacet_factor(normal, view, z, safe_normalize(z + view), ndotv, roughness, f0, metallic)


def microfacet_factor(normal, view, light, half, ndotv, roughness, f0, metallic=0.0):
    ndotl = torch.clamp(dot(normal, light), NDOTV_MIN, 1)
    g = smith_g2_ggx(ndotl, ndotv, ggx_alpha(roughness))
    return fresnel(f0, dot(view, half), metallic) * (g / (4 * ndotv)).unsqueeze(-1)


def normalize_or_zero(v):
    return v / torch.sqrt(torch.clamp_min(dot(v, v), TINY_SQUARED_LENGTH)).unsqueeze(-1)


def horizon_fraction(elevation, sharpness):
    exponent = -HORIZON_LOGISTIC * elevation * torch.sqrt(2 * sharpness)
    return 1 / (1 + torch.exp(torch.clamp_max(exponent, HORIZON_EXPONENT_MAX)))


def sg_glossy(axis, sharpness, amplitude, normal, view, roughness, f0, lobes=GLOSSY_NDF_LOBES,
              iterations=LOCAL_WARP_ITERATIONS, metallic=0.0):
    z, _, _, ndotv = reflection_frame(normal, view)
    _, lam_d, mu_d = ndf_sg(normal, roughness)
    nu = sharpness / 2
    along_z = dot(axis, z)
    tangent = axis - along_z.unsqueeze(-1) * z
    facing = torch.clamp_min(along_z, 0)
    total, factor = 0.0, None
    for amplitude_scale, sharpness_scale in lobes:
        lam, mu = lam_d * sharpness_scale, mu_d * amplitude_scale
        lam_in = lam / 8
        lam_across = lam / (8 * ndotv**2)
        peak = z
        for _ in range(iterations):
            across = normalize_or_zero(torch.linalg.cross(torch.broadcast_to(view, peak.shape), peak, dim=-1))
            d_in, d_across = lam_in + nu * facing, lam_across + nu * facing
            step = (nu / d_in).unsqueeze(-1) * tangent + \
                (nu * dot(axis, across) * (1 / d_across - 1 / d_in)).unsqueeze(-1) * across
            peak = normalize_or_zero(z + step)
            half = normalize_or_zero(peak + view)
            vdoth = torch.clamp(dot(view, half), NDOTV_MIN, 1)
            lam_across = lam / (8 * vdoth**2)
        cosine = torch.clamp_min(dot(axis, peak), 0)
        exponent = -0.5 * lam * dot(normal - half, normal - half) - 0.5 * sharpness * dot(axis - peak, axis - peak)
        width = math.pi / torch.sqrt((lam_across + nu * cosine) * (lam_in + nu * cosine))
        above = horizon_fraction(dot(normal, peak), lam_in + nu * cosine)
        integral = amplitude * (mu * width * above * torch.exp(exponent)).unsqueeze(-1)
        if factor is None:
            factor = microfacet_factor(normal, view, peak, half, ndotv, roughness, f0, metallic)
        total = total + integral * factor
    return total


def bessel_i_scaled(x):
    xs = torch.clamp_max(x, 1.0)
    x2 = xs * xs

    def series(l, dfact):
        t, total = torch.ones_like(xs), torch.ones_like(xs)
        for k in range(1, 7):
            t = t * x2 / (2 * k * (2 * l + 2 * k + 1))
            total = total + t
        return xs**l / dfact * total * torch.exp(-xs)

    xb = torch.clamp_min(x, 1.0)
    e2 = torch.exp(-2 * xb)
    i0 = (1 - e2) / (2 * xb)
    i1 = ((1 + e2) / 2 - i0) / xb
    i2 = i0 - 3 * i1 / xb
    i3 = i1 - 5 * i2 / xb
    i4 = i2 - 7 * i3 / xb
    small = x < 1.0
    return tuple(torch.where(small, series(l, df), big)
                 for l, df, big in ((0, 1.0, i0), (1, 3.0, i1), (2, 15.0, i2), (4, 945.0, i4)))


def sg_irradiance_series(axis, sharpness, amplitude, normal):
    c = torch.clamp(dot(axis, normal), -1, 1)
    i0, i1, i2, i4 = bessel_i_scaled(torch.clamp_max(sharpness, IRRADIANCE_SERIES_MAX_SHARPNESS))
    p2 = 0.5 * (3 * c * c - 1)
    p4 = (35 * c**4 - 30 * c * c + 3) / 8
    k = CLAMPED_COSINE_LEGENDRE
    e = k[0] * i0 + 3 * k[1] * i1 * c + 5 * k[2] * i2 * p2 + 9 * k[4] * i4 * p4
    return amplitude * e.unsqueeze(-1)


def sg_irradiance_fitted(axis, sharpness, amplitude, normal):
    lam = torch.clamp_min(sharpness, IRRADIANCE_SERIES_MAX_SHARPNESS)
    mu_dot_n = torch.clamp(dot(axis, normal), -1, 1)
    c0 = 0.36
    c1 = 1 / (4 * c0)
    eml = torch.exp(-lam)
    em2l = eml * eml
    rl = 1 / lam
    scale = 1 + 2 * em2l - rl
    bias = (eml - em2l) * rl - em2l
    x = torch.sqrt(torch.clamp_min(1 - scale, 1e-12))
    x0 = c0 * mu_dot_n
    x1 = c1 * x
    n = x0 + x1
    y = torch.where(torch.abs(x0) <= x1, n * n / x, torch.clamp(mu_dot_n, 0, 1))
    normalized = torch.clamp_min(scale * y + bias, 0)
    return sg_integral(lam, amplitude) * normalized.unsqueeze(-1)


def sg_irradiance(axis, sharpness, amplitude, normal):
    broad = (sharpness < IRRADIANCE_SERIES_MAX_SHARPNESS).unsqueeze(-1)
    return torch.where(broad, sg_irradiance_series(axis, sharpness, amplitude, normal),
                       sg_irradiance_fitted(axis, sharpness, amplitude, normal))


def sanitize_sg_params(axis, sharpness, amplitude):
    axis = safe_normalize(torch.nan_to_num(axis, nan=0.0, posinf=0.0, neginf=0.0))
    sharpness = torch.clamp(torch.nan_to_num(sharpness, nan=SHARPNESS_MIN), SHARPNESS_MIN, SHARPNESS_MAX)
    amplitude = torch.clamp_min(torch.nan_to_num(amplitude, nan=0.0, posinf=0.0, neginf=0.0), 0)
    return axis, sharpness, amplitude


def sg_sum_eval(v, axes, sharpness, amplitudes):
    return sg_eval(v.unsqueeze(-2), axes, sharpness, amplitudes).sum(dim=-2)


# --- octahedral map (twin of shaders/octahedral.py) -------------------------------------------
def _sign_nonzero(x):
    return torch.where(x >= 0, 1.0, -1.0).to(x.dtype)


def oct_encode(d):
    l1 = torch.clamp_min(d.abs().sum(dim=-1, keepdim=True), 1e-30)
    p = d / l1
    u, v, z = p[..., 0], p[..., 1], p[..., 2]
    lower = z < 0
    fu = (1 - v.abs()) * _sign_nonzero(u)
    fv = (1 - u.abs()) * _sign_nonzero(v)
    return torch.stack([torch.where(lower, fu, u), torch.where(lower, fv, v)], dim=-1)


def oct_decode(uv):
    u, v = uv[..., 0], uv[..., 1]
    z = 1 - u.abs() - v.abs()
    lower = z < 0
    x = torch.where(lower, (1 - v.abs()) * _sign_nonzero(u), u)
    y = torch.where(lower, (1 - u.abs()) * _sign_nonzero(v), v)
    p = torch.stack([x, y, z], dim=-1)
    return p / torch.linalg.vector_norm(p, dim=-1, keepdim=True)


def pixel_solid_angles(resolution: int, dtype=torch.float32, device=None):
    from ..shaders.octahedral import pixel_solid_angles as exact

    return torch.tensor(np.array(exact(resolution)), dtype=dtype, device=device)


__all__ += ["oct_encode", "oct_decode", "pixel_solid_angles"]
