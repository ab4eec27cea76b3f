"""Paper II's hair-filtering U-Net: every configuration, output ranges, loss, training on synthetic strands,
ONNX export and onnxruntime (CPU) agreeing with torch to 1e-4."""
import numpy as np
import pytest
import torch

from sg_lightfield.hair.unet import CONFIGS, HairNetConfig, HairUNet, export_onnx, hair_loss, onnx_session


@pytest.mark.parametrize("name", list(CONFIGS))
def test_every_configuration_keeps_the_image_size_and_output_ranges(name):
    config = HairNetConfig.named(name)
    torch.manual_seed(0)
    model = HairUNet(config)
    features = torch.randn(2, config.in_channels, 32, 48) * 3
    with torch.no_grad():
        out = model(features)
    assert out.shape == (2, 3, 32, 48)
    assert float(out[:, 2].min()) >= 0 and float(out[:, 2].max()) <= 1  # alpha clipped
    assert float(out[:, 1].min()) >= 0  # highlight positive


def _synthetic_strands(batch, size, samples, generator):
    """Random antialiased lines as the target; the input is the same lines with stochastic (hashed) coverage."""
    target = torch.zeros(batch, 3, size, size)
    features = torch.zeros(batch, 6 * samples, size, size)
    ys, xs = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    for b in range(batch):
        for _ in range(12):
            angle = torch.rand(1, generator=generator) * np.pi
            offset = (torch.rand(1, generator=generator) - 0.5) * size
            distance = (xs - size / 2) * torch.sin(angle) - (ys - size / 2) * torch.cos(angle) - offset
            coverage = (1 - distance.abs()).clamp(0, 1) * 0.6
            target[b, 2] = 1 - (1 - target[b, 2]) * (1 - coverage)
            target[b, 0] = torch.maximum(target[b, 0], coverage * 1.5 + 1 - 0.6)
            target[b, 1] = torch.maximum(target[b, 1], coverage * (torch.cos(angle) ** 2))
            for s in range(samples):
                hit = (torch.rand(size, size, generator=generator) < coverage).float()
                base = 6 * s
                features[b, base + 0] = torch.maximum(features[b, base + 0], hit * 1.5)
                features[b, base + 1] = torch.maximum(features[b, base + 1], hit * torch.cos(angle) ** 2)
                features[b, base + 2] = torch.maximum(features[b, base + 2], hit)
                features[b, base + 3] += hit * 0.1
                features[b, base + 4] += hit * torch.cos(angle)
                features[b, base + 5] += hit * torch.sin(angle)
    target[:, 0] = torch.where(target[:, 2] > 0, target[:, 0], torch.ones_like(target[:, 0]))
    return features, target


def test_training_lowers_the_loss_on_synthetic_strands():
    config = HairNetConfig.named("small")
    generator = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = HairUNet(config)
    features, target = _synthetic_strands(8, 32, config.samples, generator)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = float(hair_loss(model(features), target))
    for _ in range(150):
        optimizer.zero_grad()
        loss = hair_loss(model(features), target)
        loss.backward()
        optimizer.step()
    assert float(loss) < 0.3 * first


@pytest.mark.parametrize("name", ["base", "base+blend"])
def test_onnx_export_and_onnxruntime_match_torch(tmp_path, name):
    config = HairNetConfig.named(name)
    torch.manual_seed(0)
    model = HairUNet(config).eval()
    path = export_onnx(model, tmp_path / "hair.onnx")
    session = onnx_session(path)
    features = torch.randn(1, config.in_channels, 48, 64)  # another size than the export's: dynamic axes
    features[:, 2::6] = (features[:, 2::6] > 0).float()  # alphas: some samples covered, some not
    with torch.no_grad():
        expected = model(features).numpy()
    got = session.run(["outputs"], {"features": features.numpy()})[0]
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=1e-4)


def test_clamped_outputs_keep_a_small_gradient_in_training_and_exact_values():
    """A highlight pushed below zero must still learn (else the channel dies), yet the value is max(0, x)."""
    from sg_lightfield.hair.unet import LEAK, output_transform

    raw = torch.tensor([[-2.0, -1.0, 2.0], [0.5, 0.3, 0.5]]).T.reshape(1, 3, 1, 2).requires_grad_(True)
    out = output_transform(raw)
    assert float(out[0, 1, 0, 0]) == 0.0 and float(out[0, 2, 0, 0]) == 1.0  # relu and clip values
    out[:, 1:].sum().backward()
    assert float(raw.grad[0, 1, 0, 0]) == pytest.approx(LEAK) and float(raw.grad[0, 1, 0, 1]) == 1.0
    assert float(raw.grad[0, 2, 0, 0]) == pytest.approx(LEAK)
    with torch.no_grad():
        np.testing.assert_array_equal(output_transform(raw).numpy(), out.detach().numpy())


def test_input_blend_mixes_the_two_composites_and_keeps_the_ranges():
    """share 0 gives the filter's output, share 1 the unfiltered one, and any share s composites to the s-mix of
    the two composites (what the loss and the viewer see), with colour factor 1 where nothing is left."""
    from sg_lightfield.hair.raster import composite
    from sg_lightfield.hair.unet import blend_with_input

    generator = torch.Generator().manual_seed(3)
    def outputs(empty_pixels):
        o = torch.rand(1, 3, 8, 8, generator=generator) * torch.tensor([2.0, 0.5, 1.0]).view(1, 3, 1, 1)
        o[:, 0] += 0.5
        o[:, 2].view(-1)[:empty_pixels] = 0
        o[:, 0].view(-1)[:empty_pixels] = 1
        o[:, 1].view(-1)[:empty_pixels] = 0
        return o
    filtered, unfiltered = outputs(5), outputs(9)
    share = torch.rand(1, 1, 8, 8, generator=generator)
    hair, background = (0.4, 0.2, 0.1), np.full((8, 8, 3), 0.2)
    def comp(o):
        return composite(o[0].double().numpy(), hair, background, light=2.0)
    np.testing.assert_allclose(comp(blend_with_input(filtered, unfiltered, torch.zeros_like(share))), comp(filtered),
                               atol=1e-3)
    np.testing.assert_allclose(comp(blend_with_input(filtered, unfiltered, torch.ones_like(share))), comp(unfiltered),
                               atol=1e-3)
    mixed = blend_with_input(filtered, unfiltered, share)
    s = share[0, 0].numpy()[..., None]
    np.testing.assert_allclose(comp(mixed), s * comp(unfiltered) + (1 - s) * comp(filtered), atol=1e-3)
    assert float(mixed[:, 0].view(-1)[0]) == pytest.approx(1.0)  # empty in both: colour factor 1
    assert float(mixed[:, 2].min()) >= 0 and float(mixed[:, 2].max()) <= 1


def test_torch_flip_is_the_flip_evaluators_and_has_gradients():
    """The LDR-FLIP loss twin against the flip-evaluator package the bench scores with, on composited hair: a
    noisy render, a blurred one and the reference itself."""
    from sg_lightfield.hair import raster as hair_raster
    from sg_lightfield.bake_directory.image_metrics import flip, tonemap as tonemap_np
    from sg_lightfield.training.flip_loss import flip_map
    from sg_lightfield.hair.unet import composite, evaluation_looks, hair_loss, tonemap

    rng = np.random.default_rng(0)
    size = 48
    ys, xs = np.mgrid[0:size, 0:size]
    alpha = np.zeros((size, size))
    for _ in range(14):
        angle, offset = rng.uniform(0, np.pi), rng.uniform(-size / 2, size / 2)
        distance = (xs - size / 2) * np.sin(angle) - (ys - size / 2) * np.cos(angle) - offset
        alpha = 1 - (1 - alpha) * (1 - np.clip(1 - np.abs(distance), 0, 1) * 0.8)
    reference = np.stack([1 + 0.5 * np.sin(xs / 5.0), 0.3 * np.cos(ys / 3.0) ** 2, alpha])
    noisy = reference.copy()
    noisy[2] = (rng.random((size, size)) < alpha).astype(float)
    blurred = reference.copy()
    blurred[2] = sum(np.roll(alpha, shift, axis) for shift in (-1, 1) for axis in (0, 1)) / 5 + alpha / 5
    color, light, background = hair_raster.EVALUATION_LOOK

    def ldr_np(outputs):
        return tonemap_np(hair_raster.composite(outputs, color, np.full((size, size, 3), background), light))

    def ldr_torch(outputs):
        looks = [x.double() for x in evaluation_looks(1)]
        return tonemap(composite(torch.from_numpy(outputs[None]).double(), *looks))

    np.testing.assert_allclose(ldr_torch(noisy)[0].numpy().transpose(1, 2, 0), ldr_np(noisy), atol=1e-7)
    for test in (noisy, blurred, reference):
        expected_mean, expected_map = flip(ldr_np(reference), ldr_np(test))
        got = flip_map(ldr_torch(test), ldr_torch(reference))[0, 0].numpy()
        np.testing.assert_allclose(got, expected_map, atol=2e-5)
        assert float(got.mean()) == pytest.approx(expected_mean, abs=1e-5)
    assert flip(ldr_np(reference), ldr_np(noisy))[0] > 0.05  # the cases are not trivial

    prediction = torch.from_numpy(blurred[None]).float().requires_grad_(True)
    loss = hair_loss(prediction, torch.from_numpy(reference[None]).float(), flip_weight=1.0)
    loss.backward()
    assert torch.isfinite(prediction.grad).all() and float(prediction.grad.abs().sum()) > 0
