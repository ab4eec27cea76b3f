"""Python environments with the Blender LTS releases as modules (bpy 4.2 and 4.5 are on PyPI for Python 3.11), each
under .venv-blender/VERSION with the packages the pipeline imports inside Blender, made once and reused.

    python tests/blender_environments.py 4.5.15 4.2.23
`make test` makes them before the suite (tests/test_blender_versions.py makes one on first use otherwise)."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ENVIRONMENTS = REPO / ".venv-blender"
# what the pipeline imports inside Blender besides bpy (pinned as in requirements.txt)
PACKAGES = ["numpy==1.26.4", "openexr==3.5.3", "xatlas==0.0.11", "pillow==11.3.0", "onnxruntime==1.31.1",
            "flip-evaluator==1.7", "scipy==1.13.1"]


def blender_module_python(version: str) -> Path:
    """A Python 3.11 with bpy==version and the pipeline's packages (made once, reused)."""
    venv = ENVIRONMENTS / version
    python = venv / "bin" / "python"
    marker = venv / ".complete"
    if not marker.is_file():
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
        base = subprocess.run([str(python), "-c", "import sys; print(sys.version_info[:2])"], capture_output=True,
                              text=True)
        if base.stdout.strip() != "(3, 11)":
            raise RuntimeError(f"{python} is Python {base.stdout.strip()}, bpy {version} needs 3.11")
        install = subprocess.run([str(python), "-m", "pip", "install", "--quiet", f"bpy=={version}", *PACKAGES],
                                 capture_output=True, text=True)
        if install.returncode != 0:
            raise RuntimeError(f"installing bpy {version} failed: {install.stderr[-2000:]}")
        marker.write_text(version)
    return python


if __name__ == "__main__":
    for version in sys.argv[1:]:
        print(blender_module_python(version))
