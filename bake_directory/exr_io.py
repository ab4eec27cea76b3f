"""EXR input/output for bake directories: half or float, any channel count, atomic writes.

Arrays are (H, W) or (H, W, C); row 0 is the top scanline. Channel names default to R, G, B, A for
up to four channels and ``c000``, ``c001``, ... beyond. Every error names the file.
"""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .atomic import atomic_output

_DTYPES = {"half": np.float16, "float": np.float32}


class ExrError(RuntimeError):
    """A missing, unreadable or malformed EXR file (the message names it)."""


def default_channel_names(count: int) -> list[str]:
    if count <= 4:
        return list("RGBA"[:count]) if count != 1 else ["Y"]
    return [f"c{i:03d}" for i in range(count)]


def write_exr(path, array, *, precision: str = "half", channels: list[str] | None = None,
              metadata: dict[str, str] | None = None, compression: str = "zip") -> Path:
    """Write (H, W[, C]) to `path` atomically (temp file in the same folder, then rename)."""
    import OpenEXR

    path = Path(path)
    if precision not in _DTYPES:
        raise ValueError(f"precision must be 'half' or 'float', got {precision!r}")
    data = np.asarray(array)
    if data.ndim == 2:
        data = data[..., None]
    if data.ndim != 3 or data.shape[0] < 1 or data.shape[1] < 1 or data.shape[2] < 1:
        raise ExrError(f"{path}: expected an (H, W) or (H, W, C) array, got shape {np.shape(array)}")
    names = channels or default_channel_names(data.shape[2])
    if len(names) != data.shape[2] or len(set(names)) != len(names):
        raise ExrError(f"{path}: {data.shape[2]} channels but names {names}")
    dtype = _DTYPES[precision]
    if precision == "half":
        finite_max = float(np.finfo(np.float16).max)
        data = np.clip(data, -finite_max, finite_max)  # inf would silently poison every reader
    pixels = {name: np.ascontiguousarray(data[..., i].astype(dtype)) for i, name in enumerate(names)}
    header = {
        "compression": {"zip": OpenEXR.ZIP_COMPRESSION, "none": OpenEXR.NO_COMPRESSION,
                        "piz": OpenEXR.PIZ_COMPRESSION}[compression],
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (metadata or {}).items():
        header[f"sglf_{key}"] = str(value)
    try:
        with atomic_output(path, suffix=".tmp.exr") as tmp, OpenEXR.File(header, pixels) as exr:
            exr.write(str(tmp))
    except OSError as exc:
        raise ExrError(f"{path}: cannot write ({exc.strerror or exc})") from exc
    return path


@contextmanager
def _opened(path, **options):
    """An OpenEXR.File of `path`; a missing, foreign or unreadable file raises ExrError naming it, also when the
    error comes from reading inside the block."""
    import OpenEXR

    if not path.is_file():
        raise ExrError(f"{path}: EXR file not found")
    try:
        if not OpenEXR.isOpenExrFile(str(path)):
            raise ExrError(f"{path}: not an OpenEXR file (corrupt or wrong format)")
        with OpenEXR.File(str(path), **options) as exr:
            yield exr
    except ExrError:
        raise
    except Exception as exc:  # OpenEXR raises plain RuntimeError/ValueError for truncated data
        raise ExrError(f"{path}: cannot read EXR ({exc})") from exc


def _metadata(header) -> dict[str, str]:
    return {k[len("sglf_"):]: str(v) for k, v in header.items() if k.startswith("sglf_")}


def read_exr(path, *, channels: list[str] | None = None, dtype=np.float32):
    """Read an EXR into (H, W, C) `dtype` plus (channel names, metadata written by write_exr)."""
    path = Path(path)
    with _opened(path, separate_channels=True) as exr:
        found = exr.channels()
        header = dict(exr.header())  # the live header empties when the file closes
        names = channels or _ordered_names(found.keys())
        missing = [n for n in names if n not in found]
        if missing:
            raise ExrError(f"{path}: missing channels {missing}; file has {sorted(found)}")
        data = np.stack([np.asarray(found[n].pixels, dtype=dtype) for n in names], axis=-1)
    return data, names, _metadata(header)


def read_exr_metadata(path) -> dict[str, str]:
    """The metadata written by write_exr (keys without the ``sglf_`` prefix), from the header alone."""
    path = Path(path)
    with _opened(path, header_only=True) as exr:
        header = dict(exr.header())
    return _metadata(header)


def _ordered_names(names):
    names = list(names)
    rgba = [c for c in "RGBA" if c in names]
    if len(rgba) == len(names):
        return rgba
    return sorted(names)
