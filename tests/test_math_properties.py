"""Property tests (hypothesis): numpy == torch, no NaN/Inf at the extremes, ranges, gradients,
octahedral round trips, half-float storage of SG parameters, and the reference-noise correction of RMSE."""
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sg_lightfield.shaders import octahedral as octa
from sg_lightfield.shaders import sg_math as m
from sg_lightfield.training import sg_torch as t

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

finite = dict(allow_nan=False, allow_infinity=False)
components = st.floats(-1.0, 1.0, **finite)
vec3 = st.tuples(components, components, components).map(lambda v: np.array(v, dtype=np.float64))
sharpness_st = st.one_of(st.sampled_from([m.SHARPNESS_MIN, 1e-2, 1.0, 4.0, 1e2, m.SHARPNESS_MAX]),
                         st.floats(m.SHARPNESS_MIN, m.SHARPNESS_MAX, **finite))
amplitude_st = st.one_of(st.sampled_from([0.0, 1.0, 65504.0, 1e5]), st.floats(0.0, 1e5, **finite))
roughness_st = st.one_of(st.sampled_from([0.0, m.ROUGHNESS_MIN, 0.3, 1.0, 2.0]), st.floats(0.0, 1.5, **finite))
ndotv_st = st.one_of(st.sampled_from([-0.5, 0.0, 1e-6, m.NDOTV_MIN, 0.01, 1.0]), st.floats(-1.0, 1.0, **finite))


def unit(v):
    return m.safe_normalize(np.asarray(v, dtype=np.float64))


def view_at(ndotv):
    ndotv = float(np.clip(ndotv, -1, 1))
    return np.array([np.sqrt(1 - ndotv**2), 0.0, ndotv])


def all_outputs(xp, axis, lam, amp, normal, view, rough, f0, axis2, lam2):
    """Every public SG function on one input set, for numpy (m) or torch (t)."""
    asg = xp.warp_ndf_to_asg(normal, view, rough)
    return {
        "eval": xp.sg_eval(view, axis, lam, amp),
        "integral": xp.sg_integral(lam, amp),
        "inner": xp.sg_inner_product(axis, lam, amp, axis2, lam2, amp),
        "asg": xp.asg_eval(axis, asg)[..., None],
        "convolve": xp.sg_asg_convolve(axis, lam, amp, asg),
        "glossy": xp.sg_glossy(axis, lam, amp, normal, view, rough, f0),
        "glossy_partly_metallic": xp.sg_glossy(axis, lam, amp, normal, view, rough, f0, metallic=0.3),
        "glossy_mirror_warp": xp.sg_glossy_mirror_warp(axis, lam, amp, normal, view, rough, f0),
        "irradiance": xp.sg_irradiance(axis, lam, amp, normal),
        "sharpness_x": asg.sharpness_x[..., None],
    }


def as_torch(*arrays, dtype=torch.float64, grad=False):
    return [torch.tensor(a, dtype=dtype, requires_grad=grad) for a in arrays]


@SETTINGS
@given(axis=vec3, axis2=vec3, lam=sharpness_st, lam2=sharpness_st, amp=amplitude_st, rough=roughness_st,
       ndotv=ndotv_st)
def test_numpy_equals_torch_and_everything_is_finite(axis, axis2, lam, lam2, amp, rough, ndotv):
    normal = np.array([0.0, 0.0, 1.0])
    args_np = (unit(axis), np.float64(lam), np.array([amp, amp / 2, 0.0]), normal, view_at(ndotv),
               np.float64(rough), np.array([0.04, 0.5, 1.0]), unit(axis2), np.float64(lam2))
    out_np = all_outputs(m, *args_np)
    out_t = all_outputs(t, *as_torch(*args_np))
    for name, value in out_np.items():
        assert np.all(np.isfinite(value)), name
        assert np.all(value >= 0), name
        np.testing.assert_allclose(out_t[name].detach().numpy(), value, rtol=1e-5, atol=1e-300, err_msg=name)


@SETTINGS
@given(axis=vec3, lam=sharpness_st, amp=amplitude_st, rough=roughness_st, ndotv=ndotv_st)
def test_results_in_range(axis, lam, amp, rough, ndotv):
    a, normal, view = unit(axis), np.array([0.0, 0.0, 1.0]), view_at(ndotv)
    mu = np.array([amp])
    value = m.sg_eval(view, a, np.float64(lam), mu)
    assert 0 <= value[0] <= amp
    integral = m.sg_integral(np.float64(lam), mu)[0]
    assert 0 <= integral <= 4 * np.pi * amp * (1 + 1e-12)
    irradiance = m.sg_irradiance(a, np.float64(lam), mu, normal)[0]
    assert 0 <= irradiance <= integral * (1 + 1e-6) + 1e-300
    self_inner = m.sg_inner_product(a, np.float64(lam), mu, a, np.float64(lam), mu)[0]
    assert self_inner <= amp * integral * (1 + 1e-9) + 1e-300  # G^2 <= mu G pointwise


@SETTINGS
@given(axis=vec3, lam=sharpness_st, amp=amplitude_st, rough=roughness_st, ndotv=ndotv_st, n_sg=st.integers(1, 4))
def test_torch_gradients_finite_at_extremes(axis, lam, amp, rough, ndotv, n_sg):
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float32)
    view = torch.tensor(view_at(ndotv), dtype=torch.float32)
    raw_axis = torch.tensor(np.tile(axis, (n_sg, 1)), dtype=torch.float32, requires_grad=True)
    lam_t = torch.full((n_sg,), float(lam), requires_grad=True)
    amp_t = torch.full((n_sg, 3), float(amp), requires_grad=True)
    rough_t = torch.tensor(float(rough), requires_grad=True)
    ax, sh, am = t.sanitize_sg_params(raw_axis, lam_t, amp_t)
    total = (t.sg_glossy(ax, sh, am, normal, view, rough_t, torch.tensor([0.04, 0.04, 0.04])).sum()
             + t.sg_irradiance(ax, sh, am, normal).sum()
             + t.sg_eval(view, ax, sh, am).sum()
             + t.sg_inner_product(ax, sh, am, ax.flip(0), sh.flip(0), am.flip(0)).sum())
    total.backward()
    for name, p in (("axis", raw_axis), ("sharpness", lam_t), ("amplitude", amp_t), ("roughness", rough_t)):
        assert torch.all(torch.isfinite(p.grad)), name


def test_float32_torch_matches_float64_numpy_for_moderate_lobes():
    rng = np.random.default_rng(3)
    axes = unit(rng.normal(size=(2000, 3)))
    views = unit(rng.normal(size=(2000, 3)))
    lam = rng.uniform(1e-4, 10.0, size=2000)
    amp = rng.uniform(0, 10.0, size=(2000, 3))
    ref = m.sg_eval(views, axes, lam, amp)
    got = t.sg_eval(*as_torch(views, axes, lam, amp, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5 * amp.max())


def test_node_group_formula_is_the_numpy_reference_glossy():
    """sg_shading.shade (what the node group computes, run with NumpyOps) gives exactly sg_math.sg_glossy summed over
    the texel's SGs: the node formula is the one the quadrature checks hold to."""
    from sg_lightfield.shaders.sg_shading import NumpyOps, decode_sharpness, encode_sharpness, shade

    rng = np.random.default_rng(5)
    count, n = 400, 3
    normal = unit(rng.normal(size=(count, 3)))
    view = unit(normal + rng.normal(size=(count, 3)) * 0.6)
    rough, f0 = rng.uniform(0.05, 1.0, count), rng.uniform(0.02, 1.0, (count, 3))
    axes = unit(rng.normal(size=(n, count, 3)))
    encoded = rng.uniform(0, 1, (n, count))
    sharpness = decode_sharpness(NumpyOps(), encoded)
    amplitude = rng.uniform(0, 5, (n, count, 3))
    lookups = {"sg": lambda j: (axes[j], encoded[j]), "amp": lambda j: (amplitude[j], None)}
    got = shade(NumpyOps(), lambda kind, j: lookups[kind](j), normal, view, rough, f0, np.zeros((count, 3)), n,
                has_irradiance=False)["glossy"]
    want = sum(m.sg_glossy(axes[j], sharpness[j], amplitude[j], normal, view, rough, f0) for j in range(n))
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert np.allclose(encode_sharpness(sharpness), encoded)


def test_degenerate_inputs_never_produce_nan():
    zero = np.zeros(3)
    assert np.all(m.safe_normalize(zero) == [0, 0, 1])
    axis, lam, amp = m.sanitize_sg_params(np.array([np.nan, 0, 0]), np.array(np.nan), np.array([np.inf, -1.0, np.nan]))
    assert np.all(np.isfinite(axis)) and np.isfinite(lam) and np.all(amp == 0)
    # normal parallel to view: the warp's plane of incidence is undefined; the basis must still be a frame
    asg = m.warp_ndf_to_asg(np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), np.float64(0.3))
    frame = np.stack([asg.x, asg.y, asg.z])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    # black texel: zero amplitudes give exactly zero everywhere
    for value in all_outputs(m, np.array([0, 0, 1.0]), np.float64(1.0), np.zeros(3), np.array([0, 0, 1.0]),
                             view_at(0.5), np.float64(0.3), np.array([0.04] * 3), np.array([1.0, 0, 0]),
                             np.float64(2.0)).values():
        assert np.all(np.isfinite(value))


@SETTINGS
@given(d=vec3)
def test_octahedral_encode_decode_identity(d):
    if np.linalg.norm(d) < 1e-6:
        return
    d = unit(d)
    uv = octa.oct_encode(d)
    assert np.all(np.abs(uv) <= 1 + 1e-12)
    np.testing.assert_allclose(octa.oct_decode(uv), d, atol=1e-12)
    np.testing.assert_allclose(t.oct_decode(t.oct_encode(torch.tensor(d))).numpy(), d, atol=1e-12)
    np.testing.assert_allclose(t.oct_encode(torch.tensor(d)).numpy(), uv, atol=1e-12)


def test_octahedral_special_directions():
    for d in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [1, 1, 0], [-1, -1, 0]):
        d = unit(d)
        np.testing.assert_allclose(octa.oct_decode(octa.oct_encode(d)), d, atol=1e-12)
    # +Z (up) is the centre of the map
    row, col = octa.direction_to_pixel(np.array([0, 0, 1.0]), 16)
    assert (int(row), int(col)) in {(7, 7), (7, 8), (8, 7), (8, 8)}


@settings(max_examples=20, deadline=None)
@given(resolution=st.integers(1, 96))
def test_solid_angles_sum_to_4pi(resolution):
    w = octa.pixel_solid_angles(resolution)
    assert np.all(w > 0)
    assert abs(w.sum() - 4 * np.pi) < 1e-4
    tw = t.pixel_solid_angles(resolution, dtype=torch.float64)
    assert abs(float(tw.sum()) - 4 * np.pi) < 1e-4


@SETTINGS
@given(axis=vec3, lam=sharpness_st, amp=st.floats(0.0, 1e5, **finite), view=vec3)
def test_half_float_roundtrip_of_sg_parameters(axis, lam, amp, view):
    """Stored as half: the evaluated SG moves by at most 2e-3 of its peak for sharpness <= 100
    and 8e-2 for the sharpest stored lobes (axis quantisation ~ 2^-11 rad vs a 0.01 rad lobe);
    amplitudes below the smallest half subnormal (6e-8, times the amplitude scale) flush to 0."""
    a = unit(axis)
    v = unit(view) if np.linalg.norm(view) > 1e-6 else a
    mu = np.array([amp, amp * 0.25, 0.0])
    scale = m.half_amplitude_scale(mu)
    packed = m.pack_sg_half(a, np.float64(lam), mu, scale)
    assert all(p.dtype == np.float16 and np.all(np.isfinite(p)) for p in packed)
    a2, lam2, mu2 = m.unpack_sg_half(*packed, amplitude_scale=scale, dtype=np.float64)
    exact = m.sg_eval(v, a, np.float64(lam), mu)
    stored = m.sg_eval(v, a2, lam2, mu2)
    bound = 2e-3 if lam <= 100 else 8e-2
    assert np.all(np.abs(stored - exact) <= bound * amp + 6e-8 * scale)


def test_rmse_against_converged_removes_the_noise_of_a_two_half_reference():
    from sg_lightfield.bake_directory.image_metrics import rmse, rmse_against_converged

    rng = np.random.default_rng(7)
    converged = rng.uniform(0.2, 0.8, (144, 256, 3))
    test = converged + 0.02 * np.sin(np.arange(256) / 9.0)[None, :, None]  # a structured error, RMSE ~0.014
    half_a, half_b = (converged + rng.normal(0, 0.03, converged.shape) for _ in range(2))
    reference = 0.5 * (half_a + half_b)
    noise = rmse(half_a, half_b) / 2
    raw, truth = rmse(test, reference), rmse(test, converged)
    assert raw > 1.3 * truth  # the reference's noise inflates the error against it
    assert rmse_against_converged(raw, noise) == pytest.approx(truth, rel=0.03)
    assert rmse_against_converged(noise, 2 * noise) == 0.0  # noise explains everything: 0, never NaN
