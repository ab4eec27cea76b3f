"""Blender releases other than the pinned bpy: the LTS releases as Python modules (bpy 4.2 and 4.5 on PyPI for
Python 3.11), each in an environment of its own under .venv-blender/ (tests/blender_environments.py: made by
`make test` before the suite, or here on first use), run the pipeline through
tests/blender_version_check.py. 4.5 runs all of it; 4.2 is refused with one clear sentence, because Cycles' custom
OSL camera, which renders the light fields, first shipped in 4.5. The manifest's blender_version_min says the same."""
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from sg_lightfield.blender_addon.scene_analysis import MIN_BLENDER, require_blender_version
from sg_lightfield.bake_directory.bake_plan import BakeInputError
from tests.blender_environments import blender_module_python

REPO = Path(__file__).resolve().parent.parent
LTS_RELEASES = ("4.5.15", "4.2.23")  # the Makefile's BLENDER_LTS


def run_check(version: str, out: Path, extension_zip: Path | None = None) -> dict:
    env = {**os.environ, "SGLF_TORCH_PYTHON": sys.executable}  # training in the project's Python with torch
    command = [str(blender_module_python(version)), str(REPO / "tests" / "blender_version_check.py"), str(out)]
    result = subprocess.run(command + ([str(extension_zip)] if extension_zip else []), capture_output=True,
                            text=True, env=env, timeout=1800, cwd=REPO)
    steps = {}
    for line in result.stdout.splitlines():
        if line.startswith('{"step"'):
            entry = json.loads(line)
            steps[entry["step"].split(" (")[0]] = entry
    return steps


def test_the_minimum_blender_is_the_one_with_the_custom_osl_camera():
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert manifest["blender_version_min"] == ".".join(map(str, MIN_BLENDER)) == "4.5.0"
    with pytest.raises(BakeInputError, match=r"needs Blender 4\.5\.0 or later: .*custom OSL camera, which Blender "
                                             r"4\.2\.23 does not have"):
        require_blender_version((4, 2, 23))
    require_blender_version((4, 5, 0))
    require_blender_version((5, 0, 1))


@pytest.mark.slow
def test_blender_4_5_lts_installs_the_extension_and_bakes_end_to_end(tmp_path):
    from sg_lightfield.headless.build_extension import build

    steps = run_check(LTS_RELEASES[0], tmp_path, build(tmp_path / "dist", platform="linux-x64"))
    failed = {name: entry["error"] for name, entry in steps.items() if not entry["ok"]}
    assert not failed and len(steps) == 5, (failed, list(steps))
    bake = steps["bake spheres"]["detail"]
    assert bake["training_python"] == "SGLF_TORCH_PYTHON" and 0 < bake["flip"] < 0.5
    assert bake["eevee_error"] is None and 0 < bake["eevee_flip"] < 0.5  # EEVEE of 4.5 ("EEVEE Next") renders it
    # and EEVEE alone, its light probes baked by 4.5's own bake, for the comparison
    assert bake["eevee_alone_error"] is None and 0 < bake["eevee_alone_flip"] < 1
    assert steps["capture demo:geometry"]["detail"]["texels"] > 0


@pytest.mark.slow
def test_blender_4_2_lts_is_told_which_release_the_bake_needs(tmp_path):
    steps = run_check(LTS_RELEASES[1], tmp_path)
    assert steps["register"]["ok"]  # the add-on loads; the bake says why it cannot run
    for name in ("bake spheres", "capture demo:materials", "capture demo:geometry"):
        assert not steps[name]["ok"]
        assert "BakeInputError: the bake needs Blender 4.5.0 or later" in steps[name]["error"], steps[name]["error"]
