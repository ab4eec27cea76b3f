"""Run the exported hair filter with onnxruntime (CPU provider): no torch, so it works inside Blender.

The ONNX file carries its configuration in its metadata (written by training.hair_unet.export_onnx):
samples per pixel and stride. Images whose sides are not multiples of the stride are padded with empty
pixels (no hair) and cropped back, so any resolution works; the result says when that happened.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

try:
    from .hair_raster import FEATURE_NAMES, StochasticRender
except ImportError:
    from shaders.hair_raster import FEATURE_NAMES, StochasticRender

SHIPPED_MODEL = Path(__file__).resolve().parent.parent / "models" / "hair_base.onnx"


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

    def filter(self, render: StochasticRender) -> tuple[np.ndarray, bool]:
        """Filtered outputs of a stochastic render; alpha is zero beyond one pixel of any strand (the
        network's small bias would otherwise veil the whole frame)."""
        if render.samples < self.samples:
            raise HairFilterError(f"the model needs {self.samples} samples per pixel; the render has {render.samples}")
        outputs, padded = self.run(render.network_input(self.samples))
        footprint = render.extras.get("footprint")
        if footprint is not None:
            near = np.pad(footprint, 1)
            near = (near[:-2, :-2] | near[:-2, 1:-1] | near[:-2, 2:] | near[1:-1, :-2] | near[1:-1, 1:-1]
                    | near[1:-1, 2:] | near[2:, :-2] | near[2:, 1:-1] | near[2:, 2:])
            outputs = outputs.copy()
            outputs[2] = np.where(near, outputs[2], 0.0)
        return outputs, padded


def load_filter(path=None, threads: int = 0) -> HairFilter:
    """An onnxruntime session for the model at `path` (the shipped Base model by default)."""
    path = Path(path) if path else SHIPPED_MODEL
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
