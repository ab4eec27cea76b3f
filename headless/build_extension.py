"""Build the installable extension zips with Blender's own tool (bpy's bundled blender_ext.py), one per platform.

    python -m headless.build_extension --out dist [--wheels DIR] [--platforms linux-x64,windows-x64,...]
    python -m headless.build_extension --download-wheels DIR   (what `make` runs: every platform's wheels)
Then in Blender: Edit > Preferences > Get Extensions > Install from Disk, and pick the zip for your platform.

The add-on imports OpenEXR, xatlas, Pillow and onnxruntime inside Blender, which Blender does not ship: their
wheels (requirements-extension.txt) are bundled, for Python 3.11 (Blender 4.5, 5.0) and 3.13 (Blender 5.1 and later).
Wheels are per platform, so the build makes one zip per platform (linux-x64, windows-x64, macos-arm64, macos-x64),
each with that platform's wheels and `platforms` field; Blender's build tool splits them (`--split-platforms`) and
validates each zip.
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
STAGE_IGNORE = shutil.ignore_patterns(".git", ".venv*", "__pycache__", "bake_out", "bench_out*", "hair_data", "dist",
                                      "build", "tests", ".pytest_cache", ".hypothesis", "*.zip")
# Blender's platform -> the wheel platform tag pip downloads for it (CPython 3.11, what Blender 4.2-5.0 ship).
# pip expands macOS versions downwards itself, not manylinux glibc versions, so those are listed.
PLATFORM_TAGS = {"linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"),
                 "windows-x64": ("win_amd64",), "macos-arm64": ("macosx_14_0_arm64",),
                 "macos-x64": ("macosx_14_0_x86_64",)}
# Blender 4.5 and 5.0 run Python 3.11, Blender 5.1 and later 3.13: each zip carries wheels for both, and Blender
# installs the ones for its own Python.
PYTHON_TAGS = {"3.11": "cp311", "3.13": "cp313"}
# onnxruntime stopped publishing Intel-macOS wheels after 1.23.2; the hair filters (ONNX opset 17) run on it.
PIN_OVERRIDES = {"macos-x64": {"onnxruntime": "1.23.2"}}


def requirements(platform: str) -> list[str]:
    """requirements-extension.txt's pins for `platform`, with that platform's overrides."""
    pins = [line.strip() for line in (REPO / "requirements-extension.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    overrides = PIN_OVERRIDES.get(platform, {})
    return [f"{name}=={overrides[name]}" if (name := pin.split("==")[0].strip().lower()) in overrides else pin
            for pin in pins]


def download_wheels(wheels_dir: Path, platforms=tuple(PLATFORM_TAGS)) -> None:
    """Every platform's wheels into wheels_dir/<platform>/ (pip download; only binary wheels, no dependencies)."""
    for platform in platforms:
        for python, abi in PYTHON_TAGS.items():
            target = Path(wheels_dir) / platform
            command = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                       *(arg for tag in PLATFORM_TAGS[platform] for arg in ("--platform", tag)),
                       "--python-version", python, "--implementation", "cp",
                       "--abi", abi, "-d", str(target), *requirements(platform)]
            result = subprocess.run(command, capture_output=True, text=True)
            if result.returncode != 0:
                errors = [line for line in result.stderr.splitlines() if line.startswith("ERROR")]
                raise RuntimeError(f"wheels for {platform}, Python {python}: {' '.join(errors) or result.stderr[-500:]}")


def bundled_wheels(wheels_dir: Path | None, platforms=tuple(PLATFORM_TAGS)) -> dict[str, list[Path]]:
    """{platform: its wheels of requirements-extension.txt} from wheels_dir/<platform>/; {} without a folder."""
    if wheels_dir is None or not Path(wheels_dir).is_dir():
        return {}
    found = {}
    for platform in platforms:
        folder = Path(wheels_dir) / platform
        found[platform] = []
        for pin in requirements(platform):
            name, version = (part.strip() for part in pin.split("=="))
            for python, abi in PYTHON_TAGS.items():
                matches = sorted(folder.glob(f"{name}-{version}-{abi}-*.whl"), key=lambda p: p.name.lower())
                if not matches:
                    raise FileNotFoundError(f"no {name} {version} wheel for {platform}, Python {python} in {folder}; "
                                            "run make (it downloads them) or python -m headless.build_extension "
                                            "--download-wheels DIR")
                found[platform].append(matches[-1])
    return found


def _staged_source(stage: Path, wheels: dict[str, list[Path]]) -> Path:
    source = stage / "sg_lightfield"
    shutil.copytree(REPO, source, ignore=STAGE_IGNORE)
    if wheels:
        (source / "wheels").mkdir()
        listed = []
        for platform_wheels in wheels.values():
            for wheel in platform_wheels:
                if not (source / "wheels" / wheel.name).exists():
                    shutil.copy2(wheel, source / "wheels" / wheel.name)
                    listed.append(wheel.name)
        manifest = (source / "blender_manifest.toml").read_text()
        extra = "wheels = [\n" + "".join(f'  "./wheels/{name}",\n' for name in sorted(listed)) + "]\n"
        extra += f"platforms = {sorted(wheels)!r}\n".replace("'", '"')
        manifest = re.sub(r'(blender_version_min = "[^"]+"\n)', lambda m: m.group(1) + extra, manifest, count=1)
        (source / "blender_manifest.toml").write_text(manifest)
    return source


def blender_ext_script() -> Path:
    import bpy  # only to locate the bundled scripts

    script = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    if not script.is_file():
        raise FileNotFoundError(f"Blender's extension tool not found at {script}")
    return script


def build_all(out_dir: Path, wheels_dir: Path | None = DEFAULT_WHEELS,
              platforms=tuple(PLATFORM_TAGS)) -> dict[str, Path]:
    """{platform: zip}: one zip per platform with its wheels (one zip for all platforms, "any", without wheels)."""
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    wheels = bundled_wheels(wheels_dir, platforms)
    before = set(out_dir.glob("sg_lightfield-*.zip"))
    with tempfile.TemporaryDirectory(prefix="sglf-extension-") as stage:
        source = _staged_source(Path(stage), wheels)
        result = subprocess.run(
            [sys.executable, str(blender_ext_script()), "build", "--source-dir", str(source), "--output-dir",
             str(out_dir), *(["--split-platforms"] if wheels else [])], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"extension build failed:\n{result.stdout}\n{result.stderr}")
    zips = {}
    for path in sorted(set(out_dir.glob("sg_lightfield-*.zip")) - before or out_dir.glob("sg_lightfield-*.zip")):
        platform = next((p for p in wheels if path.stem.endswith(p.replace("-", "_"))), "any")
        zips[platform] = path
    if wheels and set(zips) != set(wheels):
        raise RuntimeError(f"extension build wrote {sorted(p.name for p in zips.values())} into {out_dir}, not one zip "
                           f"per platform of {sorted(wheels)}:\n{result.stdout}")
    return zips


def build(out_dir: Path, wheels_dir: Path | None = DEFAULT_WHEELS, platform: str = "linux-x64") -> Path:
    """The zip for one platform."""
    zips = build_all(out_dir, wheels_dir, (platform,))
    return zips.get(platform) or zips["any"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="dist", help="output folder (default: dist)")
    parser.add_argument("--wheels", type=Path, default=DEFAULT_WHEELS,
                        help="folder with a sub-folder of wheels per platform (default: .venv/wheels)")
    parser.add_argument("--platforms", default=",".join(PLATFORM_TAGS),
                        help="comma-separated subset of " + ",".join(PLATFORM_TAGS))
    parser.add_argument("--download-wheels", type=Path, metavar="DIR",
                        help="download every platform's wheels into DIR/<platform>/ and stop")
    args = parser.parse_args(argv)
    platforms = [p for p in args.platforms.split(",") if p]
    unknown = sorted(set(platforms) - set(PLATFORM_TAGS))
    if unknown:
        print(f"error: unknown platform {', '.join(unknown)}; choose from {', '.join(PLATFORM_TAGS)}", file=sys.stderr)
        return 1
    try:
        if args.download_wheels:
            download_wheels(args.download_wheels, platforms)
            print(f"wheels for {', '.join(platforms)} in {args.download_wheels}")
            return 0
        for platform, path in build_all(Path(args.out), args.wheels, platforms).items():
            print(f"{platform}: {path}")
    except (RuntimeError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
