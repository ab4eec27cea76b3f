"""Build the installable extension zip with Blender's own tool (bpy's bundled blender_ext.py).

    python -m headless.build_extension --out dist [--wheels DIR]
Then in Blender: Edit > Preferences > Get Extensions > Install from Disk, and pick the zip.

The add-on imports OpenEXR, xatlas, Pillow and onnxruntime inside Blender, which Blender does not ship: their wheels
(requirements-extension.txt, fetched by `make` into .venv/wheels) are bundled and listed in the zip's
manifest, which then declares the platform those wheels are for.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEFAULT_WHEELS = REPO / ".venv" / "wheels"
STAGE_IGNORE = shutil.ignore_patterns(".git", ".venv", "__pycache__", "bake_out", "bench_out*", "hair_data", "dist",
                                      "build", "tests", ".pytest_cache", ".hypothesis", "*.zip")
WHEEL_PLATFORMS = {"manylinux": "linux-x64", "win_amd64": "windows-x64", "macosx": "macos-arm64"}


def bundled_wheels(wheels_dir: Path | None) -> list[Path]:
    """The wheels of requirements-extension.txt found in `wheels_dir` (one per requirement), or []."""
    if wheels_dir is None or not Path(wheels_dir).is_dir():
        return []
    names = [line.split("==")[0].strip().lower() for line in (REPO / "requirements-extension.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    found = []
    for name in names:
        matches = sorted(Path(wheels_dir).glob(f"{name}-*.whl"), key=lambda p: p.name.lower())
        if not matches:
            raise FileNotFoundError(f"no wheel for {name} in {wheels_dir}; run make (it downloads them)")
        found.append(matches[-1])
    return found


def _staged_source(stage: Path, wheels: list[Path]) -> Path:
    source = stage / "sg_lightfield"
    shutil.copytree(REPO, source, ignore=STAGE_IGNORE)
    if wheels:
        (source / "wheels").mkdir()
        for wheel in wheels:
            shutil.copy2(wheel, source / "wheels" / wheel.name)
        platforms = sorted({platform for key, platform in WHEEL_PLATFORMS.items()
                            if all(key in w.name or "none-any" in w.name for w in wheels)})
        manifest = (source / "blender_manifest.toml").read_text()
        extra = "wheels = [\n" + "".join(f'  "./wheels/{w.name}",\n' for w in wheels) + "]\n"
        extra += f"platforms = {platforms!r}\n".replace("'", '"')
        manifest = re.sub(r'(blender_version_min = "[^"]+"\n)', lambda m: m.group(1) + extra, manifest, count=1)
        (source / "blender_manifest.toml").write_text(manifest)
    return source


def blender_ext_script() -> Path:
    import bpy  # only to locate the bundled scripts

    script = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    if not script.is_file():
        raise FileNotFoundError(f"Blender's extension tool not found at {script}")
    return script


def build(out_dir: Path, wheels_dir: Path | None = DEFAULT_WHEELS) -> Path:
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="sglf-extension-") as stage:
        source = _staged_source(Path(stage), bundled_wheels(wheels_dir))
        result = subprocess.run(
            [sys.executable, str(blender_ext_script()), "build", "--source-dir", str(source), "--output-dir",
             str(out_dir)], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"extension build failed:\n{result.stdout}\n{result.stderr}")
    zips = sorted(out_dir.glob("sg_lightfield-*.zip"), key=lambda p: p.stat().st_mtime)
    if not zips:
        raise RuntimeError(f"extension build wrote no zip into {out_dir}:\n{result.stdout}")
    return zips[-1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="dist", help="output folder (default: dist)")
    parser.add_argument("--wheels", type=Path, default=DEFAULT_WHEELS, help="folder with the bundled wheels")
    args = parser.parse_args(argv)
    try:
        print(build(Path(args.out), args.wheels))
    except (RuntimeError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
