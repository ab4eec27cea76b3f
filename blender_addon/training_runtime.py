"""The training runtime: a Python with torch and what training needs besides (RUNTIME_REQUIREMENTS) in a virtual
environment of the extension's own.

Blender's Python has no torch, so training runs as a separate process in a Python that has it. An artist gets one
with *Install Training Runtime* in the add-on's preferences: after their consent, and only where Blender allows
online access (or from a folder of wheels, offline), a venv is made from Blender's own Python in the extension's
user directory (`bpy.utils.extension_path_user`) and pip installs the pinned packages into it. The install runs in
the background with progress and cancel; it is built in a staging folder and renamed into place when complete, so a
cancelled or failed install never counts as a runtime.

Which Python trains (`find_torch_python`): the *Python with torch* preference, else the environment variable
SGLF_TORCH_PYTHON (farms), else the installed runtime, else this process when it has torch (bpy as a module), else
python3.11 / python3 on PATH. No bpy here: the operators and the panel call these functions.
"""
from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

# What the train stage imports (requirements.txt's pins): torch, numpy, OpenEXR for the bake directory's EXRs,
# scipy for the baselines' and refits' least squares, Pillow for its pictures.
RUNTIME_REQUIREMENTS = ("torch==2.13.0", "numpy==1.26.4", "openexr==3.5.3", "scipy==1.13.1", "pillow==11.3.0")
RUNTIME_FOLDER = "training_runtime"
MARKER = "sglf_runtime.json"
ENV_VAR = "SGLF_TORCH_PYTHON"
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
TORCH_CUDA_INDEX = "https://download.pytorch.org/whl/cu128"
SOURCES = ("auto", "pip", "wheels")
PROBE = "import torch, numpy, OpenEXR, scipy.optimize, PIL.Image"
TORCH_HELP = ("training needs a Python with torch 2.13, and none was found: install one with Install Training "
              "Runtime (the panel, or the add-on preferences), set Python with torch in the add-on preferences, or set "
              f"{ENV_VAR} to a Python 3.11 with {', '.join(RUNTIME_REQUIREMENTS)}")


class RuntimeInstallError(RuntimeError):
    """One clear sentence on why the runtime cannot be installed or found."""


def nvidia_driver_found(system: str | None = None) -> bool:
    """Whether an NVIDIA driver is installed (then torch's CUDA wheels can use the GPU)."""
    system = system or sys.platform
    if system.startswith("linux"):
        return Path("/proc/driver/nvidia/version").is_file() or shutil.which("nvidia-smi") is not None
    if system == "win32":
        return shutil.which("nvidia-smi") is not None or Path(
            os.environ.get("SystemRoot", r"C:\Windows"), "System32", "nvidia-smi.exe").is_file()
    return False


def runtime_python(venv: Path, system: str | None = None) -> Path:
    system = system or sys.platform
    return Path(venv) / ("Scripts/python.exe" if system == "win32" else "bin/python")


@dataclass
class InstallPlan:
    """What Install Training Runtime will do: where, from which Python, with which pip options, and what it costs."""
    target: Path
    base_python: str
    source: str
    accelerator: str  # "cuda", "cpu" or "cpu or Apple GPU"
    pip_options: list[str] = field(default_factory=list)
    requirements: tuple[str, ...] = RUNTIME_REQUIREMENTS
    needs_network: bool = True

    @property
    def staging(self) -> Path:
        return self.target.with_name(self.target.name + ".partial")

    def description(self) -> str:
        where = {"auto": "PyPI" + (" and download.pytorch.org" if self.pip_options else ""),
                 "pip": "the package index pip is configured with",
                 "wheels": f"the wheels in {self.pip_options[-1] if self.pip_options else '?'} (offline)"}[self.source]
        size = "about 3 GB to download, 6 GB on disk" if self.accelerator == "cuda" else \
            "about 250 MB to download, 1 GB on disk"
        return (f"{', '.join(self.requirements)} ({self.accelerator}) from {where}, {size}, into {self.target}"
                if self.needs_network else
                f"{', '.join(self.requirements)} ({self.accelerator}) from {where}, into {self.target}")


def plan_install(user_dir, *, source: str = "auto", wheel_dir: str = "", base_python: str | None = None,
                 system: str | None = None, nvidia: bool | None = None) -> InstallPlan:
    """The install for this machine. source: 'auto' (CUDA wheels where an NVIDIA driver is found, CPU wheels
    otherwise), 'pip' (whatever pip is configured with: PyPI or a mirror), 'wheels' (offline, from wheel_dir)."""
    system = system or sys.platform
    if source not in SOURCES:
        raise RuntimeInstallError(f"unknown runtime source '{source}'; use one of {', '.join(SOURCES)}")
    target = Path(user_dir) / RUNTIME_FOLDER
    python = base_python or sys.executable
    if source == "wheels":
        folder = Path(wheel_dir).expanduser() if wheel_dir else None
        if folder is None or not folder.is_dir():
            raise RuntimeInstallError(f"the folder of wheels '{wheel_dir}' does not exist; choose the folder that "
                                      "holds the torch, numpy, openexr, scipy and pillow wheels")
        if not list(folder.glob("torch-*.whl")):
            raise RuntimeInstallError(f"no torch wheel (torch-*.whl) in '{folder}'")
        return InstallPlan(target, python, source, "cuda" if "+cu" in " ".join(p.name for p in folder.glob(
            "torch-*.whl")) else "cpu", ["--no-index", "--find-links", str(folder)], needs_network=False)
    if source == "pip":
        return InstallPlan(target, python, source, "as pip resolves it")
    nvidia = nvidia_driver_found(system) if nvidia is None else nvidia
    if system == "darwin":
        return InstallPlan(target, python, source, "cpu or Apple GPU")
    if nvidia:  # Linux's PyPI torch is CUDA already; Windows' is CPU, so its CUDA wheels come from PyTorch's index
        return InstallPlan(target, python, source, "cuda",
                           ["--extra-index-url", TORCH_CUDA_INDEX] if system == "win32" else [])
    # Linux's PyPI torch pulls GBs of CUDA libraries; PyTorch's CPU index has the CPU wheel (+cpu sorts first)
    return InstallPlan(target, python, source, "cpu",
                       ["--extra-index-url", TORCH_CPU_INDEX] if system.startswith("linux") else [])


def installed_runtime(user_dir) -> Path | None:
    """The installed runtime's Python, or None (a staging folder of an unfinished install does not count)."""
    if not user_dir:
        return None
    venv = Path(user_dir) / RUNTIME_FOLDER
    python = runtime_python(venv)
    return python if (venv / MARKER).is_file() and python.is_file() else None


def runtime_record(user_dir) -> dict:
    venv = Path(user_dir) / RUNTIME_FOLDER
    try:
        return json.loads((venv / MARKER).read_text())
    except (OSError, ValueError):
        return {}


def remove_runtime(user_dir) -> bool:
    """Delete the installed runtime and any unfinished install; True when something was removed."""
    removed = False
    for folder in (Path(user_dir) / RUNTIME_FOLDER, Path(user_dir) / (RUNTIME_FOLDER + ".partial")):
        if folder.exists():
            shutil.rmtree(folder)
            removed = True
    return removed


def _has_torch(python: str) -> bool:
    try:
        return subprocess.run([python, "-c", PROBE], capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def torch_in_process() -> bool:
    """Whether this Python can import torch (bpy as a module with the project's requirements; not Blender)."""
    return importlib.util.find_spec("torch") is not None


def find_torch_python(preferred: str = "", user_dir=None, tried: list | None = None) -> tuple[str, str] | None:
    """(python, where it came from) for the first Python that imports what training needs (PROBE), or None. `tried`
    collects 'where: python' for every candidate that exists but lacks them (for the message)."""
    candidates = []
    if preferred:
        candidates.append((preferred, "the Python with torch preference"))
    if os.environ.get(ENV_VAR):
        candidates.append((os.environ[ENV_VAR], f"{ENV_VAR}"))
    runtime = installed_runtime(user_dir)
    if runtime is not None:
        candidates.append((str(runtime), "the installed training runtime"))
    if torch_in_process():
        candidates.append((sys.executable, "this Python"))
    candidates += [(shutil.which(name) or "", f"{name} on PATH") for name in ("python3.11", "python3")]
    for python, origin in candidates:
        if python and os.path.isfile(python):
            if _has_torch(python):
                return python, origin
            if tried is not None:
                tried.append(f"{origin}: {python}")
        elif python and tried is not None and origin in ("the Python with torch preference", ENV_VAR):
            tried.append(f"{origin}: {python} (no such file)")
    return None


def missing_torch_message(help_text: str, tried: list) -> str:
    return help_text + (f" (tried, without torch 2.13, numpy, OpenEXR, scipy and Pillow: {'; '.join(tried)})"
                        if tried else "")


PIP_COLLECTING = re.compile(r"^(Collecting|Processing|Requirement already satisfied:?) (\S+)")


@dataclass
class InstallProgress:
    fraction: float = 0.0
    message: str = "starting"
    done: bool = False
    error: str = ""
    log: list = field(default_factory=list)


class RuntimeInstall:
    """The install as a background thread: start(), poll progress, cancel(). The runtime appears at plan.target only
    when every step succeeded."""

    def __init__(self, plan: InstallPlan, online_allowed: bool = True):
        if plan.needs_network and not online_allowed:
            raise RuntimeInstallError(
                "Blender does not allow online access (Preferences > System > Network > Allow Online Access); "
                "allow it, or install from a folder of wheels")
        self.plan = plan
        self.progress = InstallProgress()
        self._process: subprocess.Popen | None = None
        self._cancelled = False
        self._thread: threading.Thread | None = None

    def start(self) -> "RuntimeInstall":
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> InstallProgress:
        if self._thread is not None:
            self._thread.join(timeout)
        return self.progress

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def cancel(self):
        self._cancelled = True
        process = self._process
        if process is not None and process.poll() is None:
            process.terminate()

    def _step(self, command, fraction_from: float, fraction_to: float, message: str) -> None:
        if self._cancelled:  # cancelled between two steps
            raise InterruptedError
        self.progress.fraction, self.progress.message = fraction_from, message
        env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1", "PYTHONNOUSERSITE": "1"}
        self._process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                         env=env)
        seen = 0
        for line in self._process.stdout:
            line = line.rstrip()
            self.progress.log.append(line)
            match = PIP_COLLECTING.match(line)
            if match:
                seen += 1
                self.progress.message = f"{message}: {Path(match.group(2)).name}"
            elif line.startswith("Installing collected packages"):
                self.progress.message = f"{message}: unpacking"
                seen = max(seen, 20)
            # packages seen so far move the bar towards the step's end without reaching it
            self.progress.fraction = fraction_from + (fraction_to - fraction_from) * (1 - 0.85 ** seen)
        code = self._process.wait()
        if self._cancelled:
            raise InterruptedError
        if code != 0:
            tail = [line for line in self.progress.log[-40:] if line.startswith("ERROR")] or self.progress.log[-3:]
            raise RuntimeInstallError(f"{message} failed: {' '.join(tail)[-400:]}")
        self.progress.fraction = fraction_to

    def _run(self):
        plan, staging = self.plan, self.plan.staging
        try:
            if staging.exists():
                shutil.rmtree(staging)
            self._step([plan.base_python, "-m", "venv", str(staging)], 0.0, 0.08, "creating the environment")
            python = str(runtime_python(staging))
            self._step([python, "-m", "pip", "install", "--progress-bar", "off", *plan.pip_options,
                        *plan.requirements], 0.08, 0.9, "installing torch, numpy, OpenEXR, scipy and Pillow")
            self._step([python, "-c", PROBE + "; print(torch.__version__, torch.cuda.is_available())"], 0.9, 0.97,
                       "checking the runtime")
            version, cuda = (self.progress.log[-1].split() + ["?", "False"])[:2]
            record = {"requirements": list(plan.requirements), "source": plan.source, "torch": version,
                      "cuda_available": cuda == "True", "accelerator": plan.accelerator,
                      "installed": time.strftime("%Y-%m-%d %H:%M:%S")}
            (staging / MARKER).write_text(json.dumps(record, indent=1))
            if plan.target.exists():
                shutil.rmtree(plan.target)
            os.replace(staging, plan.target)
            self.progress.fraction, self.progress.message = 1.0, f"installed: torch {version}" + (
                " with CUDA" if cuda == "True" else "")
        except InterruptedError:
            self.progress.error = "cancelled"
        except (RuntimeInstallError, OSError) as error:
            self.progress.error = str(error)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
            self.progress.done = True
