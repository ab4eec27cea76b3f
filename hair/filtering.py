"""Run the exported hair filter with onnxruntime (CPU provider): no torch, so it works inside Blender.

The ONNX file carries its configuration in its metadata (written by hair.unet.export_onnx):
samples per pixel and stride. Images whose sides are not multiples of the stride are padded with empty
pixels (no hair) and cropped back, so any resolution works; the result says when that happened.

`filter` runs the network on the image and on its mirror images (left-right, up-down, both) and averages the
results as composites do (alpha-weighted): the network's errors differ between mirror images, so the mean has
less of them (docs/design-additions.md §11 measures what 1, 2 and 4 passes give and cost).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .raster import FEATURE_NAMES, StochasticRender

MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
SHIPPED_MODELS = {  # the 4-spp networks shipped in models/; docs/design-additions.md §22 and §25 measure both
    "base": MODELS_DIR / "hair_base.onnx",  # 0.6-0.8 s at 1024^2 with 4 passes on 2 cores
    "large": MODELS_DIR / "hair_large.onnx",  # 1.4-1.5 s, FLIP 0.002-0.004 lower on every split
}
DEFAULT_NETWORK = "large"  # beats unfiltered 16 spp on the trained styles' FLIP by 2.6 standard errors (§25)
SHIPPED_MODEL = SHIPPED_MODELS[DEFAULT_NETWORK]
MIRRORS = {1: ((False, False),), 2: ((False, False), (True, False)),
           4: ((False, False), (True, False), (False, True), (True, True))}  # passes -> (left-right, up-down)
DEFAULT_PASSES = 4
_TANGENT_X, _TANGENT_Y = FEATURE_NAMES.index("tangent_x"), FEATURE_NAMES.index("tangent_y")


def mirror_features(features: np.ndarray, left_right: bool, up_down: bool) -> np.ndarray:
    """(..., 6*S, H, W) network input of the mirror image: pixels flipped, view-space tangents with them."""
    if not (left_right or up_down):
        return features
    out = np.ascontiguousarray(features[..., ::-1 if up_down else 1, ::-1 if left_right else 1])
    if left_right:
        out[..., _TANGENT_X::len(FEATURE_NAMES), :, :] *= -1
    if up_down:
        out[..., _TANGENT_Y::len(FEATURE_NAMES), :, :] *= -1
    return out


def unmirror(outputs: np.ndarray, left_right: bool, up_down: bool) -> np.ndarray:
    """(..., H, W) outputs of a mirrored input, back in the image's own orientation."""
    if up_down:
        outputs = np.flip(outputs, -2)
    if left_right:
        outputs = np.flip(outputs, -1)
    return outputs


def mean_as_composited(outputs) -> np.ndarray:
    """Mean of several (3, H, W) colour factor, highlight, alpha results whose composite over any background
    is the mean of their composites: alpha averaged (clipped to [0, 1] as composite clips it), colour factor and
    highlight weighted by alpha (a plain mean where every alpha is 0)."""
    alpha_sum = np.zeros_like(outputs[0][2])
    weighted = np.zeros_like(outputs[0][:2])
    plain = np.zeros_like(outputs[0][:2])
    for output in outputs:  # accumulated in place, without stacking copies of every output
        alpha = np.clip(output[2], 0.0, 1.0)
        alpha_sum += alpha
        weighted += output[:2] * alpha
        plain += output[:2]
    covered = alpha_sum > 0
    mean = np.empty_like(outputs[0])
    mean[:2] = np.where(covered, weighted / np.where(covered, alpha_sum, 1.0), plain / len(outputs))
    mean[2] = alpha_sum / len(outputs)
    return mean


class HairFilterError(RuntimeError):
    """A missing, corrupt or unsuitable model file, or input it cannot filter (the message says which)."""


@dataclass
class HairFilter:
    session: object
    path: Path
    config: str
    samples: int
    stride: int

    def run(self, features: np.ndarray) -> tuple[np.ndarray, bool]:
        """(1, 6*S, H, W) float32 -> ((3, H, W) colour factor, highlight, alpha; whether it padded)."""
        expected = len(FEATURE_NAMES) * self.samples
        if features.ndim != 4 or features.shape[1] != expected:
            raise HairFilterError(f"the model {self.path.name} takes {expected} feature channels "
                                  f"({self.samples} samples per pixel), got shape {features.shape}")
        _, _, height, width = features.shape
        pad_h, pad_w = -height % self.stride, -width % self.stride
        padded = np.pad(features, ((0, 0), (0, 0), (0, pad_h), (0, pad_w))) if pad_h or pad_w else features
        outputs = self.session.run(["outputs"], {"features": np.ascontiguousarray(padded, np.float32)})[0]
        return outputs[0, :, :height, :width], bool(pad_h or pad_w)

    def filter(self, render: StochasticRender, passes: int = DEFAULT_PASSES) -> tuple[np.ndarray, bool]:
        """Filtered outputs of a stochastic render, the mean over `passes` mirror images (1, 2 or 4); alpha is
        zero beyond one pixel of any strand (the network's small bias would otherwise veil the whole frame)."""
        if passes not in MIRRORS:
            raise HairFilterError(f"filter passes must be one of {sorted(MIRRORS)}, got {passes}")
        if render.samples < self.samples:
            raise HairFilterError(f"the model needs {self.samples} samples per pixel; the render has {render.samples}")
        features = render.network_input(self.samples)
        results = []
        for left_right, up_down in MIRRORS[passes]:
            outputs, padded = self.run(mirror_features(features, left_right, up_down))
            results.append(unmirror(outputs, left_right, up_down))
        outputs = results[0] if len(results) == 1 else mean_as_composited(results)
        footprint = render.extras.get("footprint")
        if footprint is not None:
            near = np.pad(footprint, 1)
            near = (near[:-2, :-2] | near[:-2, 1:-1] | near[:-2, 2:] | near[1:-1, :-2] | near[1:-1, 1:-1]
                    | near[1:-1, 2:] | near[2:, :-2] | near[2:, 1:-1] | near[2:, 2:])
            outputs = outputs.copy()
            outputs[2] = np.where(near, outputs[2], 0.0)
        return outputs, padded


def load_filter(path=None, threads: int = 0, network: str | None = None) -> HairFilter:
    """An onnxruntime session for the model at `path`, or else for the shipped `network` (base or large; None:
    DEFAULT_NETWORK)."""
    network = network or DEFAULT_NETWORK
    if not path and network not in SHIPPED_MODELS:
        raise HairFilterError(f"unknown hair filter network {network!r}; choose one of {', '.join(SHIPPED_MODELS)}")
    path = Path(path) if path else SHIPPED_MODELS[network]
    if not path.is_file():
        raise HairFilterError(f"hair filter model not found: {path}")
    try:
        import onnxruntime
    except ImportError as error:
        raise HairFilterError("onnxruntime is not installed; install the extension's wheels") from error
    options = onnxruntime.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own types for truncated or non-ONNX files
        raise HairFilterError(f"hair filter model {path} is not a readable ONNX file: {error}") from error
    meta = session.get_modelmeta().custom_metadata_map
    try:
        samples, stride = int(meta["sglf_hair_samples"]), int(meta["sglf_hair_stride"])
    except (KeyError, ValueError) as error:
        raise HairFilterError(f"{path} is an ONNX file but not an SG Lightfield hair filter "
                              "(no sglf_hair_* metadata)") from error
    inputs = session.get_inputs()
    if len(inputs) != 1 or inputs[0].shape[1] != len(FEATURE_NAMES) * samples:
        raise HairFilterError(f"{path}: input {inputs[0].shape if inputs else None} does not match "
                              f"{samples} samples per pixel")
    return HairFilter(session, path, meta.get("sglf_hair_config", "?"), samples, stride)
