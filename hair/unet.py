"""The hair-filtering U-Net of Paper II (Currius & Sintorn 2022), its loss, ONNX export and onnxruntime inference.

Input: per-pixel features of a stochastic-transparency render, for each of S samples per pixel:
colour factor, specular highlight, alpha, depth, view-space tangent x and y (6 x S channels).
Output: colour factor, highlight, alpha, transformed as the paper says:
alpha = clip(x, 0, 1), colour factor = x^3/32 + x/5 + 1 (precision around 1), highlight = max(x, 0).
Architecture: stride-2 3x3 convolutions down (ReLU), stride-2 transposed convolutions up (ReLU except the
last), skip connections between each down/up pair except the first (the input is not skipped).
Loss: MSE of alpha-premultiplied colour factor and highlight plus alpha, plus MSE of their image gradients.

Ours beyond the paper (the shipped filters use both; docs/design-additions.md §10 has the measurements):
"+blend" configurations give the last layer one more output, a per-pixel share of the plain stochastic-transparency
result mixed into the output (premultiplied), so strand detail the input already resolves need not pass the
half-resolution decoder; and the loss can add an LDR-FLIP term on the composited, tone-mapped images
(training/flip_loss.py), the metric the product is judged by.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .raster import EVALUATION_LOOK
from ..training.flip_loss import flip_loss

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
# The same networks with a learned per-pixel share of the unfiltered input in the output (HairUNet.input_blend).
CONFIGS.update({(name.replace("@", "+blend@") if "@" in name else name + "+blend"): value
                for name, value in list(CONFIGS.items())})


@dataclass(frozen=True)
class HairNetConfig:
    name: str
    samples: int
    widths: tuple

    @property
    def input_blend(self) -> bool:
        return "+blend" in self.name

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
BLEND_BIAS = -2.0  # initial share of the unfiltered input: sigmoid(-2) = 0.12
BLEND_EPS = 1e-4  # alpha below which the blended colour factor falls back to 1


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
            out = (OUTPUTS + config.input_blend) if level == 0 else widths[level - 1]
            # The decoder level's input is the previous decoder output, concatenated with the skip of the
            # matching encoder level (none for the deepest, which starts the decoder).
            incoming = widths[-1] if level == len(widths) - 1 else 2 * widths[level]
            self.up.append(nn.ConvTranspose2d(incoming, out, 4, stride=2, padding=1))
        if config.input_blend:
            with torch.no_grad():
                self.up[-1].bias[OUTPUTS] = BLEND_BIAS

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
        if self.config.input_blend:
            return blend_with_input(output_transform(x[:, :OUTPUTS]), unfiltered_estimate(features),
                                    torch.sigmoid(x[:, OUTPUTS:OUTPUTS + 1]))
        return output_transform(x)


def unfiltered_estimate(features: torch.Tensor) -> torch.Tensor:
    """(B, 6*S, H, W) features -> (B, 3, H, W): the plain stochastic-transparency result, i.e. colour factor and
    highlight averaged over the covered samples (1 and 0 where none is), alpha = the covered share."""
    colour, highlight, alpha = (features[:, i::FEATURES_PER_SAMPLE] for i in range(3))
    covered = (alpha > 0).to(features.dtype)
    count = covered.sum(dim=1, keepdim=True)
    safe = count.clamp(min=1.0)
    has = (count > 0).to(features.dtype)
    colour_mean = (colour * covered).sum(dim=1, keepdim=True) / safe * has + (1 - has)
    highlight_mean = (highlight * covered).sum(dim=1, keepdim=True) / safe
    return torch.cat([colour_mean, highlight_mean, count / colour.shape[1]], dim=1)


def blend_with_input(filtered: torch.Tensor, unfiltered: torch.Tensor, share: torch.Tensor) -> torch.Tensor:
    """Mix (colour factor, highlight, alpha) images alpha-premultiplied, `share` (B, 1, H, W) of the unfiltered one:
    what is composited is the same mix of the two composites. Colour factor and highlight are then divided by the
    mixed alpha again (colour factor 1 and highlight 0 where it is ~0); a highlight stays >= 0 for any input."""
    a_f, a_u = filtered[:, 2:3], unfiltered[:, 2:3]
    alpha = share * a_u + (1 - share) * a_f
    weight_u, weight_f = share * a_u, (1 - share) * a_f
    colour = (weight_u * unfiltered[:, 0:1] + weight_f * filtered[:, 0:1] + BLEND_EPS) / (alpha + BLEND_EPS)
    highlight = torch.relu(weight_u * unfiltered[:, 1:2] + weight_f * filtered[:, 1:2]) / (alpha + BLEND_EPS)
    return torch.cat([colour, highlight, alpha], dim=1)


def _gradients(image: torch.Tensor):
    return image[..., :, 1:] - image[..., :, :-1], image[..., 1:, :] - image[..., :-1, :]


LOSS_NORMS = {"l2": lambda d: torch.mean(d ** 2), "l1": lambda d: torch.mean(d.abs())}


def composite(outputs: torch.Tensor, hair_color: torch.Tensor, light: torch.Tensor,
              background: torch.Tensor) -> torch.Tensor:
    """Torch twin of hair.raster.composite: (B, 3, H, W) outputs, per-image hair colour (B, 3), light (B,)
    and grey background (B,) -> (B, 3, H, W) linear RGB."""
    alpha = outputs[:, 2:3].clamp(0, 1)
    hair = light.view(-1, 1, 1, 1) * (outputs[:, 0:1] * hair_color.view(-1, 3, 1, 1) + outputs[:, 1:2])
    return alpha * hair + (1 - alpha) * background.view(-1, 1, 1, 1)


def tonemap(linear: torch.Tensor) -> torch.Tensor:
    """Torch twin of bake_directory.image_metrics.tonemap: Reinhard per channel, then sRGB encoding."""
    mapped = linear.clamp(min=0) / (1 + linear.clamp(min=0))
    return torch.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * mapped.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def random_looks(batch: int, generator: torch.Generator):
    """Hair colours from dark to blond (red >= green >= blue), key lights and grey backgrounds to composite with."""
    u = torch.rand(batch, 5, generator=generator)
    red = 0.03 * (0.6 / 0.03) ** u[:, 0]  # log-uniform in [0.03, 0.6]
    green = red * (0.45 + 0.45 * u[:, 1])
    blue = green * (0.4 + 0.5 * u[:, 2])
    return torch.stack([red, green, blue], dim=1), 1.5 + 3 * u[:, 3], 0.05 + 0.45 * u[:, 4]


def evaluation_looks(batch: int):
    color, light, background = EVALUATION_LOOK
    return torch.tensor([color] * batch), torch.full((batch,), light), torch.full((batch,), background)


def hair_loss(prediction: torch.Tensor, target: torch.Tensor, gradient_weight: float = 1.0,
              norm: str = "l2", flip_weight: float = 0.0, looks=None) -> torch.Tensor:
    """MSE of (colour factor x alpha, highlight x alpha, alpha) plus the MSE of their image gradients (the paper's);
    norm "l1" takes mean absolute errors instead. flip_weight adds that times the LDR-FLIP of the two composited
    with `looks` (hair colour, light, background per image; EVALUATION_LOOK when None) and tone-mapped."""
    def premultiplied(image):
        alpha = image[:, 2:3]
        return torch.cat([image[:, 0:2] * alpha, alpha], dim=1)

    error = LOSS_NORMS[norm]
    p, t = premultiplied(prediction), premultiplied(target)
    loss = error(p - t)
    for gp, gt in zip(_gradients(p), _gradients(t)):
        loss = loss + gradient_weight * error(gp - gt)
    if flip_weight:
        looks = evaluation_looks(len(prediction)) if looks is None else looks
        loss = loss + flip_weight * flip_loss(tonemap(composite(prediction, *looks)),
                                              tonemap(composite(target, *looks)))
    return loss


def export_onnx(model: HairUNet, path, height: int = 64, width: int = 64, opset: int = 17,
                metadata: dict | None = None):
    """Export with dynamic batch and image size, atomically; returns the path. The model's configuration
    (name, samples per pixel, stride) and `metadata` go into the ONNX metadata, which the filter checks.
    Uses torch's TorchScript exporter: the torch.export one needs onnxscript, which nothing else needs."""
    import onnx

    from ..bake_directory.atomic import atomic_output
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
