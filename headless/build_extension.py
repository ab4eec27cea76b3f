"""Build the installable extension zip with Blender's own tool (bpy's bundled blender_ext.py).

    python -m headless.build_extension --out dist
Then in Blender: Edit > Preferences > Get Extensions > Install from Disk, and pick the zip.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def blender_ext_script() -> Path:
    import bpy  # only to locate the bundled scripts

    script = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    if not script.is_file():
        raise FileNotFoundError(f"Blender's extension tool not found at {script}")
    return script


def build(out_dir: Path) -> Path:
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(
        [sys.executable, str(blender_ext_script()), "build", "--source-dir", str(REPO), "--output-dir", str(out_dir)],
        capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"extension build failed:\n{result.stdout}\n{result.stderr}")
    zips = sorted(out_dir.glob("sg_lightfield-*.zip"), key=lambda p: p.stat().st_mtime)
    if not zips:
        raise RuntimeError(f"extension build wrote no zip into {out_dir}:\n{result.stdout}")
    return zips[-1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="dist", help="output folder (default: dist)")
    args = parser.parse_args(argv)
    try:
        print(build(Path(args.out)))
    except (RuntimeError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
