"""bench_out/results.md: pictures first, every section's numbers as tables, no non-finite number written."""
import math
import re

import numpy as np

from sg_lightfield.bake_directory.bake_report import save_png
from sg_lightfield.headless.bench_results import results_markdown, write_results_page


RESULTS = {
    "presets": [{"scene": "spheres", "preset": "draft", "bake_s": 55.21234, "flip": 0.04551, "psnr_db": math.inf,
                 "per_material": {"Floor": 0.1}},
                {"scene": "room", "preset": "draft", "bake_s": 54.5, "flip": math.nan, "converged": True}],
    "render": {"atlas_s": 55.7, "per_texel_s": 232.0, "speedup": 4.17, "devices": ["cpu"],
               "cut": {"with_s": 58.1, "without_s": 105.4}, "rows": [{"texels": 4780, "spp": 16}]},
}


def test_every_section_becomes_a_table_with_finite_cells_only():
    page = results_markdown(RESULTS, ["pareto.png", "room_draft/evaluate_view0_three_way.png"])
    assert page.index("## Pictures") < page.index("## presets") < page.index("## render")
    assert "![pareto](pareto.png)" in page
    assert "| scene | preset | bake_s | flip | psnr_db | converged |" in page  # union of scalar columns, in order
    assert "| spheres | draft | 55.21 | 0.04551 | — | — |" in page
    assert "| room | draft | 54.5 | — | — | yes |" in page
    assert "| atlas_s | 55.7 |" in page and "### render: cut" in page and "| 4780 | 16 |" in page
    assert not re.search(r"\bnan\b|\binf", page.lower())


def test_the_page_is_written_beside_bench_json_with_the_plots_and_each_bakes_comparison(tmp_path):
    picture = np.zeros((4, 4, 3), np.float32)
    save_png(tmp_path / "pareto.png", picture)
    save_png(tmp_path / "spheres_draft" / "evaluate_view0_three_way.png", picture)
    save_png(tmp_path / "spheres_draft" / "capture_normal.png", picture)  # a bake's detail, not listed
    path = write_results_page(tmp_path, RESULTS)
    page = path.read_text()
    assert path == tmp_path / "results.md"
    assert "(pareto.png)" in page and "(spheres_draft/evaluate_view0_three_way.png)" in page
    assert "capture_normal" not in page
    assert not list(tmp_path.glob(".results.md.*"))  # written atomically, nothing left behind
