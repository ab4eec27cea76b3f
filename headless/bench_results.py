"""bench_out/results.md: the bench's pictures first, then each section's numbers as tables.

Written by `python -m headless.bench` after every run from everything bench.json holds (sections run earlier
included). Pure Python: rows of scalars become one table per list, nested records a table of their scalars and a
sub-table per list inside them. Non-finite numbers are written as "—", never as NaN or Infinity.
"""
from __future__ import annotations

import math
from pathlib import Path

from ..bake_directory.atomic import atomic_output

MAX_COLUMNS = 14


def _cell(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "—"
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        return " / ".join(_cell(float(v) if isinstance(v, float) else v) for v in value) if len(value) <= 6 else \
            f"{len(value)} values"
    text = str(value).replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= 80 else text[:77] + "..."


def _is_scalar(value) -> bool:
    return value is None or isinstance(value, (str, int, float, bool)) or (
        isinstance(value, (list, tuple)) and len(value) <= 6
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))


def _rows_table(rows: list) -> list[str]:
    records = [row for row in rows if isinstance(row, dict)]
    if not records:
        return ["| value |", "|---|", *(f"| {_cell(row)} |" for row in rows)] if all(map(_is_scalar, rows)) else []
    columns: list[str] = []
    for record in records:
        for key, value in record.items():
            if key not in columns and _is_scalar(value):
                columns.append(key)
    columns = columns[:MAX_COLUMNS]
    if not columns:
        return []
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(record.get(key)) for key in columns) + " |" for record in records]
    return lines


def _section(name: str, value, level: int) -> list[str]:
    lines = ["#" * level + f" {name}", ""]
    if isinstance(value, list):
        lines += _rows_table(value)
    elif isinstance(value, dict):
        scalars = {k: v for k, v in value.items() if _is_scalar(v)}
        if scalars:
            lines += ["| measure | value |", "|---|---|"]
            lines += [f"| {_cell(k)} | {_cell(v)} |" for k, v in scalars.items()]
        for key, inner in value.items():
            if key in scalars or level >= 4:
                continue
            if isinstance(inner, (list, dict)) and inner:
                lines += [""] + _section(f"{name}: {key}", inner, level + 1)
    else:
        lines.append(_cell(value))
    lines.append("")
    return lines


def results_markdown(results: dict, pictures: list[str]) -> str:
    """The page for bench.json's `results`, with `pictures` (paths relative to the page) first."""
    lines = ["# Benchmark results", "",
             "Written by `python -m headless.bench` from bench.json; conditions (machine, scenes, presets) are in "
             "each section's rows and in the command that ran it.", ""]
    if pictures:
        lines += ["## Pictures", ""]
        lines += [f"![{Path(p).stem}]({p})" for p in pictures]
        lines.append("")
    for name, value in results.items():
        lines += _section(name, value, 2)
    return "\n".join(lines).rstrip() + "\n"


def write_results_page(out_dir: Path, results: dict) -> Path:
    out_dir = Path(out_dir)
    found = [*out_dir.glob("*.png"), *out_dir.glob("*/*_three_way.png")]  # the bench's plots, each bake's comparison
    pictures = sorted(p.relative_to(out_dir).as_posix() for p in found)
    path = out_dir / "results.md"
    with atomic_output(path) as tmp:
        Path(tmp).write_text(results_markdown(results, pictures), encoding="utf-8")
    return path
