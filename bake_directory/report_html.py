"""report.html: one self-contained page per bake (pictures embedded as data URIs), from report.json, plan.json
and the PNGs the stages wrote. Pure Python; rewritten after every stage.

Read top to bottom as a user does: the verdict (time, size on disk, FLIP of EEVEE with the bake and without it),
a large comparison per view (Cycles reference | EEVEE alone | EEVEE with the bake, and a before/after slider),
the table per material, then the details folded away (plan, numbers, capture maps, light fields, training)."""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from .atomic import atomic_output
from .bake_plan import STAGES
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


def _numbers_rows(report: dict) -> list:
    """(label, value) rows of every measured number, for the folded details."""
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
    if "reference_samples" in errors:
        rows.append(("samples per pixel", f"reference {errors['reference_samples']} (two halves), the baked scene "
                                          f"{errors.get('test_samples', errors['reference_samples'])}"))
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
                                              f"{_flip(entry.get('reference_noise_flip'))}; {entry['pixels']} pixels)")
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
    return rows


def _seconds(value: float) -> str:
    value = float(value)
    if value < 60:
        return f"{value:.1f} s"
    minutes, seconds = divmod(round(value), 60)
    return f"{minutes} min {seconds:02d} s" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


def _megabytes(size: int) -> str:
    return f"{size / 1e6:.1f} MB" if size >= 1e5 else f"{size / 1e3:.0f} kB"


def _disk_sizes(out_dir: Path) -> tuple[int, int]:
    """Bytes of the whole bake directory (report.html left out) and of the textures the baked scene reads."""
    files = [p for p in out_dir.rglob("*") if p.is_file() and p.name != "report.html" and not p.name.startswith(".")]
    scene_reads = sum(p.stat().st_size for p in files if p.parent == out_dir and p.name.startswith("sg_")
                      and p.suffix == ".exr")
    return sum(p.stat().st_size for p in files), scene_reads


def _flip(value) -> str:
    return "—" if value is None else f"{value:.3f}"


SAME_WITHIN = 0.05  # per-material FLIPs within 5 % of each other are a tie, not a gain or a loss


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the PNG's IHDR chunk (bytes 16-24), without reading the rest."""
    with open(path, "rb") as png:
        header = png.read(24)[16:24]
    return int.from_bytes(header[:4], "big"), int.from_bytes(header[4:], "big")


def _verdict(report: dict, plan: dict, out_dir: Path) -> list[str]:
    esc = html.escape
    errors = report.get("errors", {})
    eevee = errors.get("eevee") or {}
    alone = errors.get("eevee_without_bake") or {}
    timings = report.get("timings_s", {})
    total, scene_reads = _disk_sizes(out_dir)
    parts = ['<section id="verdict">']
    baked, without = eevee.get("flip"), alone.get("flip")
    if baked is not None and without is not None:
        if baked < without:
            line = (f"The bake brings EEVEE {without / baked:.1f}&times; closer to the path-traced reference: "
                    f"FLIP {baked:.3f} with the bake, {without:.3f} without it.")
            css = "better"
        else:
            line = (f"Here EEVEE alone is closer to the path-traced reference: FLIP {without:.3f} without the bake, "
                    f"{baked:.3f} with it. The table per material below shows where the bake gains and loses.")
            css = "worse"
        parts.append(f'<p class="verdict {css}">{line}</p>')
    elif baked is not None:
        parts.append(f'<p class="verdict">EEVEE with the bake: FLIP {baked:.3f} against the path-traced reference '
                     f'(EEVEE without the bake: {esc(alone.get("error", "not rendered"))}).</p>')
    elif "flip" in errors:
        parts.append(f'<p class="verdict">Cycles rendering the baked materials: FLIP {errors["flip"]:.3f} against the '
                     f'path-traced reference (EEVEE: {esc(eevee.get("error", "not rendered"))}).</p>')
    else:
        parts.append('<p class="verdict">Not evaluated yet: the evaluate stage compares the bake with a path-traced '
                     'reference.</p>')
    facts = []
    if timings:
        order = [s for s in STAGES if s in timings] + [s for s in timings if s not in STAGES]
        stages = " · ".join(f"{esc(stage)} {_seconds(timings[stage])}" for stage in order)
        facts.append(f"<li><b>Time</b> {_seconds(sum(timings.values()))} ({stages})</li>")
    facts.append(f"<li><b>On disk</b> {_megabytes(total)} in the bake directory"
                 + (f", of which the scene reads {_megabytes(scene_reads)} of SG textures" if scene_reads else "")
                 + "</li>")
    if "flip" in errors and baked is not None:
        facts.append(f"<li><b>Cycles rendering the baked materials</b> FLIP {errors['flip']:.3f}</li>")
    if plan.get("summary"):
        facts.append(f"<li><b>Plan</b> {esc(plan['summary'])}</li>")
    parts.append("<ul class=facts>" + "".join(facts) + "</ul>")
    parts += [f"<p class=warning>&#9888; {esc(warning)}</p>" for warning in plan.get("warnings", [])]
    parts.append("</section>")
    return parts


def _comparisons(errors: dict, out_dir: Path) -> list[str]:
    """Per view: a before/after slider over EEVEE with the bake, then reference | EEVEE alone | EEVEE with the bake."""
    eevee = errors.get("eevee") or {}
    alone = errors.get("eevee_without_bake") or {}
    baked_views = eevee.get("views", []) if "error" not in eevee else []
    alone_views = alone.get("views", []) if "error" not in alone else []
    parts = []
    for k, view in enumerate(baked_views):
        pictures = dict(view.get("pictures", {}))
        if k < len(alone_views):
            pictures.update(alone_views[k].get("pictures", {}))
        if not all((out_dir / pictures.get(name, "-")).is_file() for name in ("reference", "eevee_baked")):
            continue
        data = {name: _data_uri(out_dir / path) for name, path in pictures.items() if (out_dir / path).is_file()}
        before = "eevee_alone" if "eevee_alone" in data else "reference"
        labels = {"reference": "Cycles reference", "eevee_alone": "EEVEE alone", "eevee_baked": "EEVEE with the bake"}
        flips = {"eevee_baked": view.get("flip"), "eevee_alone": alone_views[k].get("flip") if k < len(alone_views)
                 else None}
        title = "scene camera" if k == 0 else f"view {k}"
        width, height = _png_size(out_dir / pictures["eevee_baked"])
        fit = f"max-width:min(100%, calc(60vh * {width} / {max(height, 1)}))"  # the whole picture on the first screen
        parts.append(f'<h2>{title}</h2><figure class="slider" data-view="{k}" style="{fit}">'
                     f'<div class=stack><img class=after alt="EEVEE with the bake" src="{data["eevee_baked"]}">'
                     f'<img class=before alt="{labels[before]}" src="{data[before]}"></div>'
                     f'<input type=range min=0 max=100 value=50 aria-label="before and after">'
                     f'<figcaption><span class=left>&larr; <select>'
                     + "".join(f'<option value="{data[name]}"{" selected" if name == before else ""}>{labels[name]}'
                               f'</option>' for name in ("eevee_alone", "reference") if name in data)
                     + '</select></span><span class=right>EEVEE with the bake &rarr;</span></figcaption></figure>')
        cells = []
        for name in ("reference", "eevee_alone", "eevee_baked"):
            if name in data:
                caption = labels[name] + (f" · FLIP {_flip(flips[name])}" if flips.get(name) is not None else "")
                cells.append(f'<figure><img alt="{labels[name]}" src="{data[name]}"><figcaption>{caption}'
                             f'</figcaption></figure>')
        parts.append("<div class=row>" + "".join(cells) + "</div>")
    return parts


def _materials_table(plan: dict, errors: dict) -> list[str]:
    eevee = errors.get("eevee") or {}
    alone = errors.get("eevee_without_bake") or {}
    by_baked = eevee.get("flip_by_material", {}) if "error" not in eevee else {}
    by_alone = alone.get("flip_by_material", {}) if "error" not in alone else {}
    by_cycles = errors.get("flip_by_material", {})
    what = {}
    for entry in plan.get("objects", []):
        for material in entry.get("materials", []):
            if material["name"] in what:
                continue
            textured = f" (textured: {', '.join(material['textured'])})" if material.get("textured") else ""
            if material.get("glossy"):
                what[material["name"]] = f"{material.get('sg_count')} SGs{textured}"
            elif material.get("irradiance_only"):
                what[material["name"]] = f"irradiance lightmap{textured}"
            else:
                what[material["name"]] = "left to the renderer: " + material.get("reason", "")
    names = list(dict.fromkeys([*by_alone, *by_baked, *by_cycles]))
    pixel_count = {name: (by_baked.get(name) or by_alone.get(name) or by_cycles.get(name) or {}).get("pixels") or 0
                   for name in names}
    names.sort(key=lambda name: -pixel_count[name])  # the surfaces most in view first
    if not names:
        return []
    esc = html.escape
    rows = ["<h2>Per material</h2><table class=materials><tr><th>material</th><th>FLIP, EEVEE alone</th>"
            "<th>FLIP, EEVEE with the bake</th><th>FLIP, Cycles with the bake</th><th>reference noise</th>"
            "<th>pixels</th><th>what the bake does</th></tr>"]
    for name in names:
        cycles = by_cycles.get(name, {})
        baked, without = (by_baked.get(name) or {}).get("flip"), (by_alone.get(name) or {}).get("flip")
        left_alone = what.get(name, "").startswith("left to the renderer")
        css = "" if baked is None or without is None or left_alone or abs(baked - without) <= SAME_WITHIN * without \
            else (" class=gain" if baked < without else " class=loss")
        pixels = (by_baked.get(name) or by_alone.get(name) or cycles).get("pixels")
        rows.append(f"<tr{css}><th>{esc(name)}</th><td>{_flip(without)}</td><td>{_flip(baked)}</td>"
                    f"<td>{_flip(cycles.get('flip'))}</td><td>{_flip(cycles.get('reference_noise_flip'))}</td>"
                    f"<td>{pixels if pixels is not None else '—'}</td><td>{esc(what.get(name, ''))}</td></tr>")
    rows.append("</table>")
    return rows


STYLE = """body{font:15px/1.45 system-ui,sans-serif;max-width:1200px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.5em;margin-bottom:.2em}.verdict{font-size:1.25em;margin:.4em 0}.verdict.better{color:#14632a}
.verdict.worse{color:#8a3b00}.facts{list-style:none;padding:0;color:#444}.facts li{margin:.15em 0}
.warning{color:#8a3b00}.slider{margin:0}.stack{position:relative;line-height:0}
.stack img{width:100%;display:block}.stack img.before{position:absolute;top:0;left:0}
.slider input{width:100%;margin:.4em 0}.slider figcaption{display:flex;justify-content:space-between}
.row{display:flex;gap:6px}.row figure{flex:1;margin:0}.row img{width:100%}
table{border-collapse:collapse;margin:.5em 0}td,th{padding:3px 10px;text-align:left;vertical-align:top}
tr:nth-child(even){background:#f3f3f3}tr.gain td:nth-child(3){color:#14632a;font-weight:600}
tr.loss td:nth-child(3){color:#8a3b00;font-weight:600}details{margin:.6em 0}summary{cursor:pointer;font-weight:600}
details img{max-width:100%;image-rendering:pixelated}"""

SLIDER_SCRIPT = """document.querySelectorAll('figure.slider').forEach(function (figure) {
  var range = figure.querySelector('input'), before = figure.querySelector('img.before');
  var choice = figure.querySelector('select');
  function show() { before.style.clipPath = 'inset(0 ' + (100 - range.value) + '% 0 0)'; }
  range.addEventListener('input', show);
  if (choice) choice.addEventListener('change', function () { before.src = choice.value; });
  show();
});"""


def _data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


def write_report_html(out_dir) -> Path:
    out_dir = Path(out_dir)
    report = json.loads((out_dir / "report.json").read_text()) if (out_dir / "report.json").is_file() else {}
    plan = json.loads((out_dir / "plan.json").read_text()) if (out_dir / "plan.json").is_file() else {}
    esc = html.escape
    errors = report.get("errors", {})
    eevee = errors.get("eevee") or {}
    parts = ["<!doctype html><meta charset=utf-8><meta name=viewport content='width=device-width'>"
             "<title>SG Lightfield bake report</title>", f"<style>{STYLE}</style>",
             f"<h1>SG Lightfield bake: {esc(plan.get('scene', ''))}</h1>"]
    parts += _verdict(report, plan, out_dir)
    parts += _comparisons(errors, out_dir)
    parts += _materials_table(plan, errors)
    parts.append("<details><summary>Plan: what is baked and what is left to the renderer</summary><ul>")
    parts += [f"<li>{esc(line)}</li>" for line in plan.get("decisions", [])]
    parts.append("</ul></details>")
    parts.append("<details><summary>Numbers: stages, texels, errors, refits</summary><table>")
    for key, value in _numbers_rows(report):
        if value is not None:
            parts.append(f"<tr><th>{esc(key)}</th><td>{esc(str(round(value, 5) if isinstance(value, float) else value))}"
                         "</td></tr>")
    parts.append("</table></details>")
    details = [(name, caption) for name, caption in PICTURE_CAPTIONS if (out_dir / name).is_file()]
    details += [(view["picture"], f"{view['view']}: reference | Cycles with the bake | FLIP error (FLIP "
                                  f"{view['flip']:.4f}, PSNR {_psnr(view['psnr'])})") for view in errors.get("views", [])
                if (out_dir / view["picture"]).is_file()]
    if eevee and "error" not in eevee:
        details += [(view["picture"], f"view {k}: Cycles reference | EEVEE with the bake | FLIP error "
                                      f"(FLIP {view['flip']:.4f}, PSNR {_psnr(view['psnr'])})")
                    for k, view in enumerate(eevee.get("views", [])) if (out_dir / view["picture"]).is_file()]
    if details:
        parts.append("<details><summary>Pictures: capture maps, light fields, training, error maps</summary>")
        parts += [f"<figure>{_image(out_dir / name)}<figcaption>{esc(caption)}</figcaption></figure>"
                  for name, caption in details]
        parts.append("</details>")
    parts.append(f"<script>{SLIDER_SCRIPT}</script>")
    path = out_dir / "report.html"
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(parts), encoding="utf-8")
    return path
