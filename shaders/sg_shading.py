"""What the "SG Lightfield" node group computes, written once against a small set of operations.

`shade(ops, ...)` runs with `NumpyOps` (the numpy reference of the node group) or with the node backend in
shaders/node_group.py, which turns every operation into one Blender shader node. Both therefore follow the
same formula step by step; tests hold this reference to shaders/sg_math.py and a Cycles render of the
nodes to this reference.

Semantics follow Blender's math nodes where they differ from plain numpy: division by zero gives 0,
normalising a zero vector gives the zero vector, square roots of negatives give 0.

Glossy (Paper I section 6, DESIGN section 3): for every SG j of the texel, sg_math.sg_glossy (`glossy_sg`): the
SG times the two-lobe GGX NDF integrated by Laplace's method about their product's peak, with the NDF's warp to
light directions taken at that peak (not at the mirror direction z, Xu et al. 2013, which makes the lobe far too
narrow at grazing view), each lobe's share above the horizon, times the Fresnel (sg_math.fresnel) and
height-correlated Smith G over 4 (n.v) at the peak. The node backend builds `glossy_sg` once as a nested group
(`ops.call`) and instances it per SG. Environment: the same glossy of the environment's global SGs, times W_E(z)
from the texel's IWEV SGs. Diffuse: albedo x irradiance / pi, the irradiance read from its own texture tile (see
apply.py for why); under a dielectric's specular the albedo is scaled by 1 minus the split sum (split_sum_albedo).
The SH L2 baseline (the benchmark's encoder at equal bytes) swaps the glossy sum for the radiance's 9 SH
coefficients convolved with the NDF warped about z (GGX_NDF_LOBES), Fresnel and G taken at z; each warped lobe
is taken as the isotropic SG of equal solid-angle integral (sharpness 2 sqrt(lam_x lam_y)): Funk-Hecke gives
each band the SG's exact Legendre ratio (sh_band_ratios).
"""
from __future__ import annotations

import math

import numpy as np

from .sg_math import (DIELECTRIC_FRESNEL_IOR, GGX_NDF_LOBES, GLOSSY_NDF_LOBES, HORIZON_EXPONENT_MAX,
                      HORIZON_LOGISTIC, LOCAL_WARP_ITERATIONS, NDOTV_MIN, ROUGHNESS_MIN, SHARPNESS_MAX,
                      SHARPNESS_MIN)


class NumpyOps:
    """Scalars (...,) and vectors (..., 3) as numpy arrays, with Blender node semantics."""

    def barrier(self, value):
        """Order hint for the node backend (later lookups wait for `value`); nothing to do in numpy."""

    def call(self, name, function, **inputs):
        """function(ops, **inputs) -> {output: value}; the node backend builds it once as a nested group `name`."""
        return function(self, **inputs)

    def const(self, value):
        return np.float64(value)

    def vconst(self, value):
        return np.asarray(value, np.float64)

    def add(self, a, b):
        return np.add(a, b)

    def sub(self, a, b):
        return np.subtract(a, b)

    def mul(self, a, b):
        return np.multiply(a, b)

    def div(self, a, b):
        a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
        return np.divide(a, b, out=np.zeros_like(a), where=b != 0)

    def maximum(self, a, b):
        return np.maximum(a, b)

    def minimum(self, a, b):
        return np.minimum(a, b)

    def clamp(self, a, lo, hi):
        return np.clip(a, lo, hi)

    def exp(self, a):
        return np.exp(a)

    def sqrt(self, a):
        return np.sqrt(np.maximum(a, 0.0))

    def power(self, a, exponent: float):
        return np.power(np.maximum(a, 0.0), exponent)

    def dot(self, a, b):
        return np.sum(np.multiply(a, b), axis=-1)

    def cross(self, a, b):
        return np.cross(a, b)

    def normalize(self, a):
        length = np.linalg.norm(a, axis=-1, keepdims=True)
        return np.divide(a, length, out=np.zeros_like(np.asarray(a, np.float64)), where=length != 0)

    def vadd(self, a, b):
        return np.add(a, b)

    def vsub(self, a, b):
        return np.subtract(a, b)

    def vmul(self, a, b):  # componentwise
        return np.multiply(a, b)

    def vscale(self, a, s):
        return np.multiply(a, np.asarray(s)[..., None])

    def vmax(self, a, b):
        return np.maximum(a, b)

    def vmin(self, a, b):
        return np.minimum(a, b)


LOG_SHARPNESS_MIN, LOG_SHARPNESS_MAX = math.log(SHARPNESS_MIN), math.log(SHARPNESS_MAX)


def encode_sharpness(sharpness):
    """Sharpness -> [0, 1] for an alpha channel (numpy)."""
    log = np.log(np.clip(sharpness, SHARPNESS_MIN, SHARPNESS_MAX))
    return (log - LOG_SHARPNESS_MIN) / (LOG_SHARPNESS_MAX - LOG_SHARPNESS_MIN)


def decode_sharpness(ops, encoded):
    return ops.exp(ops.add(ops.const(LOG_SHARPNESS_MIN),
                           ops.mul(ops.clamp(encoded, 0.0, 1.0), ops.const(LOG_SHARPNESS_MAX - LOG_SHARPNESS_MIN))))


def pixel_terms(ops, normal, view, roughness):
    """Per-pixel terms shared by every SG: n, v (unit), z (the mirror direction), n.v (clamped), alpha, and the NDF
    SG's sharpness and amplitude (lam_d, mu_d)."""
    n = ops.normalize(normal)
    v = ops.normalize(view)
    r = ops.clamp(roughness, ROUGHNESS_MIN, 1.0)
    alpha = ops.mul(r, r)
    a2 = ops.mul(alpha, alpha)
    ndotv = ops.clamp(ops.dot(n, v), NDOTV_MIN, 1.0)
    z = ops.normalize(ops.vsub(ops.vscale(n, ops.mul(ndotv, ops.const(2.0))), v))
    return {"n": n, "v": v, "z": z, "ndotv": ndotv, "alpha": alpha, "lam_d": ops.div(ops.const(2.0), a2),
            "mu_d": ops.div(ops.const(1.0 / math.pi), a2)}


def mirror_warped_lobes(ops, pixel):
    """The NDF lobes of GGX_NDF_LOBES warped about z (Xu et al. 2013), as the SH baseline shades: per lobe
    (sharpness across the plane of incidence, sharpness along it, amplitude)."""
    ndotv = pixel["ndotv"]
    lam_x = ops.div(pixel["lam_d"], ops.mul(ops.const(8.0), ops.mul(ndotv, ndotv)))
    lam_y = ops.mul(pixel["lam_d"], ops.const(1.0 / 8.0))
    return [(ops.mul(lam_x, b), ops.mul(lam_y, b), ops.mul(pixel["mu_d"], a)) for a, b in GGX_NDF_LOBES]


def fresnel_weight(ops, cosine, metallic):
    """sg_math.fresnel's w: the dielectric's exact Fresnel (IOR 1.5) normalised to [0, 1], mixed by `metallic` with
    Schlick's (1 - cos)^5."""
    c = ops.clamp(cosine, 0.0, 1.0)
    g = ops.sqrt(ops.add(ops.mul(c, c), DIELECTRIC_FRESNEL_IOR ** 2 - 1.0))
    a = ops.div(ops.sub(g, c), ops.add(g, c))
    b = ops.div(ops.sub(ops.mul(c, ops.add(g, c)), 1.0), ops.add(ops.mul(c, ops.sub(g, c)), 1.0))
    at_normal = ((DIELECTRIC_FRESNEL_IOR - 1.0) / (DIELECTRIC_FRESNEL_IOR + 1.0)) ** 2
    exact = ops.mul(ops.mul(ops.mul(a, a), 0.5), ops.add(ops.mul(b, b), 1.0))
    dielectric = ops.mul(ops.sub(exact, at_normal), 1.0 / (1.0 - at_normal))
    schlick = ops.power(ops.sub(ops.const(1.0), c), 5.0)
    return ops.add(dielectric, ops.mul(metallic, ops.sub(schlick, dielectric)))


def microfacet_factor(ops, n, v, light, half, ndotv, alpha, f0, metallic):
    """Fresnel (sg_math.fresnel) at v.h x height-correlated Smith G / (4 n.v), for one light direction: a colour."""
    weight = fresnel_weight(ops, ops.dot(v, half), metallic)
    fresnel = ops.vadd(f0, ops.vscale(ops.vsub(ops.vconst((1.0, 1.0, 1.0)), f0), weight))
    ndotl = ops.clamp(ops.dot(n, light), NDOTV_MIN, 1.0)
    alpha2 = ops.mul(alpha, alpha)

    def smith_lambda(c):
        c2 = ops.mul(c, c)
        return ops.mul(ops.const(0.5), ops.sub(ops.sqrt(ops.add(ops.const(1.0), ops.div(
            ops.mul(alpha2, ops.sub(ops.const(1.0), c2)), c2))), ops.const(1.0)))

    g = ops.div(ops.const(1.0), ops.add(ops.add(ops.const(1.0), smith_lambda(ndotl)), smith_lambda(ndotv)))
    return ops.vscale(fresnel, ops.div(g, ops.mul(ops.const(4.0), ndotv)))


def horizon_fraction(ops, elevation, sharpness):
    """sg_math.horizon_fraction: the logistic share of a lobe above the horizon."""
    exponent = ops.mul(ops.mul(elevation, -HORIZON_LOGISTIC), ops.sqrt(ops.mul(sharpness, 2.0)))
    return ops.div(1.0, ops.add(1.0, ops.exp(ops.minimum(exponent, HORIZON_EXPONENT_MAX))))


def glossy_sg(ops, n, v, z, ndotv, lam_d, mu_d, alpha, f0, metallic, axis, sharpness, amplitude):
    """sg_math.sg_glossy of one SG (axis, sharpness, colour amplitude) step by step: {'glossy': colour}. The
    arguments after metallic are the SG's; the others before f0 are pixel_terms'."""
    axis = ops.normalize(axis)
    lam = ops.clamp(sharpness, SHARPNESS_MIN, SHARPNESS_MAX)
    amplitude = ops.vmax(amplitude, ops.vconst((0.0, 0.0, 0.0)))
    nu = ops.mul(lam, 0.5)
    along_z = ops.dot(axis, z)
    tangent = ops.vsub(axis, ops.vscale(z, along_z))  # the SG axis in the tangent plane at z
    nu_facing = ops.mul(nu, ops.maximum(along_z, 0.0))
    total = factor = None
    for amplitude_scale, sharpness_scale in GLOSSY_NDF_LOBES:
        lam_k, mu_k = ops.mul(lam_d, sharpness_scale), ops.mul(mu_d, amplitude_scale)
        lam_in = ops.mul(lam_k, 1.0 / 8.0)  # along the plane of v and l
        lam_across = ops.div(lam_k, ops.mul(ops.mul(ndotv, ndotv), 8.0))
        d_in = ops.add(lam_in, nu_facing)
        peak = z
        for _ in range(LOCAL_WARP_ITERATIONS):
            across = ops.normalize(ops.cross(v, peak))
            d_across = ops.add(lam_across, nu_facing)
            offset = ops.mul(ops.mul(nu, ops.dot(axis, across)), ops.sub(ops.div(1.0, d_across), ops.div(1.0, d_in)))
            step = ops.vadd(ops.vscale(tangent, ops.div(nu, d_in)), ops.vscale(across, offset))
            peak = ops.normalize(ops.vadd(z, step))
            half = ops.normalize(ops.vadd(peak, v))
            vdoth = ops.clamp(ops.dot(v, half), NDOTV_MIN, 1.0)
            lam_across = ops.div(lam_k, ops.mul(ops.mul(vdoth, vdoth), 8.0))
        nu_cosine = ops.mul(nu, ops.maximum(ops.dot(axis, peak), 0.0))
        to_normal, to_axis = ops.vsub(n, half), ops.vsub(axis, peak)
        exponent = ops.sub(ops.mul(ops.mul(lam_k, -0.5), ops.dot(to_normal, to_normal)),
                           ops.mul(nu, ops.dot(to_axis, to_axis)))
        width = ops.div(math.pi, ops.sqrt(ops.mul(ops.add(lam_across, nu_cosine), ops.add(lam_in, nu_cosine))))
        above = horizon_fraction(ops, ops.dot(n, peak), ops.add(lam_in, nu_cosine))
        term = ops.mul(ops.mul(ops.mul(mu_k, width), above), ops.exp(exponent))
        total = term if total is None else ops.add(total, term)
        if factor is None:
            factor = microfacet_factor(ops, n, v, peak, half, ndotv, alpha, f0, metallic)
    return {"glossy": ops.vmul(ops.vscale(amplitude, total), factor)}


def sg_value(ops, direction, axis, sharpness, amplitude):
    """amplitude * exp(sharpness (axis . direction - 1)) with the stored-parameter clamps (amplitude a vector)."""
    axis = ops.normalize(axis)
    lam = ops.clamp(sharpness, SHARPNESS_MIN, SHARPNESS_MAX)
    amplitude = ops.vmax(amplitude, ops.vconst((0.0, 0.0, 0.0)))
    return ops.vscale(amplitude, ops.exp(ops.mul(lam, ops.sub(ops.dot(axis, direction), ops.const(1.0)))))


SH_L2_COUNT = 9
SH_L2_BAND = (0, 1, 1, 1, 2, 2, 2, 2, 2)  # band l of each coefficient, in training.baselines.sh_basis order


def sh_l2_basis(ops, d):
    """The 9 real SH of band <= 2 at unit direction d (the order and constants of training.baselines.sh_basis)."""
    x, y, z = (ops.dot(d, ops.vconst(e)) for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    return [ops.const(0.282095), ops.mul(y, 0.488603), ops.mul(z, 0.488603), ops.mul(x, 0.488603),
            ops.mul(ops.mul(x, y), 1.092548), ops.mul(ops.mul(y, z), 1.092548),
            ops.mul(ops.sub(ops.mul(ops.mul(z, z), 3.0), 1.0), 0.315392), ops.mul(ops.mul(x, z), 1.092548),
            ops.mul(ops.sub(ops.mul(x, x), ops.mul(y, y)), 0.546274)]


def sh_band_ratios(ops, sharpness):
    """(1, k1, k2): the Legendre coefficients of exp(sharpness (t - 1)) over its integral, exactly:
    k1 = coth(s) - 1/s, k2 = 1 - 3 k1 / s (the recurrence of modified spherical Bessel functions)."""
    e = ops.exp(ops.mul(sharpness, -2.0))
    k1 = ops.sub(ops.div(ops.add(1.0, e), ops.sub(1.0, e)), ops.div(1.0, sharpness))
    return ops.const(1.0), k1, ops.sub(1.0, ops.div(ops.mul(k1, 3.0), sharpness))


def convolve_sh(ops, pixel, lookup):
    """Radiance given by SH L2 coefficients (lookup('sh', j) -> (colour, _)) integrated against the warped NDF:
    >= 0. Each lookup waits for the sum before it (the node backend's barrier, as for the SGs)."""
    band_weights = [ops.const(0.0)] * 3  # sum over the NDF lobes of integral x Legendre ratio, per band
    for lam_x, lam_y, mu in mirror_warped_lobes(ops, pixel):
        sharpness = ops.mul(ops.sqrt(ops.mul(lam_x, lam_y)), 2.0)
        integral = ops.div(ops.mul(mu, 2.0 * math.pi), sharpness)  # = mu pi / sqrt(lam_x lam_y), as sg_asg_convolve
        band_weights = [ops.add(w, ops.mul(integral, k)) for w, k in zip(band_weights, sh_band_ratios(ops, sharpness))]
    radiance = ops.vconst((0.0, 0.0, 0.0))
    for j, (band, basis) in enumerate(zip(SH_L2_BAND, sh_l2_basis(ops, pixel["z"]))):
        radiance = ops.vadd(radiance, ops.vscale(lookup("sh", j)[0], ops.mul(band_weights[band], basis)))
        ops.barrier(ops.vmax(radiance, ops.vconst((0.0, 0.0, 0.0))))
    return ops.vmax(radiance, ops.vconst((0.0, 0.0, 0.0)))


# The split-sum GGX directional albedo, F0 * scale + bias (Schlick Fresnel is linear in F0), as Chebyshev series
# sum c[i][j] T_i(x) T_j(y) with x, y mapping sqrt(roughness) and (n.v)^(1/4) over [ROUGHNESS_MIN, 1] and
# [NDOTV_MIN, 1] onto [-1, 1] (well conditioned in float32, unlike monomials of this degree). Least squares on a 26 x 30
# grid of importance-sampled quadratures of sg_math.ggx_brdf_cos; against 150 random points off the grid within 0.009
# (scale) and 0.011 (bias), at roughness >= 0.55 within 0.007 and 0.005 (tests/test_math_quadrature.py).
SPLIT_SUM_SCALE = (
    (0.660232, 0.151590, 0.034332, -0.035124, -0.020134, 0.005480, 0.006332, 0.000883),
    (0.132502, -0.470330, -0.072482, 0.082832, 0.026453, -0.015653, -0.006777, 0.000655),
    (-0.091737, -0.025800, -0.043099, -0.018566, 0.010362, 0.007096, -0.001920, -0.001240),
    (-0.037799, 0.010156, 0.010552, -0.013729, -0.014166, 0.003856, 0.005363, -0.001074),
    (0.013186, -0.007708, 0.004815, 0.009232, -0.002229, -0.007119, 0.000117, 0.002548),
    (0.004475, 0.004725, -0.000153, 0.002521, 0.005812, 0.000363, -0.004170, -0.000632),
)
SPLIT_SUM_BIAS = (
    (0.232203, -0.245781, -0.038430, 0.041260, 0.024499, -0.007661, -0.007393, 0.001014),
    (-0.260325, 0.281238, 0.041082, -0.051372, -0.030660, 0.013958, 0.009332, -0.003367),
    (0.036986, -0.051301, 0.003762, 0.014720, 0.003514, -0.011124, 0.000615, 0.004520),
    (0.025672, -0.022843, -0.009140, 0.001664, 0.005280, 0.005166, -0.005948, -0.002137),
    (-0.010687, 0.013059, 0.000759, -0.002725, -0.002749, -0.000309, 0.005195, -0.001152),
    (-0.001273, -0.000644, 0.002480, 0.000091, -0.000015, -0.001214, -0.001903, 0.002982),
)


# The dielectric's extra: the F0 = 0 albedo with sg_math.fresnel's dielectric w minus Schlick's, on the same series
# (shaders/check_math.py fit_split_sum_dielectric: a 26 x 30 grid of the quadrature).
SPLIT_SUM_DIELECTRIC = (
    (-0.002144, 0.006295, 0.002479, -0.004346, -0.005495, -0.000180, 0.002862, 0.001376),
    (0.008227, -0.008842, -0.005930, 0.004024, 0.007169, 0.000208, -0.003876, -0.001571),
    (0.000806, -0.003561, 0.002265, 0.001106, -0.001179, 0.000212, 0.000853, -0.000220),
    (-0.003572, 0.003910, 0.000458, -0.000831, -0.000648, -0.000312, 0.000477, 0.000598),
    (0.000467, -0.000117, -0.000258, -0.000233, 0.000181, 0.000139, -0.000368, -0.000126),
    (0.000866, -0.000839, -0.000240, 0.000292, 0.000080, -0.000031, 0.000063, -0.000160),
)


def _chebyshev(ops, x, degree: int) -> list:
    """T_0(x) .. T_degree(x) by the recurrence T_n = 2 x T_(n-1) - T_(n-2)."""
    values = [ops.const(1.0), x]
    for _ in range(degree - 1):
        values.append(ops.sub(ops.mul(ops.mul(x, values[-1]), ops.const(2.0)), values[-2]))
    return values[:degree + 1]


def _split_sum_chebyshev(ops, roughness, ndotv, degrees):
    """T_0..T_degrees[0] of sqrt(roughness) and T_0..T_degrees[1] of (n.v)^(1/4), each mapped onto [-1, 1]."""
    def unit_interval(value, low):  # [low, 1] -> [-1, 1]
        return ops.sub(ops.mul(ops.sub(value, ops.const(low)), ops.const(2.0 / (1.0 - low))), ops.const(1.0))

    x = unit_interval(ops.sqrt(ops.clamp(roughness, ROUGHNESS_MIN, 1.0)), math.sqrt(ROUGHNESS_MIN))
    y = unit_interval(ops.sqrt(ops.sqrt(ops.clamp(ndotv, NDOTV_MIN, 1.0))), math.sqrt(math.sqrt(NDOTV_MIN)))
    return _chebyshev(ops, x, degrees[0]), _chebyshev(ops, y, degrees[1])


def split_sum_series_basis(ops, roughness, ndotv, degrees):
    """(points, terms) numpy array of T_i(x) T_j(y), i-major: the split sum's least-squares basis (NumpyOps)."""
    tx, ty = _split_sum_chebyshev(ops, np.asarray(roughness), np.asarray(ndotv), degrees)
    return np.stack(np.broadcast_arrays(*(a * b for a in tx for b in ty)), -1)


def split_sum_albedo(ops, f0, roughness, ndotv, metallic):
    """GGX directional albedo (a colour): the fraction of uniform light a surface reflects specularly towards v.
    Times E / pi it is the specular of an irradiance-lightmapped material; 1 minus it is what the diffuse under a
    dielectric's specular receives (as Principled layers them). With sg_math.fresnel, F0 + (1 - F0) w: F0 scale +
    bias for Schlick's w, plus (1 - F0) (1 - metallic) the dielectric's extra over Schlick's."""
    degrees = (len(SPLIT_SUM_SCALE) - 1, len(SPLIT_SUM_SCALE[0]) - 1)
    tx, ty = _split_sum_chebyshev(ops, roughness, ndotv, degrees)

    def series(coefficients):
        total = None
        for t_i, row in zip(tx, coefficients):
            inner = ops.const(row[0])
            for t_j, c in zip(ty[1:], row[1:]):
                inner = ops.add(inner, ops.mul(t_j, ops.const(c)))
            term = ops.mul(t_i, inner)
            total = term if total is None else ops.add(total, term)
        return total

    scale, bias, extra = series(SPLIT_SUM_SCALE), series(SPLIT_SUM_BIAS), series(SPLIT_SUM_DIELECTRIC)
    white = ops.vconst((1.0, 1.0, 1.0))
    schlick = ops.vadd(ops.vscale(f0, scale), ops.vscale(white, bias))
    return ops.vadd(schlick, ops.vscale(ops.vsub(white, f0), ops.mul(extra, ops.sub(1.0, metallic))))


def shade(ops, lookup, normal, view, roughness, f0, albedo, sg_count: int, iwev_count: int = 0, env_sgs=(),
          has_irradiance: bool = True, sh_count: int = 0, metallic=0.0):
    """Colours {'glossy', 'diffuse', 'environment', 'total', 'irradiance'} ('irradiance': E / pi, what a white
    Lambertian surface shows: a Diffuse BSDF of any colour is that colour times it).

    lookup(name, j) -> (vector, alpha): 'sg' j: (axis, encoded sharpness); 'amp' j: (rgb amplitude, unused);
    'iwev' j: (axis, encoded sharpness); 'iwev_amp' j: (rgb amplitude, unused); 'irradiance' 0: (rgb, unused);
    'sh' j: (rgb SH L2 coefficient j, unused) when sh_count = SH_L2_COUNT (the SH baseline; sg_count is then 0).
    Sharpness travels in the alpha channel log-encoded to [0, 1] (encode_sharpness): image alpha is clamped
    to [0, 1] by the renderers, and interpolating log-sharpness is the better blend anyway.
    env_sgs: [(axis, sharpness, rgb amplitude)] global constants of the environment. metallic: the share of the
    Fresnel that takes the metal's shape (sg_math.fresnel)."""
    pixel = pixel_terms(ops, normal, view, roughness)

    def glossy_of(axis, sharpness, amplitude):  # one Group node per SG in the node backend
        return ops.call("glossy SG", glossy_sg, **pixel, f0=f0, metallic=metallic, axis=axis, sharpness=sharpness,
                        amplitude=amplitude)["glossy"]

    black = ops.vconst((0.0, 0.0, 0.0))
    glossy = black
    for j in range(sg_count):
        axis, encoded = lookup("sg", j)
        amplitude, _ = lookup("amp", j)
        glossy = ops.vadd(glossy, glossy_of(axis, decode_sharpness(ops, encoded), amplitude))
        ops.barrier(glossy)
    if sh_count:
        z = pixel["z"]
        factor = microfacet_factor(ops, pixel["n"], pixel["v"], z, ops.normalize(ops.vadd(z, pixel["v"])),
                                   pixel["ndotv"], pixel["alpha"], f0, metallic)
        glossy = ops.vmul(convolve_sh(ops, pixel, lookup), factor)
    environment = black
    if env_sgs and iwev_count:
        def environment_glossy(env_ops, **pixel_inputs):  # one Group node in the node backend; the SGs are its constants
            env = env_ops.vconst((0.0, 0.0, 0.0))
            for axis, sharpness, amplitude in env_sgs:
                env = env_ops.vadd(env, env_ops.call("glossy SG", glossy_sg, **pixel_inputs, axis=env_ops.vconst(axis),
                                                     sharpness=env_ops.const(sharpness),
                                                     amplitude=env_ops.vconst(amplitude))["glossy"])
            return {"glossy": env}

        env = ops.call("environment", environment_glossy, **pixel, f0=f0, metallic=metallic)["glossy"]
        visibility = black
        for j in range(iwev_count):
            axis, encoded = lookup("iwev", j)
            amplitude, _ = lookup("iwev_amp", j)
            value = ops.call("SG value", lambda value_ops, **sg: {"value": sg_value(value_ops, **sg)},
                             direction=pixel["z"], axis=axis, sharpness=decode_sharpness(ops, encoded),
                             amplitude=amplitude)["value"]
            visibility = ops.vadd(visibility, value)
            ops.barrier(visibility)
        visibility = ops.vmax(ops.vmin(visibility, ops.vconst((1.0, 1.0, 1.0))), black)  # W_E in [0, 1]
        environment = ops.vmul(env, visibility)
    diffuse = uniform_radiance = black
    if has_irradiance:
        irradiance, _ = lookup("irradiance", 0)
        uniform_radiance = ops.vscale(ops.vmax(irradiance, black), ops.const(1.0 / math.pi))
        # The diffuse under the specular gets what the specular leaves, as Principled layers them (a white furnace
        # in Cycles: tests/test_apply.py). Without SGs (an irradiance lightmap) the specular is the split sum too.
        specular_albedo = split_sum_albedo(ops, f0, roughness, pixel["ndotv"], metallic)
        if not sg_count and not sh_count:
            glossy = ops.vmul(specular_albedo, uniform_radiance)
        albedo = ops.vmul(albedo, ops.vmax(ops.vsub(ops.vconst((1.0, 1.0, 1.0)), specular_albedo), black))
        diffuse = ops.vmul(albedo, uniform_radiance)
    total = ops.vadd(ops.vadd(glossy, environment), diffuse)
    return {"glossy": glossy, "diffuse": diffuse, "environment": environment, "total": total,
            "irradiance": uniform_radiance}
