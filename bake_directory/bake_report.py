"""report.json and report pictures of a bake directory (pure Python + numpy + Pillow).

Every stage merges its fields into one ``report.json``; a report made for another plan is started
afresh so numbers of different bakes are never mixed.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .atomic import atomic_output
from .bake_plan import write_json_atomic

REPORT_NAME = "report.json"


def read_report(out_dir) -> dict:
    path = Path(out_dir) / REPORT_NAME
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def update_report(out_dir, plan_hash: str, *, timings_s: dict | None = None, **fields) -> dict:
    """Merge `fields` (and per-stage `timings_s`) into DIR/report.json for the plan `plan_hash`."""
    report = read_report(out_dir)
    if report.get("plan_hash") != plan_hash:
        report = {"plan_hash": plan_hash, "timings_s": {}}
    report.setdefault("timings_s", {}).update({k: round(float(v), 3) for k, v in (timings_s or {}).items()})
    report.update(fields)
    write_json_atomic(Path(out_dir) / REPORT_NAME, report)
    from .report_html import write_report_html
    write_report_html(out_dir)
    return report


def save_png(path, image, *, min_width: int = 512) -> Path:
    """Save an (H, W, 3) or (H, W) float image in [0, 1] as an 8-bit PNG, atomically.

    Small atlases are enlarged by an integer factor (nearest neighbour, so texels stay visible)."""
    from PIL import Image

    path = Path(path)
    data = np.asarray(image, dtype=np.float64)
    data = np.nan_to_num(data, nan=0.0, posinf=1.0, neginf=0.0)
    scale = max(1, -(-min_width // max(data.shape[1], 1)))
    data = np.repeat(np.repeat(data, scale, axis=0), scale, axis=1)
    pixels = np.round(np.clip(data, 0.0, 1.0) * 255).astype(np.uint8)
    with atomic_output(path, suffix=".tmp.png") as tmp:
        Image.fromarray(pixels).save(tmp, format="PNG")
    return path
