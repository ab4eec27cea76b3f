"""report.html: one self-contained page per bake (pictures embedded as data URIs), from report.json, plan.json
and the PNGs the stages wrote. Pure Python; rewritten after every stage."""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from .atomic import atomic_output
from .image_metrics import rmse_against_converged

PICTURE_CAPTIONS = [
    ("capture_position.png", "Texel positions (atlas)"), ("capture_normal.png", "Texel shading normals"),
    ("capture_validity.png", "Texel validity: white covered, blue partly covered, orange pushed out, red buried, grey gutter"),
    ("render_lightfield.png", "Light fields of 16 texels (octahedral, tone mapped)"),
    ("render_env_visibility.png", "Environment visibility W_E of 16 texels"),
    ("train_lightfield.png", "Rendered light fields (left) and their SG reconstruction (right)"),
    ("train_env_visibility.png", "W_E rendered (left) and its SGs (right)"),
]


def _image(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img src="data:image/png;base64,{data}" style="max-width:100%;image-rendering:pixelated">'


def _psnr(value) -> str:
    """PSNR in dB; report.json holds null where it is infinite (bake and reference identical, e.g. all black)."""
    return "∞ dB (identical images)" if value is None or value == float("inf") else f"{value:.2f} dB"


def _error_rows(label: str, errors: dict, before: dict, before_label: str) -> list:
    """One row per material: its error, and the error before a refit where there is one."""
    return [(f"{label}, {material}", error if material not in before else
             f"{error:.4f} ({before_label} {before[material]:.4f})") for material, error in errors.items()]


def write_report_html(out_dir) -> Path:
    out_dir = Path(out_dir)
    report = json.loads((out_dir / "report.json").read_text()) if (out_dir / "report.json").is_file() else {}
    plan = json.loads((out_dir / "plan.json").read_text()) if (out_dir / "plan.json").is_file() else {}
    esc = html.escape
    parts = ["<!doctype html><meta charset=utf-8><title>SG Lightfield bake report</title>",
             "<style>body{font:14px sans-serif;max-width:1100px;margin:2em auto}td,th{padding:2px 10px;"
             "text-align:left}table{border-collapse:collapse}tr:nth-child(even){background:#f3f3f3}</style>",
             f"<h1>SG Lightfield bake: {esc(plan.get('scene', ''))}</h1>",
             f"<p><b>Plan:</b> {esc(plan.get('summary', ''))}</p><ul>"]
    parts += [f"<li>{esc(line)}</li>" for line in plan.get("decisions", [])]
    parts.append("</ul>")
    for warning in plan.get("warnings", []):
        parts.append(f"<p>&#9888; {esc(warning)}</p>")
    parts.append("<h2>Numbers</h2><table>")
    timings = report.get("timings_s", {})
    rows = [("texels", report.get("texels")), ("coverage %", report.get("coverage_percent")),
            ("pushed-out texels", report.get("pushed_out_texels")), ("buried texels", report.get("buried_texels")),
            ("SGs per texel", report.get("sg_count")), ("bytes per texel", report.get("bytes_per_texel"))]
    render = report.get("render", {})
    if render.get("devices"):
        rows.append(("rendered on", ", ".join(render["devices"])))
    apply = report.get("apply", {})
    if apply.get("node_groups"):
        rows.append(("node groups (nodes)", ", ".join(f"{k}: {v}" for k, v in apply["node_groups"].items())))
        rows.append(("SG evaluations saved by per-material counts", apply.get("sg_evaluations_saved")))
        rows += [(f"EEVEE uniform block of '{name}' (bytes, at most {apply.get('eevee_uniform_limit')})", size)
                 for name, size in (apply.get("eevee_uniform_bytes") or {}).items()]
        rows += [("apply warning", warning) for warning in apply.get("warnings", ())]
    rows += [(f"{stage} seconds", seconds) for stage, seconds in timings.items()]
    errors = report.get("errors", {})
    rows += [(f"error {key}", _psnr(errors[key]) if key == "psnr" else errors[key])
             for key in ("rmse", "psnr", "flip", "reference_noise_rmse", "reference_noise_flip") if key in errors]
    rows += [(f"FLIP where {name}", entry["flip"]) for name, entry in errors.get("flip_by_roughness", {}).items()
             if entry.get("pixels")]
    noise_by_class = errors.get("reference_noise_flip_by_roughness", {})
    rows += [(f"RMSE where {name}", f"{entry['rmse']:.4f} (against the converged image "
              f"{rmse_against_converged(entry['rmse'], noise_by_class[name]['rmse']):.4f}; the reference's noise "
              f"{noise_by_class[name]['rmse']:.4f})")
             for name, entry in errors.get("flip_by_roughness", {}).items()
             if entry.get("pixels") and entry.get("rmse") is not None
             and (noise_by_class.get(name) or {}).get("rmse") is not None]
    rows += [(f"FLIP of the reference's own noise where {name} (the floor)", entry["flip"])
             for name, entry in errors.get("reference_noise_flip_by_roughness", {}).items() if entry.get("pixels")]
    rows += [(f"FLIP on material '{name}'", f"{entry['flip']:.4f} (the reference's noise there: "
                                              f"{entry.get('reference_noise_flip', float('nan')):.4f}; "
                                              f"{entry['pixels']} pixels)")
             for name, entry in errors.get("flip_by_material", {}).items()]
    eevee = errors.get("eevee") or {}
    if "error" in eevee:
        rows.append(("EEVEE", f"not rendered: {eevee['error']}"))
    elif eevee:
        rows += [("EEVEE FLIP vs reference", eevee.get("flip")),
                 ("EEVEE PSNR", _psnr(eevee["psnr"]) if "psnr" in eevee else None),
                 ("EEVEE FLIP vs Cycles bake", eevee.get("flip_vs_cycles_bake")),
                 ("EEVEE first render s (incl. shader compile)", eevee.get("first_render_s"))]
        rows += [("EEVEE shader failed (renders magenta)", error) for error in eevee.get("shader_errors", ())]
    without = errors.get("eevee_without_bake") or {}
    if "error" in without:
        rows.append(("EEVEE without the bake", f"not rendered: {without['error']}"))
    elif without:
        rows.append(("EEVEE without the bake FLIP vs reference (ray tracing, baked probes)", without.get("flip")))
    lightfield = report.get("train", {}).get("metrics", {}).get("lightfield", {})
    rows += [(f"light-field fit {key}", value) for key, value in lightfield.items() if not isinstance(value, dict)]
    if "midpoint" in lightfield:
        rows.append(("held-out midpoint RMSE", lightfield["midpoint"]["rmse"]))
    refit = lightfield.get("amplitude_refit", {})
    rows += _error_rows("glossy error through the node group", lightfield.get("shaded_error", {}),
                        refit.get("shaded_error_before", {}), "the CNN's SGs")
    if refit:
        not_kept = [f"; not kept for {material} (it raised the error to {error:.4f})"
                    for material, error in refit.get("reverted_for", {}).items()]
        not_kept += [f"; not kept for {material} (it raised the error between texels to {error:.4f})"
                     for material, error in refit.get("reverted_between_texels_for", {}).items()]
        rows.append(("amplitude refit", f"{refit['texels']} texels at roughness >= {refit['min_roughness']} in "
                                        f"{refit['seconds']:.1f} s" + "".join(not_kept)))
    lobes = refit.get("lobes", {})
    rows += _error_rows("glossy error between texels (SGs blended)", lightfield.get("interpolated_shaded_error", {}),
                        lobes.get("interpolated_error_before", {}), "before the lobe refit")
    if lobes:
        rows.append(("lobe refit (axes, sharpness, amplitudes)",
                     f"{lobes.get('steps')} steps on {lobes.get('texels')} texels at roughness >= "
                     f"{lobes.get('min_roughness')} in {lobes.get('seconds', 0):.1f} s"
                     + (f"; kept unless it raised the error between texels more than {lobes['tolerance']}x"
                        if "tolerance" in lobes else "")
                     + "".join(f"; not kept for {material} (it raised the error between texels to {error:.4f})"
                               for material, error in lobes.get("reverted_for", {}).items())))
    for key, value in rows:
        if value is not None:
            parts.append(f"<tr><th>{esc(key)}</th><td>{esc(str(round(value, 5) if isinstance(value, float) else value))}"
                         "</td></tr>")
    parts.append("</table>")
    alone = errors.get("eevee_without_bake") or {}
    baked_views = eevee.get("views", []) if eevee and "error" not in eevee else []
    pictures = [(view["picture"], f"view {k}: Cycles reference | EEVEE without the bake (FLIP {view['flip']:.4f}) | "
                                  f"EEVEE with the bake" + (f" (FLIP {baked_views[k]['flip']:.4f})"
                                                            if k < len(baked_views) else ""))
                for k, view in enumerate(alone.get("views", [])) if (out_dir / view["picture"]).is_file()]
    pictures += [(name, caption) for name, caption in PICTURE_CAPTIONS if (out_dir / name).is_file()]
    pictures += [(view["picture"], f"{view['view']}: reference | SG bake | FLIP error (FLIP {view['flip']:.4f}, "
                                   f"PSNR {_psnr(view['psnr'])})") for view in errors.get("views", [])
                 if (out_dir / view["picture"]).is_file()]
    if eevee and "error" not in eevee:
        pictures += [(view["picture"], f"view {k}: Cycles reference | EEVEE with the bake | FLIP error "
                                       f"(FLIP {view['flip']:.4f}, PSNR {_psnr(view['psnr'])})")
                     for k, view in enumerate(eevee.get("views", [])) if (out_dir / view["picture"]).is_file()]
    if pictures:
        parts.append("<h2>Pictures</h2>")
    for name, caption in pictures:
        parts.append(f"<figure>{_image(out_dir / name)}<figcaption>{esc(caption)}</figcaption></figure>")
    path = out_dir / "report.html"
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(parts))
    return path
