"""What the "SG Lightfield" node group computes, written once against a small set of operations.

`shade(ops, ...)` runs with `NumpyOps` (the numpy reference of the node group) or with the node backend in
shaders/node_group.py, which turns every operation into one Blender shader node. Both therefore follow the
same formula step by step; tests hold this reference to shaders/sg_math.py and a Cycles render of the
nodes to this reference.

Semantics follow Blender's math nodes where they differ from plain numpy: division by zero gives 0,
normalising a zero vector gives the zero vector, square roots of negatives give 0.

Glossy (Paper I section 6, DESIGN section 3): for every SG j of the texel, the SG convolved with the GGX NDF
(the SGs of sg_math.GGX_NDF_LOBES) warped to anisotropic SGs about the reflected view direction z (Xu et al.
2013), times Schlick Fresnel and
height-correlated Smith G over 4 (n.v). The ASG exponent is written frame-free across the plane of
incidence, -sy (1 - (u.z)^2) - (sx - sy) (u.x)^2, so normal incidence (x undefined) needs no fallback.
Environment: the same convolution of the environment's global SGs, times W_E(z) from the texel's IWEV SGs.
Diffuse: albedo x irradiance / pi, the irradiance read from its own texture tile (see apply.py for why).
The SH L2 baseline (the benchmark's encoder at equal bytes) swaps the glossy sum for the radiance's 9 SH
coefficients convolved with the same warped NDF, each lobe taken as the isotropic SG of equal solid-angle
integral (sharpness 2 sqrt(lam_x lam_y)): Funk-Hecke gives each band the SG's exact Legendre ratio
(sh_band_ratios).
"""
from __future__ import annotations

import math

import numpy as np

try:
    from .sg_math import GGX_NDF_LOBES, NDOTV_MIN, ROUGHNESS_MIN, SHARPNESS_MAX, SHARPNESS_MIN
except ImportError:
    from shaders.sg_math import GGX_NDF_LOBES, NDOTV_MIN, ROUGHNESS_MIN, SHARPNESS_MAX, SHARPNESS_MIN


class NumpyOps:
    """Scalars (...,) and vectors (..., 3) as numpy arrays, with Blender node semantics."""

    def barrier(self, value):
        """Order hint for the node backend (later lookups wait for `value`); nothing to do in numpy."""

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


def warped_lobe(ops, normal, view, roughness):
    """Per-pixel terms shared by every SG: n, v, z, x, n.v, alpha, and per NDF lobe (sharpness across the plane
    of incidence, sharpness along it, amplitude)."""
    n = ops.normalize(normal)
    v = ops.normalize(view)
    r = ops.clamp(roughness, ROUGHNESS_MIN, 1.0)
    alpha = ops.mul(r, r)
    a2 = ops.mul(alpha, alpha)
    lam_d = ops.div(ops.const(2.0), a2)
    mu_d = ops.div(ops.const(1.0 / math.pi), a2)
    ndotv = ops.clamp(ops.dot(n, v), NDOTV_MIN, 1.0)
    z = ops.normalize(ops.vsub(ops.vscale(n, ops.mul(ndotv, ops.const(2.0))), v))
    x = ops.normalize(ops.cross(n, z))
    lam_x = ops.div(lam_d, ops.mul(ops.const(8.0), ops.mul(ndotv, ndotv)))
    lam_y = ops.mul(lam_d, ops.const(1.0 / 8.0))
    lobes = [(ops.mul(lam_x, b), ops.mul(lam_y, b), ops.mul(mu_d, a)) for a, b in GGX_NDF_LOBES]
    return {"n": n, "v": v, "z": z, "x": x, "ndotv": ndotv, "lobes": lobes, "alpha": alpha}


def convolve(ops, lobe, axis, sharpness, amplitude):
    """One SG (axis, sharpness, colour amplitude) convolved with the warped NDF, lobe by lobe (Xu et al. 2013)."""
    axis = ops.normalize(axis)
    lam = ops.clamp(sharpness, SHARPNESS_MIN, SHARPNESS_MAX)
    amplitude = ops.vmax(amplitude, ops.vconst((0.0, 0.0, 0.0)))
    nu = ops.mul(lam, ops.const(0.5))
    c = ops.dot(axis, lobe["z"])
    a = ops.dot(axis, lobe["x"])
    across, cosine = ops.sub(ops.const(1.0), ops.mul(c, c)), ops.maximum(c, ops.const(0.0))
    weight = None
    for lam_x, lam_y, mu in lobe["lobes"]:
        nx = ops.add(nu, lam_x)
        ny = ops.add(nu, lam_y)
        sx = ops.div(ops.mul(nu, lam_x), nx)
        sy = ops.div(ops.mul(nu, lam_y), ny)
        scale = ops.div(ops.const(math.pi), ops.sqrt(ops.mul(nx, ny)))
        exponent = ops.sub(ops.mul(ops.sub(ops.const(0.0), sy), across), ops.mul(ops.sub(sx, sy), ops.mul(a, a)))
        term = ops.mul(ops.mul(mu, scale), ops.exp(exponent))
        weight = term if weight is None else ops.add(weight, term)
    return ops.vscale(amplitude, ops.mul(weight, cosine))


def microfacet_factor(ops, lobe, f0):
    """Fresnel (Schlick) x height-correlated Smith G / (4 n.v), evaluated at l = z: a colour."""
    h = ops.normalize(ops.vadd(lobe["z"], lobe["v"]))
    one_minus = ops.sub(ops.const(1.0), ops.clamp(ops.dot(lobe["v"], h), 0.0, 1.0))
    weight = ops.power(one_minus, 5.0)
    fresnel = ops.vadd(f0, ops.vscale(ops.vsub(ops.vconst((1.0, 1.0, 1.0)), f0), weight))
    ndotl = ops.clamp(ops.dot(lobe["n"], lobe["z"]), NDOTV_MIN, 1.0)
    alpha2 = ops.mul(lobe["alpha"], lobe["alpha"])

    def smith_lambda(c):
        c2 = ops.mul(c, c)
        return ops.mul(ops.const(0.5), ops.sub(ops.sqrt(ops.add(ops.const(1.0), ops.div(
            ops.mul(alpha2, ops.sub(ops.const(1.0), c2)), c2))), ops.const(1.0)))

    g = ops.div(ops.const(1.0), ops.add(ops.add(ops.const(1.0), smith_lambda(ndotl)), smith_lambda(lobe["ndotv"])))
    return ops.vscale(fresnel, ops.div(g, ops.mul(ops.const(4.0), lobe["ndotv"])))


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


def convolve_sh(ops, lobe, lookup):
    """Radiance given by SH L2 coefficients (lookup('sh', j) -> (colour, _)) integrated against the warped NDF:
    >= 0. Each lookup waits for the sum before it (the node backend's barrier, as for the SGs)."""
    band_weights = [ops.const(0.0)] * 3  # sum over the NDF lobes of integral x Legendre ratio, per band
    for lam_x, lam_y, mu in lobe["lobes"]:
        sharpness = ops.mul(ops.sqrt(ops.mul(lam_x, lam_y)), 2.0)
        integral = ops.div(ops.mul(mu, 2.0 * math.pi), sharpness)  # = mu pi / sqrt(lam_x lam_y), as convolve
        band_weights = [ops.add(w, ops.mul(integral, k)) for w, k in zip(band_weights, sh_band_ratios(ops, sharpness))]
    radiance = ops.vconst((0.0, 0.0, 0.0))
    for j, (band, basis) in enumerate(zip(SH_L2_BAND, sh_l2_basis(ops, lobe["z"]))):
        radiance = ops.vadd(radiance, ops.vscale(lookup("sh", j)[0], ops.mul(band_weights[band], basis)))
        ops.barrier(ops.vmax(radiance, ops.vconst((0.0, 0.0, 0.0))))
    return ops.vmax(radiance, ops.vconst((0.0, 0.0, 0.0)))


def shade(ops, lookup, normal, view, roughness, f0, albedo, sg_count: int, iwev_count: int = 0, env_sgs=(),
          has_irradiance: bool = True, sh_count: int = 0):
    """Colours {'glossy', 'diffuse', 'environment', 'total'}.

    lookup(name, j) -> (vector, alpha): 'sg' j: (axis, encoded sharpness); 'amp' j: (rgb amplitude, unused);
    'iwev' j: (axis, encoded sharpness); 'iwev_amp' j: (rgb amplitude, unused); 'irradiance' 0: (rgb, unused);
    'sh' j: (rgb SH L2 coefficient j, unused) when sh_count = SH_L2_COUNT (the SH baseline; sg_count is then 0).
    Sharpness travels in the alpha channel log-encoded to [0, 1] (encode_sharpness): image alpha is clamped
    to [0, 1] by the renderers, and interpolating log-sharpness is the better blend anyway.
    env_sgs: [(axis, sharpness, rgb amplitude)] global constants of the environment."""
    lobe = warped_lobe(ops, normal, view, roughness)
    black = ops.vconst((0.0, 0.0, 0.0))
    glossy = black
    for j in range(sg_count):
        axis, encoded = lookup("sg", j)
        amplitude, _ = lookup("amp", j)
        glossy = ops.vadd(glossy, convolve(ops, lobe, axis, decode_sharpness(ops, encoded), amplitude))
        ops.barrier(glossy)
    if sh_count:
        glossy = convolve_sh(ops, lobe, lookup)
    factor = microfacet_factor(ops, lobe, f0)
    glossy = ops.vmul(glossy, factor)
    environment = black
    if env_sgs and iwev_count:
        env = black
        for axis, sharpness, amplitude in env_sgs:
            env = ops.vadd(env, convolve(ops, lobe, ops.vconst(axis), ops.const(sharpness), ops.vconst(amplitude)))
        visibility = black
        for j in range(iwev_count):
            axis, encoded = lookup("iwev", j)
            amplitude, _ = lookup("iwev_amp", j)
            visibility = ops.vadd(visibility, sg_value(ops, lobe["z"], axis, decode_sharpness(ops, encoded), amplitude))
            ops.barrier(visibility)
        visibility = ops.vmax(ops.vmin(visibility, ops.vconst((1.0, 1.0, 1.0))), black)  # W_E in [0, 1]
        environment = ops.vmul(ops.vmul(env, factor), visibility)
    diffuse = black
    if has_irradiance:
        irradiance, _ = lookup("irradiance", 0)
        diffuse = ops.vscale(ops.vmul(albedo, ops.vmax(irradiance, black)), ops.const(1.0 / math.pi))
    total = ops.vadd(ops.vadd(glossy, environment), diffuse)
    return {"glossy": glossy, "diffuse": diffuse, "environment": environment, "total": total}
