"""The hair-filtering U-Net of Paper II (Currius & Sintorn 2022), its loss, ONNX export and onnxruntime inference.

Input: per-pixel features of a stochastic-transparency render, for each of S samples per pixel:
colour factor, specular highlight, alpha, depth, view-space tangent x and y (6 x S channels).
Output: colour factor, highlight, alpha, transformed as the paper says:
alpha = clip(x, 0, 1), colour factor = x^3/32 + x/5 + 1 (precision around 1), highlight = max(x, 0).
Architecture: stride-2 3x3 convolutions down (ReLU), stride-2 transposed convolutions up (ReLU except the
last), skip connections between each down/up pair except the first (the input is not skipped).
Loss: MSE of alpha-premultiplied colour factor and highlight plus alpha, plus MSE of their image gradients.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

FEATURES_PER_SAMPLE = 6  # colour factor, highlight, alpha, depth, tangent x, tangent y
OUTPUTS = 3  # colour factor, highlight, alpha

# Paper II, Table 1: samples per pixel and encoder widths.
CONFIGS = {
    "base": (4, (32, 64, 128)),
    "base@1spp": (1, (32, 64, 128)),
    "base@2spp": (2, (32, 64, 128)),
    "large": (4, (64, 128, 256)),
    "small": (4, (16, 32, 64)),
    "shallow": (4, (32, 64)),
    "deep": (4, (32, 64, 128, 256)),
}


@dataclass(frozen=True)
class HairNetConfig:
    name: str
    samples: int
    widths: tuple

    @classmethod
    def named(cls, name: str) -> "HairNetConfig":
        if name not in CONFIGS:
            raise ValueError(f"unknown hair network {name!r}; choose one of {', '.join(CONFIGS)}")
        samples, widths = CONFIGS[name]
        return cls(name, samples, widths)

    @property
    def in_channels(self) -> int:
        return FEATURES_PER_SAMPLE * self.samples

    @property
    def multiple(self) -> int:
        """Image sides must be multiples of this (one halving per level)."""
        return 2 ** len(self.widths)


LEAK = 0.01  # gradient kept where the clamps are flat, in training only


def _leaky_gradient(clamped: torch.Tensor, raw: torch.Tensor) -> torch.Tensor:
    """The clamped value, but a LEAK-scaled gradient where the clamp cut it: without it the sparse highlight
    channel dies (ReLU output stuck at 0 for every pixel: measured on the first Base run)."""
    cut = (clamped != raw).to(raw.dtype)
    return clamped + LEAK * cut * (raw - raw.detach())


def output_transform(raw: torch.Tensor) -> torch.Tensor:
    """Raw network output (B, 3, H, W) -> (colour factor, highlight, alpha) in their ranges. The values are
    the paper's transforms exactly; in training the clamps pass a small gradient (_leaky_gradient)."""
    x_color, x_high, x_alpha = raw[:, 0:1], raw[:, 1:2], raw[:, 2:3]
    color = x_color ** 3 / 32 + x_color / 5 + 1
    high, alpha = torch.relu(x_high), x_alpha.clamp(0.0, 1.0)
    if torch.is_grad_enabled() and raw.requires_grad:
        high, alpha = _leaky_gradient(high, x_high), _leaky_gradient(alpha, x_alpha)
    return torch.cat([color, high, alpha], dim=1)


class HairUNet(nn.Module):
    def __init__(self, config: HairNetConfig):
        super().__init__()
        self.config = config
        widths = config.widths
        self.down = nn.ModuleList()
        previous = config.in_channels
        for width in widths:
            self.down.append(nn.Conv2d(previous, width, 3, stride=2, padding=1))
            previous = width
        self.up = nn.ModuleList()
        for level in reversed(range(len(widths))):
            out = OUTPUTS if level == 0 else widths[level - 1]
            # The decoder level's input is the previous decoder output, concatenated with the skip of the
            # matching encoder level (none for the deepest, which starts the decoder).
            incoming = widths[-1] if level == len(widths) - 1 else 2 * widths[level]
            self.up.append(nn.ConvTranspose2d(incoming, out, 4, stride=2, padding=1))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features (B, 6*S, H, W) -> transformed outputs (B, 3, H, W)."""
        skips = []
        x = features
        for conv in self.down:
            x = torch.relu(conv(x))
            skips.append(x)
        levels = len(self.down)
        for i, tconv in enumerate(self.up):
            level = levels - 1 - i
            if i > 0:
                x = torch.cat([x, skips[level]], dim=1)
            x = tconv(x)
            if level > 0:
                x = torch.relu(x)
        return output_transform(x)


def _gradients(image: torch.Tensor):
    return image[..., :, 1:] - image[..., :, :-1], image[..., 1:, :] - image[..., :-1, :]


def hair_loss(prediction: torch.Tensor, target: torch.Tensor, gradient_weight: float = 1.0) -> torch.Tensor:
    """MSE of (colour factor x alpha, highlight x alpha, alpha) plus the MSE of their image gradients."""
    def premultiplied(image):
        alpha = image[:, 2:3]
        return torch.cat([image[:, 0:2] * alpha, alpha], dim=1)

    p, t = premultiplied(prediction), premultiplied(target)
    loss = torch.mean((p - t) ** 2)
    for gp, gt in zip(_gradients(p), _gradients(t)):
        loss = loss + gradient_weight * torch.mean((gp - gt) ** 2)
    return loss


def export_onnx(model: HairUNet, path, height: int = 64, width: int = 64, opset: int = 17,
                metadata: dict | None = None):
    """Export with dynamic batch and image size, atomically; returns the path. The model's configuration
    (name, samples per pixel, stride) and `metadata` go into the ONNX metadata, which the filter checks.
    Uses torch's TorchScript exporter: the torch.export one needs onnxscript, which nothing else needs."""
    import onnx

    try:
        from ..shaders.atomic import atomic_output
    except ImportError:
        from shaders.atomic import atomic_output
    model.eval()
    dummy = torch.zeros((1, model.config.in_channels, height, width))
    with atomic_output(path, suffix=".tmp.onnx") as tmp:
        torch.onnx.export(model, dummy, str(tmp), input_names=["features"], output_names=["outputs"],
                          opset_version=opset, dynamic_axes={"features": {0: "batch", 2: "height", 3: "width"},
                                                             "outputs": {0: "batch", 2: "height", 3: "width"}},
                          dynamo=False)
        proto = onnx.load(str(tmp))
        entries = {"sglf_hair_config": model.config.name, "sglf_hair_samples": str(model.config.samples),
                   "sglf_hair_stride": str(model.config.multiple),
                   **{f"sglf_{k}": str(v) for k, v in (metadata or {}).items()}}
        for key, value in entries.items():
            item = proto.metadata_props.add()
            item.key, item.value = key, value
        onnx.save(proto, str(tmp))
    return path


def onnx_session(path):
    """An onnxruntime session on the CPU provider (what Blender uses: no torch needed there)."""
    import onnxruntime

    return onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
