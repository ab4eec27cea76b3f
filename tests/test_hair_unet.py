"""Paper II's hair-filtering U-Net: every configuration, output ranges, loss, training on synthetic strands,
ONNX export and onnxruntime (CPU) agreeing with torch to 1e-4."""
import numpy as np
import pytest
import torch

from training.hair_unet import CONFIGS, HairNetConfig, HairUNet, export_onnx, hair_loss, onnx_session


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


def test_onnx_export_and_onnxruntime_match_torch(tmp_path):
    config = HairNetConfig.named("base")
    torch.manual_seed(0)
    model = HairUNet(config).eval()
    path = export_onnx(model, tmp_path / "hair.onnx")
    session = onnx_session(path)
    features = torch.randn(1, config.in_channels, 48, 64)  # another size than the export's: dynamic axes
    with torch.no_grad():
        expected = model(features).numpy()
    got = session.run(["outputs"], {"features": features.numpy()})[0]
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=1e-4)


def test_clamped_outputs_keep_a_small_gradient_in_training_and_exact_values():
    """A highlight pushed below zero must still learn (else the channel dies), yet the value is max(0, x)."""
    from training.hair_unet import LEAK, output_transform

    raw = torch.tensor([[-2.0, -1.0, 2.0], [0.5, 0.3, 0.5]]).T.reshape(1, 3, 1, 2).requires_grad_(True)
    out = output_transform(raw)
    assert float(out[0, 1, 0, 0]) == 0.0 and float(out[0, 2, 0, 0]) == 1.0  # relu and clip values
    out[:, 1:].sum().backward()
    assert float(raw.grad[0, 1, 0, 0]) == pytest.approx(LEAK) and float(raw.grad[0, 1, 0, 1]) == 1.0
    assert float(raw.grad[0, 2, 0, 0]) == pytest.approx(LEAK)
    with torch.no_grad():
        np.testing.assert_array_equal(output_transform(raw).numpy(), out.detach().numpy())
