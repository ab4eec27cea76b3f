"""Check every SG identity against a >= 1e6-point sphere quadrature and print a table.

    python -m shaders.check_math            # full grid (about two minutes on 2 cores)
    python -m shaders.check_math --quick    # corners of the grid only

Errors are relative. Exact identities use the reference value; approximations (the SG x ASG
convolution, the glossy lobe, irradiance) use the response at the lobe's peak, so a tiny value in a
tail does not count as a huge error. The tests call the same functions with stated tolerances.
"""
from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import dataclass, field

import numpy as np

from . import octahedral as octa
from . import sg_math as m
from .quadrature import adaptive_sphere_quadrature, fibonacci_sphere, frame_from_z, sg_width

MIN_POINTS = 1_000_000
SHARPNESS_GRID = (1e-4, 1e-2, 1.0, 10.0, 100.0, 1e3, 1e4)
AMPLITUDE_GRID = (1.0, 1e5)
ROUGHNESS_GRID = (m.ROUGHNESS_MIN, 0.2, 0.3, 0.5, 1.0)
NDOTV_GRID = (1.0, 0.5, 0.1, 0.01)
UNDERFLOW = 1e-250  # reference values below this are skipped (both sides underflow to ~0)


@dataclass
class CheckResult:
    identity: str
    max_rel_error: float
    cases: int
    covered: str
    note: str = ""
    worst_case: dict = field(default_factory=dict)

    def row(self):
        return (self.identity, f"{self.max_rel_error:.2e}", str(self.cases), self.covered, self.note)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _rotate_towards(d, t, angle):
    """Rotate unit d by `angle` towards the unit tangent t (t perpendicular to d)."""
    return _unit(np.cos(angle) * d + np.sin(angle) * t)


class _Worst:
    def __init__(self):
        self.err, self.case, self.n = 0.0, {}, 0

    def add(self, err, **case):
        self.n += 1
        if not np.isfinite(err) or err > self.err:
            self.err, self.case = float(err), case


# --- exact identities -----------------------------------------------------------------------------
def check_sg_integral(sharpness=SHARPNESS_GRID, amplitudes=AMPLITUDE_GRID, min_points=MIN_POINTS):
    w = _Worst()
    axis = _unit([0.3, -0.5, 0.8])
    for lam, amp in itertools.product(sharpness, amplitudes):
        d, q = adaptive_sphere_quadrature(frame_from_z(axis), [(axis, sg_width(lam), sg_width(lam))],
                                          min_points=min_points)
        ref = np.sum(m.sg_eval(d, axis, np.float64(lam), np.array([amp]))[:, 0] * q)
        got = m.sg_integral(np.float64(lam), np.array([amp]))[0]
        w.add(abs(got - ref) / ref, sharpness=lam, amplitude=amp)
    return CheckResult("SG integral 2pi mu (1-e^-2l)/l", w.err, w.n,
                       f"sharpness {min(sharpness):g}..{max(sharpness):g}, mu up to {max(amplitudes):g}",
                       worst_case=w.case)


def _inner_product_cases(sharpness, angles_deg, min_points, formula):
    w = _Worst()
    u1 = _unit([0.0, 0.0, 1.0])
    for l1, l2, ang in itertools.product(sharpness, sharpness, angles_deg):
        u2 = _rotate_towards(u1, np.array([1.0, 0, 0]), np.radians(ang))
        combined = l1 * u1 + l2 * u2
        peak = _unit(combined) if np.linalg.norm(combined) > 1e-12 else u1
        frame = frame_from_z(peak)
        width = sg_width(l1 + l2)
        d, q = adaptive_sphere_quadrature(
            frame, [(peak, width, width), (u1, sg_width(l1), sg_width(l1)), (u2, sg_width(l2), sg_width(l2))],
            min_points=min_points)
        ref = np.sum(m.sg_eval(d, u1, np.float64(l1), np.ones(1))[:, 0]
                     * m.sg_eval(d, u2, np.float64(l2), np.ones(1))[:, 0] * q)
        if ref < UNDERFLOW:
            continue
        got = formula(u1, np.float64(l1), u2, np.float64(l2))
        w.add(abs(got - ref) / ref, sharpness1=l1, sharpness2=l2, angle_deg=ang)
    return w


def check_sg_inner_product(sharpness=SHARPNESS_GRID, angles_deg=(0, 60, 120, 180), min_points=MIN_POINTS):
    w = _inner_product_cases(sharpness, angles_deg, min_points,
                             lambda u1, l1, u2, l2: m.sg_inner_product(u1, l1, np.ones(1), u2, l2, np.ones(1))[0])
    return CheckResult("SG.SG inner product", w.err, w.n,
                       f"sharpness {min(sharpness):g}..{max(sharpness):g} each, axes {angles_deg} deg",
                       worst_case=w.case)


def thesis_inner_product_eq21(u1, l1, u2, l2):
    """Paper I Eq. 21-23 as printed: 4 pi a1 a2 sinh(|mu_m|) / (e^{l_m} |mu_m|), mu_m averaged."""
    lm = l1 + l2
    mum = np.linalg.norm((l1 * u1 + l2 * u2) / lm)
    return 4 * np.pi * np.sinh(mum) / (np.exp(lm) * max(mum, 1e-300))


def check_thesis_inner_product(sharpness=(1.0, 10.0, 100.0), angles_deg=(0, 60, 120), min_points=MIN_POINTS):
    w = _inner_product_cases(sharpness, angles_deg, min_points, thesis_inner_product_eq21)
    return CheckResult("thesis Eq.21-23 inner product", w.err, w.n,
                       f"sharpness {min(sharpness):g}..{max(sharpness):g}", note="MISPRINT: not the integral",
                       worst_case=w.case)


# --- approximations ---------------------------------------------------------------------------
def _asg_for(roughness, ndotv):
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([np.sqrt(1 - ndotv**2), 0.0, ndotv])
    return n, v, m.warp_ndf_to_asg(n, v, np.float64(roughness))


def _asg_widths(asg):
    return (float(min(np.pi, 1 / np.sqrt(2 * asg.sharpness_x))), float(min(np.pi, 1 / np.sqrt(2 * asg.sharpness_y))))


def _offset_axes(asg, lam):
    """SG axes to test: on the ASG's axis, and one combined width off it along x and along y."""
    wx, wy = _asg_widths(asg)
    sg = sg_width(lam)
    ox = min(np.sqrt(wx**2 + sg**2), np.radians(60))
    oy = min(np.sqrt(wy**2 + sg**2), np.radians(60))
    return {"on-axis": asg.z, "off-x": _rotate_towards(asg.z, asg.x, ox), "off-y": _rotate_towards(asg.z, asg.y, oy)}


def _convolution_cases(sharpness, roughness, ndotv, min_points, formula):
    w = _Worst()
    for lam, r, c in itertools.product(sharpness, roughness, ndotv):
        _, _, asg = _asg_for(r, c)
        wx, wy = _asg_widths(asg)
        frame = (asg.x, asg.y, asg.z)
        peak_value = None
        for name, axis in _offset_axes(asg, lam).items():
            d, q = adaptive_sphere_quadrature(
                frame, [(asg.z, wx, wy), (axis, sg_width(lam), sg_width(lam))], min_points=min_points,
                hemisphere=True)
            ref = np.sum(m.sg_eval(d, axis, np.float64(lam), np.ones(1))[:, 0] * m.asg_eval(d, asg) * q)
            if peak_value is None:
                peak_value = ref
            got = formula(axis, np.float64(lam), asg)
            w.add(abs(got - ref) / peak_value, sharpness=lam, roughness=r, ndotv=c, axis=name)
    return w


def check_sg_asg_convolution(sharpness=SHARPNESS_GRID, roughness=ROUGHNESS_GRID, ndotv=NDOTV_GRID,
                             min_points=MIN_POINTS):
    w = _convolution_cases(sharpness, roughness, ndotv, min_points,
                           lambda a, l, asg: m.sg_asg_convolve(a, l, np.ones(1), asg)[0])
    return CheckResult("SG x ASG convolution (Xu 2013)", w.err, w.n,
                       f"sharpness {min(sharpness):g}..{max(sharpness):g}, roughness {min(roughness):g}..{max(roughness):g}, "
                       f"n.v {min(ndotv):g}..{max(ndotv):g}, on/off axis", note="approximation; error / peak",
                       worst_case=w.case)


def thesis_convolution_eq24(axis, lam, asg):
    """Paper I Eq. 24 as printed: the ASG's own sharpnesses, no bandwidth change."""
    scale = np.pi / np.sqrt((lam / 2 + asg.sharpness_x) * (lam / 2 + asg.sharpness_y))
    a, b = axis @ asg.x, axis @ asg.y
    return asg.amplitude * scale * max(axis @ asg.z, 0) * np.exp(-asg.sharpness_x * a * a - asg.sharpness_y * b * b)


def check_thesis_convolution(sharpness=(10.0, 100.0), roughness=(0.3, 0.5), ndotv=(1.0, 0.5), min_points=MIN_POINTS):
    w = _convolution_cases(sharpness, roughness, ndotv, min_points, thesis_convolution_eq24)
    return CheckResult("thesis Eq.24 SG x ASG", w.err, w.n, "same grid, a corner", note="MISPRINT: no bandwidth change",
                       worst_case=w.case)


def check_glossy(sharpness=(1.0, 10.0, 100.0, 1e3, 1e4), roughness=ROUGHNESS_GRID, ndotv=NDOTV_GRID,
                 min_points=MIN_POINTS, f0=0.04, glossy=None):
    """One SG's glossy contribution (`glossy`, default sg_math.sg_glossy) vs quadrature of the exact GGX BRDF
    (same F and G) times the SG."""
    glossy = glossy or m.sg_glossy
    per_roughness = {}
    for r in roughness:
        w = _Worst()
        for lam, c in itertools.product(sharpness, ndotv):
            n, v, asg = _asg_for(r, c)
            wx, wy = _asg_widths(asg)
            frame = (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), n)  # x in the plane of incidence
            peak_value = None
            for name, axis in _offset_axes(asg, lam).items():
                d, q = adaptive_sphere_quadrature(
                    frame, [(asg.z, wy, wx), (axis, sg_width(lam), sg_width(lam))], min_points=min_points,
                    hemisphere=True)
                integrand = m.sg_eval(d, axis, np.float64(lam), np.ones(1))[:, 0] * \
                    m.ggx_brdf_cos(d, v, n, np.float64(r), np.array([f0]))[:, 0]
                ref = np.sum(integrand * q)
                if peak_value is None:
                    peak_value = ref
                got = glossy(axis, np.float64(lam), np.ones(1), n, v, np.float64(r), np.array([f0]))[0]
                w.add(abs(got - ref) / peak_value, sharpness=lam, ndotv=c, axis=name)
        per_roughness[r] = w
    return [CheckResult(f"glossy of one SG, roughness {r:g}", w.err, w.n,
                        f"SG sharpness {min(sharpness):g}..{max(sharpness):g}, n.v {min(ndotv):g}..{max(ndotv):g}",
                        note="approximation; error / peak", worst_case=w.case)
            for r, w in per_roughness.items()]


def check_irradiance(sharpness=SHARPNESS_GRID + (0.5, 2.0, 3.99, 4.0, 30.0), cosines=np.linspace(-1, 1, 9),
                     min_points=MIN_POINTS):
    w = _Worst()
    n = np.array([0.0, 0.0, 1.0])
    frame = frame_from_z(n, np.array([1.0, 0, 0]))
    for lam, c in itertools.product(sharpness, cosines):
        axis = np.array([np.sqrt(max(1 - c * c, 0)), 0.0, c])
        d, q = adaptive_sphere_quadrature(frame, [(axis, sg_width(lam), sg_width(lam))], min_points=min_points)
        ref = np.sum(m.sg_eval(d, axis, np.float64(lam), np.ones(1))[:, 0] * np.maximum(d @ n, 0) * q)
        got = m.sg_irradiance(axis, np.float64(lam), np.ones(1), n)[0]
        energy = m.sg_integral(np.float64(lam), np.ones(1))[0]
        w.add(abs(got - ref) / energy, sharpness=lam, cos=float(c))
    return CheckResult("SG irradiance (series <4, Hill fit)", w.err, w.n,
                       f"sharpness {min(sharpness):g}..{max(sharpness):g}, all axis-normal angles",
                       note="approximation; error / lobe energy", worst_case=w.case)


# --- GGX NDF as a sum of SGs (sg_math.GGX_NDF_TWO_LOBES) ---------------------------------------------
_NDF_T = np.linspace(0.0, 12.0, 4000)  # t = tan(theta) / alpha; beyond 12 the shape is below 5e-5 of its peak


def ggx_ndf_shape_error(lobes) -> float:
    """Relative L2 error, weighted by area (t dt), of sum a exp(-b t^2) against GGX's shape (1 + t^2)^-2."""
    shape = (1 + _NDF_T**2) ** -2
    fitted = sum(a * np.exp(-b * _NDF_T**2) for a, b in lobes)
    weight = np.sqrt(_NDF_T + 1e-3)
    return float(np.sqrt(np.sum(((fitted - shape) * weight) ** 2) / np.sum((shape * weight) ** 2)))


def fit_ggx_ndf_lobes():
    """The two SGs of sg_math.GGX_NDF_TWO_LOBES: least squares of ggx_ndf_shape_error with the projected integral held
    at 1 (a1/b1 + a2/b2 = 1, so a2 follows from the other three). Returns ((a1, b1), (a2, b2))."""
    from scipy.optimize import least_squares

    shape = (1 + _NDF_T**2) ** -2
    weight = np.sqrt(_NDF_T + 1e-3)

    def lobes(p):
        a1, b1, b2 = p
        return (a1, b1), ((1 - a1 / b1) * b2, b2)

    def residual(p):
        return (sum(a * np.exp(-b * _NDF_T**2) for a, b in lobes(p)) - shape) * weight

    fit = least_squares(residual, [0.8, 1.5, 0.3], bounds=([0.0, 0.1, 0.01], [5.0, 20.0, 5.0]), xtol=1e-12,
                        ftol=1e-12)
    return lobes(fit.x)


def check_ggx_ndf_lobes():
    return CheckResult("GGX NDF as two SGs (shape, t dt)", ggx_ndf_shape_error(m.GGX_NDF_TWO_LOBES), len(_NDF_T),
                       "t = tan(theta)/alpha in 0..12",
                       note=f"one SG: {ggx_ndf_shape_error(m.GGX_NDF_PEAK_MATCHED):.3f}")


# --- GGX directional albedo (the split sum of shaders/sg_shading.py) ------------------------------------
def directional_albedo(roughness, ndotv, f0, metallic=0.0, n=300):
    """Hemisphere integral of the reference integrand ggx_brdf_cos towards a view at `ndotv`, importance-sampling the
    GGX NDF on a stratified n x n grid (a uniform quadrature cannot resolve the lobes of low roughness)."""
    alpha = m.ggx_alpha(roughness)
    u1, u2 = (g.ravel() for g in np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij"))
    cos_h = np.sqrt((1 - u1) / (1 + (alpha**2 - 1) * u1))
    sin_h, phi = np.sqrt(1 - cos_h**2), 2 * np.pi * u2
    h = np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], -1)
    view = np.array([np.sqrt(1 - ndotv**2), 0.0, ndotv])
    vdoth = h @ view
    light = 2 * vdoth[:, None] * h - view
    pdf = m.ggx_ndf(cos_h, alpha) * cos_h / (4 * np.maximum(vdoth, 1e-12))  # of the light direction
    value = m.ggx_brdf_cos(light, np.broadcast_to(view, light.shape), np.broadcast_to((0.0, 0.0, 1.0), light.shape),
                           roughness, np.broadcast_to(f0, light.shape), metallic)
    return np.where((vdoth > 0)[:, None], value / np.maximum(pdf, 1e-30)[:, None], 0.0).mean(axis=0)


def split_sum_grid(rows=26, columns=30):
    """(roughness, n.v) of the split sum's fitting grid: even steps in its variables sqrt(roughness), (n.v)^(1/4)."""
    x = np.linspace(np.sqrt(m.ROUGHNESS_MIN), 1.0, rows) ** 2
    y = np.linspace(m.NDOTV_MIN ** 0.25, 1.0, columns) ** 4
    return x, y


def fit_split_sum_dielectric(degrees=(5, 7)):
    """SPLIT_SUM_DIELECTRIC of shaders/sg_shading.py: Chebyshev coefficients (as split_sum_albedo reads them) of the
    directional albedo's F0 = 0 part with the dielectric's Fresnel shape minus that with Schlick's, least squares over
    split_sum_grid. Returns rows of rounded coefficients."""
    from .sg_shading import NumpyOps, split_sum_series_basis

    roughness, ndotv = split_sum_grid()
    r, v = (g.ravel() for g in np.meshgrid(roughness, ndotv, indexing="ij"))
    target = np.array([directional_albedo(a, b, np.zeros(1), 0.0)[0] - directional_albedo(a, b, np.zeros(1), 1.0)[0]
                       for a, b in zip(r, v)])
    basis = split_sum_series_basis(NumpyOps(), r, v, degrees)  # (points, terms)
    coefficients, *_ = np.linalg.lstsq(basis, target, rcond=None)
    return tuple(tuple(round(float(c), 6) for c in row) for row in coefficients.reshape(degrees[0] + 1, degrees[1] + 1))


def check_fresnel(iors=(1.33, 1.45, 1.6, 2.0), cosines=np.linspace(0.0, 1.0, 1001)):
    """The dielectric Fresnel shape of IOR 1.5 (sg_math.fresnel_dielectric_weight) against the normalised shape at
    other IORs, and Schlick's against it."""
    shape = m.fresnel_dielectric_weight(cosines)
    worst = 0.0
    for eta in iors:
        f0 = m.fresnel_dielectric(1.0, eta)
        worst = max(worst, float(np.max(np.abs((m.fresnel_dielectric(cosines, eta) - f0) / (1 - f0) - shape))))
    schlick = float(np.max(np.abs((1 - cosines) ** 5 - shape)))
    return CheckResult("dielectric Fresnel shape, IOR 1.5 (absolute)", worst, len(iors) * len(cosines),
                       f"IOR {iors}, cos 0..1", note=f"Schlick's: {schlick:.3f}")


# --- octahedral map -------------------------------------------------------------------------------
def check_solid_angle_sum(resolutions=(1, 2, 3, 7, 8, 16, 33, 64, 128)):
    err = max(abs(octa.pixel_solid_angles(r).sum() - 4 * np.pi) / (4 * np.pi) for r in resolutions)
    return CheckResult("octahedral solid angles sum to 4pi", err, len(resolutions),
                       f"R in {resolutions}", note="exact clipping at the folds")


def check_solid_angle_pixels(resolutions=(4, 7, 16), subsamples=192):
    """Per-pixel solid angle vs a midpoint rule of dw = du dv / |p|^3 on the octahedron."""
    worst = 0.0
    for r in resolutions:
        n = r * subsamples
        c = ((np.arange(n) + 0.5) / n) * 2 - 1
        u, v = np.meshgrid(c, c, indexing="xy")
        z = 1 - np.abs(u) - np.abs(v)
        x = np.where(z < 0, (1 - np.abs(v)) * np.sign(u), u)
        y = np.where(z < 0, (1 - np.abs(u)) * np.sign(v), v)
        dens = (2.0 / n) ** 2 / (x * x + y * y + z * z) ** 1.5
        ref = dens.reshape(r, subsamples, r, subsamples).sum(axis=(1, 3))
        worst = max(worst, float(np.max(np.abs(octa.pixel_solid_angles(r) - ref) / ref)))
    return CheckResult("octahedral per-pixel solid angle", worst, len(resolutions),
                       f"R in {resolutions}, {subsamples}^2 midpoints/pixel", note="midpoint rule limits this")


def check_octahedral_roundtrip(n=MIN_POINTS):
    d, _ = fibonacci_sphere(n)
    back = octa.oct_decode(octa.oct_encode(d))
    err = float(np.max(np.linalg.norm(back - d, axis=-1)))
    uv = octa.pixel_centers_uv(32)
    row, col = octa.direction_to_pixel(octa.oct_decode(uv), 32)
    ok = np.all(row == np.arange(32)[:, None]) and np.all(col == np.arange(32)[None, :])
    return CheckResult("octahedral decode(encode(d)) = d", err, n, f"{n} Fibonacci directions",
                       note="pixel centres map back to their pixel" if ok else "PIXEL LOOKUP BROKEN")


def all_checks(quick=False):
    if quick:
        return [
            check_sg_integral(sharpness=(1e-4, 1.0, 1e4)),
            check_sg_inner_product(sharpness=(1e-4, 1.0, 1e4), angles_deg=(0, 90, 180)),
            check_thesis_inner_product(sharpness=(1.0, 10.0), angles_deg=(0, 60)),
            check_sg_asg_convolution(sharpness=(1.0, 100.0, 1e4), roughness=(m.ROUGHNESS_MIN, 0.5), ndotv=(1.0, 0.01)),
            check_thesis_convolution(sharpness=(10.0,), roughness=(0.3,), ndotv=(1.0,)),
            *check_glossy(sharpness=(10.0, 1e3), roughness=(m.ROUGHNESS_MIN, 0.5), ndotv=(1.0, 0.1)),
            check_irradiance(sharpness=(1e-4, 1.0, 4.0, 1e4), cosines=np.linspace(-1, 1, 5)), check_ggx_ndf_lobes(),
            check_fresnel(),
            check_solid_angle_sum(), check_solid_angle_pixels(resolutions=(4, 7)), check_octahedral_roundtrip(),
        ]
    return [check_sg_integral(), check_sg_inner_product(), check_thesis_inner_product(), check_sg_asg_convolution(),
            check_thesis_convolution(), *check_glossy(), check_irradiance(), check_ggx_ndf_lobes(), check_fresnel(),
            check_solid_angle_sum(),
            check_solid_angle_pixels(), check_octahedral_roundtrip()]


def format_table(results):
    header = ("identity", "max rel err", "cases", "parameter range", "note")
    rows = [header] + [r.row() for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = [" | ".join(cell.ljust(w) for cell, w in zip(row, widths)) for row in rows]
    lines.insert(1, "-+-".join("-" * w for w in widths))
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="corners of the parameter grid only")
    parser.add_argument("--worst", action="store_true", help="also print the worst case of each identity")
    args = parser.parse_args(argv)
    results = all_checks(quick=args.quick)
    print(format_table(results))
    if args.worst:
        for r in results:
            print(f"{r.identity}: worst at {r.worst_case}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
