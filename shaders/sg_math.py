"""Spherical-Gaussian math, numpy reference.

This module defines what the SG evaluator node group computes and what the torch code in
``training/sg_torch.py`` must match (same names, same clamps). It needs only numpy.

Conventions (DESIGN.md section 3):
  SG   G(v; u, lam, mu) = mu * exp(lam * (u.v - 1))           u unit axis, lam > 0, mu >= 0 (RGB)
  ASG  A(v) = a * max(v.z, 0) * exp(-lx (v.x)^2 - ly (v.y)^2)  (Xu et al. 2013)
Shapes: directions are (..., 3); sharpness is (...); amplitudes carry a trailing channel axis
(..., C). Everything broadcasts like numpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# --- Clamps shared by numpy, torch and the shader nodes (keep them in one place) -----------------
SHARPNESS_MIN = 1e-4  # broadest stored lobe
SHARPNESS_MAX = 1e4  # sharpest stored lobe: ~0.01 rad wide, finer than a 128^2 octahedral pixel
AMPLITUDE_MAX_HALF = 65504.0  # largest finite half float; stored amplitudes are scaled below this
ROUGHNESS_MIN = 0.05  # Principled roughness floor; alpha = 0.0025, NDF sharpness 3.2e5
NDOTV_MIN = 1e-4  # grazing-angle floor for n.v (the paper's 0.0001)
AXIS_EPS = 1e-8  # axes shorter than this become +Z instead of NaN
SMALL_X = 1e-6  # below this, (1 - exp(-2x)) / x uses its series
TINY_SQUARED_LENGTH = 1e-30  # floor under |v|^2 before a square root (finite gradients in torch)

# GGX NDF in the half-vector domain as a sum of SGs, (a, b) per lobe: sharpness 2 b / alpha^2, amplitude
# a / (pi alpha^2). GGX_NDF_PEAK_MATCHED is the paper's single SG; GGX_NDF_TWO_LOBES a least-squares fit of GGX's
# long-tailed shape (1 + t^2)^-2, t = tan(theta) / alpha, weighted by area, projected integral held at 1
# (shaders/check_math.py fit_ggx_ndf_lobes): 4.5 % shape error against 28 %. The product's glossy (sg_glossy, the
# local warp) uses the two lobes; the paper's form (sg_glossy_mirror_warp) and the SH baseline's convolution the
# single SG: under the warp at the mirror direction the single SG's 5-23 % excess (n.v >= 0.5) offset the warp's
# too narrow lobe at grazing, and two lobes measured no better end to end there.
GGX_NDF_PEAK_MATCHED = ((1.0, 1.0),)
GGX_NDF_TWO_LOBES = ((0.8154517580, 1.7728163207), (0.1432483284, 0.2652625597))
GGX_NDF_LOBES = GGX_NDF_PEAK_MATCHED  # sg_glossy_mirror_warp's and the SH baseline's NDF
GLOSSY_NDF_LOBES = GGX_NDF_TWO_LOBES  # sg_glossy's NDF (numpy, torch and the node group)
LOCAL_WARP_ITERATIONS = 2  # sg_glossy: solves for the SG x NDF peak, each with the warp's Jacobian there

# Clamped-cosine Legendre coefficients c_l = 2*pi * integral_0^1 P_l(t) t dt (Funk-Hecke), l = 0..4.
CLAMPED_COSINE_LEGENDRE = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0, 0.0, -math.pi / 24.0)
IRRADIANCE_SERIES_MAX_SHARPNESS = 4.0  # below: Legendre series; from here on: Hill's fit


def dot(a, b):
    """Sum of products over the last axis. Written out for 3-vectors, bit for bit the same: numpy's reduction over
    a length-3 axis is about 10x slower."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape[-1:] == b.shape[-1:] == (3,):
        return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    return np.sum(a * b, axis=-1)


def safe_normalize(v, eps=AXIS_EPS):
    """Unit vector along v; +Z where |v| < eps (never NaN)."""
    v = np.asarray(v)
    length = np.sqrt(np.maximum(dot(v, v), eps * eps))[..., None]
    fallback = np.zeros_like(v)
    fallback[..., 2] = 1
    return np.where(length > eps, v / length, fallback)


def orthonormal_tangents(z):
    """Two unit vectors (x, y) completing z to a right-handed frame (Duff et al. 2017)."""
    sign = np.where(z[..., 2] >= 0, 1.0, -1.0).astype(z.dtype)
    a = -1.0 / (sign + z[..., 2])
    b = z[..., 0] * z[..., 1] * a
    x = np.stack([1 + sign * z[..., 0] ** 2 * a, sign * b, -sign * z[..., 0]], axis=-1)
    y = np.stack([b, sign + z[..., 1] ** 2 * a, -z[..., 1]], axis=-1)
    return x, y


def one_minus_exp_neg2x_over_x(x):
    """(1 - exp(-2x)) / x for x >= 0, exact limit 2 at x = 0, no cancellation."""
    x = np.asarray(x)
    safe = np.maximum(x, SMALL_X)
    return np.where(x > SMALL_X, -np.expm1(-2 * safe) / safe, 2 - 2 * x)


# --- Isotropic SGs ---------------------------------------------------------------------------------
def sg_eval(v, axis, sharpness, amplitude):
    cos = np.clip(dot(v, axis), -1, 1)
    return amplitude * np.exp(sharpness * (cos - 1))[..., None]


def sg_integral(sharpness, amplitude):
    """Integral of the SG over the sphere: 2 pi mu (1 - e^{-2 lam}) / lam."""
    return 2 * np.pi * amplitude * one_minus_exp_neg2x_over_x(sharpness)[..., None]


def sg_inner_product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2):
    """Integral of G1 * G2 over the sphere.

    4 pi mu1 mu2 sinh(d)/d e^{-l1-l2} with d = |l1 u1 + l2 u2|, evaluated as
    2 pi mu1 mu2 e^{d-l1-l2} (1 - e^{-2d}) / d so nothing overflows (d <= l1 + l2).
    The thesis' Eq. 21-23 divide the combined axis by l1 + l2; that is not this integral.
    """
    combined = sharpness1[..., None] * axis1 + sharpness2[..., None] * axis2
    d = np.sqrt(np.maximum(dot(combined, combined), TINY_SQUARED_LENGTH))
    scale = 2 * np.pi * np.exp(d - sharpness1 - sharpness2) * one_minus_exp_neg2x_over_x(d)
    return amplitude1 * amplitude2 * scale[..., None]


# --- GGX NDF as an SG, its warp to an ASG, and the SG x ASG convolution ---------------------------
def clamp_roughness(roughness):
    return np.clip(roughness, ROUGHNESS_MIN, 1.0)


def ggx_alpha(roughness):
    """GGX alpha from Blender's Principled roughness (alpha = roughness^2), after the floor."""
    return clamp_roughness(roughness) ** 2


def ndf_sg(normal, roughness):
    """GGX NDF in the half-vector domain as an SG: axis n, sharpness 2/alpha^2, amplitude 1/(pi alpha^2)."""
    a2 = ggx_alpha(roughness) ** 2
    return normal, 2.0 / a2, 1.0 / (np.pi * a2)


@dataclass
class ASG:
    """Anisotropic SG a * max(v.z,0) * exp(-sharpness_x (v.x)^2 - sharpness_y (v.y)^2)."""

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    sharpness_x: np.ndarray
    sharpness_y: np.ndarray
    amplitude: np.ndarray


def reflection_frame(normal, view):
    """Frame of the warped lobe: z = reflect(-view, n); x = n cross z (normal to the plane of
    incidence); y = z cross x (in the plane of incidence). Returns (z, x, y, clamped n.v)."""
    ndotv = np.clip(dot(normal, view), NDOTV_MIN, 1.0)
    z = safe_normalize(2 * ndotv[..., None] * normal - view)
    x_raw = np.cross(normal, z)
    tx, _ = orthonormal_tangents(z)
    has_plane = dot(x_raw, x_raw) > 1e-12
    x = np.where(has_plane[..., None], safe_normalize(x_raw), tx)
    y = np.cross(z, x)
    return z, x, y, ndotv


def warp_ndf_to_asg(normal, view, roughness, lobe=(1.0, 1.0)):
    """The NDF SG warped to the reflected-direction domain (Paper I Eq. 18, Xu et al. 2013).

    A half-vector offset d moves the reflected direction by 2 d in the plane of incidence and by
    2 (n.v) d across it, so the lobe is sharper across the plane: sharpness_x = lam_d / (8 (n.v)^2)
    on x = n cross z, sharpness_y = lam_d / 8 on y (in the plane). lobe (a, b) scales the NDF SG's
    amplitude and sharpness: one term of GGX_NDF_LOBES ((1, 1): the single peak-matched SG)."""
    _, lam_d, mu_d = ndf_sg(normal, roughness)
    lam_d, mu_d = lam_d * lobe[1], mu_d * lobe[0]
    z, x, y, ndotv = reflection_frame(normal, view)
    lam_d = np.broadcast_to(lam_d, ndotv.shape)
    return ASG(z, x, y, lam_d / (8 * ndotv**2), lam_d / 8, np.broadcast_to(mu_d, ndotv.shape))


def asg_eval(v, asg: ASG):
    a = dot(v, asg.x)
    b = dot(v, asg.y)
    return asg.amplitude * np.maximum(dot(v, asg.z), 0) * np.exp(-asg.sharpness_x * a * a - asg.sharpness_y * b * b)


def sg_asg_convolve(axis, sharpness, amplitude, asg: ASG):
    """Integral of SG * ASG over the sphere (Xu et al. 2013 approximation).

    With nu = lam/2 the result is the ASG evaluated at the SG axis with sharpnesses
    nu*lx/(nu+lx), nu*ly/(nu+ly), scaled by pi / sqrt((nu+lx)(nu+ly)) and by mu. The thesis' Eq. 24
    keeps the ASG's own sharpnesses; quadrature shows that is wrong away from the peak."""
    nu = sharpness / 2
    sx = nu * asg.sharpness_x / (nu + asg.sharpness_x)
    sy = nu * asg.sharpness_y / (nu + asg.sharpness_y)
    scale = np.pi / (np.sqrt(nu + asg.sharpness_x) * np.sqrt(nu + asg.sharpness_y))
    a = dot(axis, asg.x)
    b = dot(axis, asg.y)
    shape = np.maximum(dot(axis, asg.z), 0) * np.exp(-sx * a * a - sy * b * b)
    return amplitude * (asg.amplitude * scale * shape)[..., None]


# --- Microfacet terms --------------------------------------------------------------------------
DIELECTRIC_FRESNEL_IOR = 1.5  # the shape of every dielectric's Fresnel (fresnel); F0 comes from the material's IOR


def fresnel_dielectric(cos_theta, eta):
    """Unpolarised Fresnel reflectance at incidence cosine cos_theta of an interface of relative IOR eta >= 1."""
    c = np.clip(cos_theta, 0, 1)
    g = np.sqrt(eta * eta - 1 + c * c)
    a, b = (g - c) / (g + c), (c * (g + c) - 1) / (c * (g - c) + 1)
    return 0.5 * a * a * (1 + b * b)


def fresnel_dielectric_weight(cos_theta):
    """(F(cos) - F(1)) / (1 - F(1)) of the dielectric of DIELECTRIC_FRESNEL_IOR: 0 at normal incidence, 1 grazing.
    Every dielectric takes this shape; its F0 comes from its own IOR. The shape of IOR 1.33 or 2 is within 0.011 of it
    up to 60 degrees and 0.029 beyond; Schlick's (1 - cos)^5 is 0.020 below it at 60 degrees, where it is 0.051
    (shaders/check_math.py check_fresnel)."""
    f0 = ((DIELECTRIC_FRESNEL_IOR - 1) / (DIELECTRIC_FRESNEL_IOR + 1)) ** 2
    return (fresnel_dielectric(cos_theta, DIELECTRIC_FRESNEL_IOR) - f0) / (1 - f0)


def fresnel(f0, cos_theta, metallic=0.0):
    """F0 + (1 - F0) w(cos), w mixed by `metallic` from Schlick's (1 - cos)^5 (Principled's metal: its F82 tint
    model is exactly Schlick with a white tint) and fresnel_dielectric_weight (Principled's dielectric, Cycles' exact
    Fresnel: 19-27 % more reflection than Schlick's from 45 to 60 degrees at IOR 1.5)."""
    t = 1 - np.clip(cos_theta, 0, 1)
    t2 = t * t
    schlick = t2 * t2 * t  # t^5 by products (numpy's power is several times slower)
    dielectric = fresnel_dielectric_weight(cos_theta)
    weight = dielectric + np.asarray(metallic) * (schlick - dielectric)
    return f0 + (1 - f0) * weight[..., None]


def smith_lambda_ggx(cos_theta, alpha):
    c2 = np.clip(cos_theta, NDOTV_MIN, 1.0) ** 2
    return 0.5 * (np.sqrt(1 + alpha**2 * (1 - c2) / c2) - 1)


def smith_g2_ggx(ndotl, ndotv, alpha):
    """Height-correlated Smith masking-shadowing for GGX (what Cycles uses)."""
    return 1 / (1 + smith_lambda_ggx(ndotl, alpha) + smith_lambda_ggx(ndotv, alpha))


def ggx_ndf(ndoth, alpha):
    """GGX / Trowbridge-Reitz D(h), normalised so that integral D (n.h) dh = 1."""
    a2 = alpha**2
    c = np.clip(ndoth, 0, 1)
    return a2 / (np.pi * ((c * c) * (a2 - 1) + 1) ** 2)


def ggx_brdf_cos(light, view, normal, roughness, f0, metallic=0.0):
    """Reference integrand f(l, v) (n.l)_+ for GGX with `fresnel` and height-correlated Smith."""
    white, vdoth = _ggx_white_integrand_and_vdoth(light, view, normal, roughness)
    return fresnel(f0, vdoth, metallic) * white[..., None]


def ggx_brdf_cos_white(light, view, normal, roughness):
    """ggx_brdf_cos with F0 = 1 (the Fresnel is then 1), without the colour axis: the refits' integrand."""
    return _ggx_white_integrand_and_vdoth(light, view, normal, roughness)[0]


def _ggx_white_integrand_and_vdoth(light, view, normal, roughness):
    """(D G / (4 n.v) where n.l > 0, else 0; and v.h for the Fresnel term)."""
    alpha = ggx_alpha(roughness)
    light, view, normal = np.asarray(light), np.asarray(view), np.asarray(normal)
    ndotl, ndotv_signed, vdotv = dot(normal, light), dot(normal, view), dot(view, view)
    ndotv = np.clip(ndotv_signed, NDOTV_MIN, 1)
    # the half vector h = safe_normalize(l + v) enters only through n.h and v.h, taken without forming h
    ldotv = dot(light, view)
    length = np.sqrt(np.maximum(dot(light, light) + 2 * ldotv + vdotv, AXIS_EPS * AXIS_EPS))
    degenerate = length <= AXIS_EPS  # safe_normalize's fallback h = +Z
    ndoth = np.where(degenerate, normal[..., 2], (ndotl + ndotv_signed) / length)
    vdoth = np.where(degenerate, view[..., 2], (ldotv + vdotv) / length)
    d = ggx_ndf(ndoth, alpha)
    g = smith_g2_ggx(np.maximum(ndotl, NDOTV_MIN), ndotv, alpha)
    return np.where(ndotl > 0, d * g / (4 * ndotv), 0.0), vdoth


def sg_glossy_mirror_warp(axis, sharpness, amplitude, normal, view, roughness, f0, metallic=0.0):
    """The paper's glossy (Paper I section 6, Xu et al. 2013), kept as the comparison for sg_glossy.

    Convolution of the SG with the NDF warped about the mirror direction z (each lobe of GGX_NDF_LOBES), times
    Fresnel, Smith masking and (n.l) / (4 (n.l)(n.v)), all evaluated at l = z."""
    asgs = [warp_ndf_to_asg(normal, view, roughness, lobe) for lobe in GGX_NDF_LOBES]
    conv = sum(sg_asg_convolve(axis, sharpness, amplitude, asg) for asg in asgs)
    asg = asgs[0]
    ndotv = np.clip(dot(normal, view), NDOTV_MIN, 1)
    return conv * microfacet_factor(normal, view, asg.z, safe_normalize(asg.z + view), ndotv, roughness, f0,
                                    metallic)


def microfacet_factor(normal, view, light, half, ndotv, roughness, f0, metallic=0.0):
    """`fresnel` at v.h times height-correlated Smith G over 4 (n.v), for one light direction: what multiplies
    the NDF integral of an SG."""
    ndotl = np.clip(dot(normal, light), NDOTV_MIN, 1)
    g = smith_g2_ggx(ndotl, ndotv, ggx_alpha(roughness))
    return fresnel(f0, dot(view, half), metallic) * (g / (4 * ndotv))[..., None]


def normalize_or_zero(v):
    """v / |v|, and 0 for a zero vector (Blender's Normalize node; the frame across the plane of incidence is
    undefined at normal incidence, where the term it scales vanishes)."""
    return v / np.sqrt(np.maximum(dot(v, v), TINY_SQUARED_LENGTH))[..., None]


HORIZON_LOGISTIC = 1.702  # logistic slope that follows the normal CDF within 0.01
HORIZON_EXPONENT_MAX = 60.0  # the logistic's exponent is clamped here (share 1e-26) so exp stays finite in float32


def horizon_fraction(elevation, sharpness):
    """Share of a Gaussian lobe exp(-sharpness t^2) (t: angle along the elevation) centred at sin(elevation)
    `elevation` that lies above the horizon: the normal CDF at elevation / sigma, sigma = 1 / sqrt(2 sharpness),
    as a logistic (node-friendly)."""
    return 1 / (1 + np.exp(np.minimum(-HORIZON_LOGISTIC * elevation * np.sqrt(2 * sharpness), HORIZON_EXPONENT_MAX)))


def sg_glossy(axis, sharpness, amplitude, normal, view, roughness, f0, lobes=GLOSSY_NDF_LOBES,
              iterations=LOCAL_WARP_ITERATIONS, metallic=0.0):
    """Radiance reflected toward `view` by a GGX surface lit by one SG: what the node group evaluates.

    For each SG lobe of the NDF (`lobes`, iterations >= 1): the integral of SG(l) D(h(l)) by Laplace's method about the
    product's peak l*. The NDF is warped to the reflected-direction domain with its Jacobian taken at l*, not at
    the mirror direction z as Xu et al. 2013 do: a half-vector offset moves l by 2x in the plane of v and l, by
    2 (v.h) across it (sharpnesses lam/8 and lam / (8 (v.h)^2)). At grazing view v.h grows fast away from z, so
    the warp at z makes the lobe far too narrow where the light is (quadrature: 0.3-0.5x of the true integral for
    SGs 30 degrees above z at n.v = 0.14). l* is found in the tangent plane at z, `iterations` times, each with
    the sharpness across the plane at the previous l*; the peak's value uses the exact SG and NDF SG at l*, h*
    (exponents from chord lengths, -lam |n - h|^2 / 2, precise for sharp lobes in float32). Fresnel (`fresnel`)
    and height-correlated Smith G over 4 (n.v) are taken at the first (dominant) NDF lobe's l*: at grazing the
    light arrives above z, where G is larger. Each lobe is scaled by its share above the horizon.

    Measured (shaders/check_math.py check_glossy grid, and the demo spheres' fitted SGs at the Draft camera):
    error / peak at n.v >= 0.5 falls from 0.20-0.27 to 0.03-0.05; on the spheres' texels the closed form against
    quadrature of the exact BRDF on the same SGs falls from 30/34/41 % to 5/4/9 % at roughness 0.3/0.4/0.5
    (sg_glossy_mirror_warp, the paper's form, is the comparison)."""
    z, _, _, ndotv = reflection_frame(normal, view)
    _, lam_d, mu_d = ndf_sg(normal, roughness)
    nu = sharpness / 2
    along_z = dot(axis, z)
    tangent = axis - along_z[..., None] * z  # the SG axis in the tangent plane at z
    facing = np.maximum(along_z, 0)
    total, factor = 0.0, None
    for amplitude_scale, sharpness_scale in lobes:
        lam, mu = lam_d * sharpness_scale, mu_d * amplitude_scale
        lam_in = lam / 8  # along the plane of v and l: any v.h
        lam_across = lam / (8 * ndotv**2)
        peak = z
        for _ in range(iterations):
            across = normalize_or_zero(np.cross(view, peak))
            d_in, d_across = lam_in + nu * facing, lam_across + nu * facing
            step = (nu / d_in)[..., None] * tangent + \
                (nu * dot(axis, across) * (1 / d_across - 1 / d_in))[..., None] * across
            peak = normalize_or_zero(z + step)
            half = normalize_or_zero(peak + view)
            vdoth = np.clip(dot(view, half), NDOTV_MIN, 1)
            lam_across = lam / (8 * vdoth**2)
        cosine = np.maximum(dot(axis, peak), 0)
        exponent = -0.5 * lam * dot(normal - half, normal - half) - 0.5 * sharpness * dot(axis - peak, axis - peak)
        width = np.pi / np.sqrt((lam_across + nu * cosine) * (lam_in + nu * cosine))
        above = horizon_fraction(dot(normal, peak), lam_in + nu * cosine)  # the lobe below it reflects nothing
        integral = amplitude * (mu * width * above * np.exp(exponent))[..., None]
        if factor is None:
            factor = microfacet_factor(normal, view, peak, half, ndotv, roughness, f0, metallic)
        total = total + integral * factor
    return total


# --- Diffuse: SG irradiance against a clamped cosine ------------------------------------------
def bessel_i_scaled(x):
    """e^{-x} i_l(x) for l = 0, 1, 2, 4 (modified spherical Bessel functions of the first kind).

    Power series below x = 1 (no cancellation), closed forms and upward recurrence above."""
    x = np.asarray(x)
    xs = np.minimum(x, 1.0)
    x2 = xs * xs

    def series(l, dfact):
        t, total = np.ones_like(xs), np.ones_like(xs)
        for k in range(1, 7):
            t = t * x2 / (2 * k * (2 * l + 2 * k + 1))
            total = total + t
        return xs**l / dfact * total * np.exp(-xs)

    xb = np.maximum(x, 1.0)
    e2 = np.exp(-2 * xb)
    i0 = (1 - e2) / (2 * xb)
    i1 = ((1 + e2) / 2 - i0) / xb
    i2 = i0 - 3 * i1 / xb
    i3 = i1 - 5 * i2 / xb
    i4 = i2 - 7 * i3 / xb
    small = x < 1.0
    return tuple(np.where(small, series(l, df), big)
                 for l, df, big in ((0, 1.0, i0), (1, 3.0, i1), (2, 15.0, i2), (4, 945.0, i4)))


def sg_irradiance_series(axis, sharpness, amplitude, normal):
    """Irradiance by the Funk-Hecke Legendre series up to l = 4 (error < 4e-4 of the lobe's
    energy for sharpness <= 4, measured against quadrature)."""
    c = np.clip(dot(axis, normal), -1, 1)
    i0, i1, i2, i4 = bessel_i_scaled(np.minimum(sharpness, IRRADIANCE_SERIES_MAX_SHARPNESS))
    p2 = 0.5 * (3 * c * c - 1)
    p4 = (35 * c**4 - 30 * c * c + 3) / 8
    k = CLAMPED_COSINE_LEGENDRE
    e = k[0] * i0 + 3 * k[1] * i1 * c + 5 * k[2] * i2 * p2 + 9 * k[4] * i4 * p4
    return amplitude * e[..., None]


def sg_irradiance_fitted(axis, sharpness, amplitude, normal):
    """Stephen Hill's fitted SG irradiance (2016) with the exact SG integral; used for sharpness >= 4
    (below that the fit is off by up to 34 % of the lobe's energy)."""
    lam = np.maximum(sharpness, IRRADIANCE_SERIES_MAX_SHARPNESS)
    mu_dot_n = np.clip(dot(axis, normal), -1, 1)
    c0 = 0.36
    c1 = 1 / (4 * c0)
    eml = np.exp(-lam)
    em2l = eml * eml
    rl = 1 / lam
    scale = 1 + 2 * em2l - rl
    bias = (eml - em2l) * rl - em2l
    x = np.sqrt(np.maximum(1 - scale, 0))
    x0 = c0 * mu_dot_n
    x1 = c1 * x
    n = x0 + x1
    y = np.where(np.abs(x0) <= x1, n * n / np.maximum(x, 1e-12), np.clip(mu_dot_n, 0, 1))
    normalized = np.maximum(scale * y + bias, 0)
    return sg_integral(lam, amplitude) * normalized[..., None]


def sg_irradiance(axis, sharpness, amplitude, normal):
    """Irradiance E(n) = integral SG(v) max(n.v, 0) dv: series for broad lobes, Hill's fit otherwise."""
    broad = (sharpness < IRRADIANCE_SERIES_MAX_SHARPNESS)[..., None]
    return np.where(broad, sg_irradiance_series(axis, sharpness, amplitude, normal),
                    sg_irradiance_fitted(axis, sharpness, amplitude, normal))


# --- Stored-parameter handling -----------------------------------------------------------------
def sanitize_sg_params(axis, sharpness, amplitude):
    """What every consumer applies to stored or interpolated SG parameters: renormalised axis,
    sharpness clamped to [SHARPNESS_MIN, SHARPNESS_MAX], amplitude >= 0; NaN becomes 0 / +Z."""
    axis = safe_normalize(np.nan_to_num(axis, nan=0.0, posinf=0.0, neginf=0.0))
    sharpness = np.clip(np.nan_to_num(sharpness, nan=SHARPNESS_MIN), SHARPNESS_MIN, SHARPNESS_MAX)
    amplitude = np.maximum(np.nan_to_num(amplitude, nan=0.0, posinf=0.0, neginf=0.0), 0)
    return axis, sharpness, amplitude


def sg_sum_eval(v, axes, sharpness, amplitudes):
    """Sum of N SGs at directions v. v (..., 3); axes (..., N, 3); sharpness (..., N);
    amplitudes (..., N, C). Returns (..., C)."""
    return sg_eval(v[..., None, :], axes, sharpness, amplitudes).sum(axis=-2)


def unit_midpoint(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """normalise(x + y): a blended axis or normal, as a shader renormalises it after interpolation."""
    total = np.asarray(x, np.float64) + y
    return total / np.maximum(np.linalg.norm(total, axis=-1, keepdims=True), 1e-8)


def midpoint_parameters(axis, sharpness, amplitude, a, b):
    """SG parameters halfway between texels a and b, as the node group's bilinear filter gives them at the midpoint:
    axes blended and renormalised, amplitudes blended, sharpness blended in the log encoding it is stored in
    (sg_shading.encode_sharpness), i.e. the geometric mean."""
    log_sharpness = np.log(np.maximum(sharpness, SHARPNESS_MIN))
    return (unit_midpoint(axis[a], axis[b]), np.exp(0.5 * (log_sharpness[a] + log_sharpness[b])),
            0.5 * (amplitude[a] + amplitude[b]))


def half_amplitude_scale(max_amplitude) -> float:
    """Scale that keeps stored amplitudes below the half-float limit (1 unless there are HDR suns)."""
    peak = float(np.nanmax(np.asarray(max_amplitude, dtype=np.float64), initial=0.0))
    return max(1.0, peak / (0.5 * AMPLITUDE_MAX_HALF)) if np.isfinite(peak) else 1.0


def pack_sg_half(axis, sharpness, amplitude, amplitude_scale=1.0):
    """Sanitised SG parameters as float16 arrays; amplitudes divided by `amplitude_scale`."""
    axis, sharpness, amplitude = sanitize_sg_params(axis, sharpness, amplitude)
    stored = np.minimum(amplitude / amplitude_scale, AMPLITUDE_MAX_HALF)
    return axis.astype(np.float16), sharpness.astype(np.float16), stored.astype(np.float16)


def unpack_sg_half(axis, sharpness, amplitude, amplitude_scale=1.0, dtype=np.float32):
    """Inverse of pack_sg_half, with the same sanitising a shader applies after interpolation."""
    axis, sharpness, amplitude = sanitize_sg_params(axis.astype(dtype), sharpness.astype(dtype), amplitude.astype(dtype))
    return axis, sharpness, amplitude * dtype(amplitude_scale)
