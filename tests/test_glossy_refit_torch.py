"""The refits' torch twins (training/glossy_refit_torch.py, what a GPU runs) against glossy_refit's numpy reference:
the GGX integrand, the pixel-integrated weights with their fine window, the reflected radiance, the projected
coordinate descent and the whole amplitude refit, on lobes wider and narrower than a pixel. On the CPU the train
stage keeps the numpy (amplitude_refit_steps)."""
import numpy as np
import pytest
import torch

from sg_lightfield.shaders.sg_math import ggx_brdf_cos_white
from sg_lightfield.training import glossy_refit as reference
from sg_lightfield.training import glossy_refit_torch as twin
from sg_lightfield.training import sg_torch
from sg_lightfield.training.sg_fit import predict

from tests.test_glossy_refit import scene


def tilted_normals(texels, seed=3):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(texels, 3)) + [0, 0, 2.0]
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def test_ggx_integrand_twin_matches_numpy_at_grazing_and_degenerate_directions():
    rng = np.random.default_rng(0)
    light = rng.normal(size=(500, 3))
    light /= np.linalg.norm(light, axis=-1, keepdims=True)
    view = np.concatenate([light[:10] * -1, rng.normal(size=(490, 3))])  # l + v = 0: the degenerate half vector
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    normal = tilted_normals(500)
    roughness = rng.uniform(0.0, 1.0, 500)
    expected = ggx_brdf_cos_white(light, view, normal, roughness)
    got = sg_torch.ggx_brdf_cos_white(*(torch.from_numpy(x) for x in (light, view, normal, roughness))).numpy()
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("roughness", [0.2, 0.35, 0.8])  # supersampled 8x, 3x, and pixel centres only
def test_pixel_integrated_weights_and_reflection_match_numpy(roughness):
    texels, resolution = 6, 16
    rng = np.random.default_rng(1)
    normals = tilted_normals(texels)
    views = reference.hemisphere_views(normals)
    rough = np.full(texels, roughness)
    expected = reference.pixel_integrated_weights(normals, views, rough, resolution)
    got = twin.pixel_integrated_weights(normals, views, rough, resolution).numpy()
    assert got.dtype == np.float32 and got.shape == expected.shape
    np.testing.assert_allclose(got, expected, rtol=0, atol=5e-4 * expected.max())  # float32 on a steep lobe
    images = rng.uniform(0.0, 3.0, (texels, resolution, resolution, 3)).astype(np.float32)
    radiance = twin.reflected_radiance_batched(images, normals, views, rough).numpy()
    # float32 weights of a steep lobe (within 5e-4 of the largest, above) summed over the pixels: 1.5e-4 on one CPU
    np.testing.assert_allclose(radiance, reference.reflected_radiance(images, normals, views, rough), rtol=5e-4)


def test_projected_coordinate_descent_twin_matches_numpy():
    rng = np.random.default_rng(2)
    base = rng.normal(size=(8, 40, 5))
    target = rng.normal(size=(8, 40, 3))
    gram, rhs = np.einsum("brn,brm->bnm", base, base), np.einsum("brn,brc->bnc", base, target)
    start = np.ones((8, 5, 3))
    expected = reference.nonnegative_quadratic_minimum(gram, rhs, start, sweeps=50)
    got = twin.nonnegative_quadratic_minimum(*(torch.from_numpy(x) for x in (gram, rhs, start)), sweeps=50).numpy()
    assert (got == 0).any()  # constraints are active
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


def test_amplitude_refit_twin_matches_numpy_and_the_cpu_keeps_the_numpy():
    images, normals, axis, sharpness, amplitude = scene(texels=40)
    roughness = np.linspace(0.25, 0.7, 40)
    counts = np.full(40, 3)
    counts[::7] = 2  # an unused SG stays zero
    biased = amplitude * 0.6
    expected = reference.refit_amplitudes(images, normals, axis, sharpness, biased, roughness, counts)
    got = twin.refit_amplitudes(images, normals, axis, sharpness, biased, roughness, counts)
    assert got.dtype == np.float32 and np.all(got[::7, 2] == biased[::7, 2].astype(np.float32))
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-6 * expected.max())
    assert np.abs(expected - biased).max() > 0.1 * biased.max()  # the refit moved them: the test compares work
    steps = twin.amplitude_refit_steps(images, normals, axis, sharpness, biased, roughness, counts, device="cpu")
    assert steps.gi_code is reference.refit_steps(images, normals, axis, sharpness, biased, roughness).gi_code


def test_the_training_prediction_as_matrix_products_equals_the_sum_of_lobes():
    rng = np.random.default_rng(4)
    directions = torch.from_numpy(rng.normal(size=(5, 8, 8, 3)))
    directions = directions / torch.linalg.vector_norm(directions, dim=-1, keepdim=True)
    axis = sg_torch.safe_normalize(torch.from_numpy(rng.normal(size=(5, 7, 3))))
    sharpness = torch.from_numpy(np.exp(rng.uniform(-3, 8, (5, 7))))
    amplitude = torch.from_numpy(rng.uniform(0, 4, (5, 7, 3)))
    expected = sg_torch.sg_sum_eval(directions, axis[:, None, None], sharpness[:, None, None],
                                    amplitude[:, None, None])
    torch.testing.assert_close(predict((axis, sharpness, amplitude), directions), expected, rtol=1e-10, atol=1e-12)


def test_the_guards_errors_twin_matches_numpy_at_texels_and_between_them():
    images, normals, axis, sharpness, amplitude = scene(texels=20)
    normals = tilted_normals(20)  # blended normals differ between neighbours
    roughness = np.linspace(0.3, 0.6, 20)
    a, b = np.arange(19), np.arange(1, 20)
    expected = reference.interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, a, b)
    got = twin.interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness, a, b)
    assert 0.01 < expected and got == pytest.approx(expected, rel=1e-4)
    shaded, between = twin.error_functions("cpu")
    assert shaded is reference.shaded_error and between is reference.interpolated_shaded_error
    assert twin.shaded_error(images, normals, axis, sharpness, amplitude, roughness) == pytest.approx(
        reference.shaded_error(images, normals, axis, sharpness, amplitude, roughness), rel=1e-4)


def test_both_refits_fit_the_same_target_computed_once():
    from sg_lightfield.training.glossy_lobe_fit import lobe_refit_steps

    images, normals, axis, sharpness, amplitude = scene(texels=12)
    roughness = np.linspace(0.3, 0.6, 12)
    targets = twin.fitted_view_targets(images, normals, roughness)
    assert targets.shape == (12, len(reference.REFIT_VIEW_COSINES) * reference.REFIT_VIEW_AZIMUTHS, 3)
    np.testing.assert_allclose(twin.fitted_view_targets(images, normals, roughness, device=torch.device("cpu")),
                               targets)
    biased = amplitude * 0.6
    np.testing.assert_array_equal(reference.refit_amplitudes(images, normals, axis, sharpness, biased, roughness,
                                                             targets=targets),
                                  reference.refit_amplitudes(images, normals, axis, sharpness, biased, roughness))
    np.testing.assert_allclose(twin.refit_amplitudes(images, normals, axis, sharpness, biased, roughness,
                                                     targets=targets),
                               twin.refit_amplitudes(images, normals, axis, sharpness, biased, roughness), rtol=1e-5)
    texels = np.stack([np.zeros(12, np.int64), np.arange(12)], -1)

    def lobes(**kwargs):
        return reference.run_to_end(lobe_refit_steps(images, normals, texels, axis, sharpness, biased, roughness, 3,
                                                     4, **kwargs))

    for given, computed in zip(lobes(target=targets), lobes()):
        np.testing.assert_array_equal(given, computed)
