"""What a lent GPU machine needs to run Blender's stages: Python 3.11, bpy and the bake's packages, in parts a call
carries.

    python -m headless.gpu_payload --out .gpu [--bakes DIR ...] [--part-mib 48]

The lent machines (docs/design-additions.md §17, §49) have CUDA, torch and Python 3.12 but no Blender, no Python 3.11
(bpy 5.0.1 is built for 3.11 only) and no way to download; a call carries at most 64 MiB. This builds, from this
machine's Python 3.11 and the project's virtual environment:
  python      the interpreter and its standard library (tests, IDLE, Tk and the build configuration left out);
  packages    bpy without what a Linux NVIDIA machine never loads (kept_in_bpy: AMD GPU kernels, CUDA kernels of
              other architectures, the denoiser's GPU devices, USD's Python, the core add-ons but Cycles, the CJK
              font), numpy, OpenEXR, flip-evaluator, Pillow, xatlas;
  sm_90       Cycles' CUDA kernels for Hopper (compute capability 9.0), compiled here by ptxas from the PTX Blender
              ships: bpy 5.0.1 has no sm_90 cubin, and the driver's own compile of that PTX on first use takes
              minutes of the lease;
  system      the glvnd OpenGL/EGL dispatch and X11 client libraries bpy links (the NVIDIA driver brings the vendor
              side), and egl_device/: a stand-in libEGL.so.1 whose default display is the first EGL device's
              (headless/egl_device_display.c), for where the default display does not work;
  wheels      OpenEXR for the machine's Python 3.12, which trains.
into one .tar.xz split in parts of --part-mib MiB under --out/partK/ (a call carries 64 MiB with the repository's
13 MiB), and the --bakes' baked.blend files under --out/bakes/, which the last call carries beside the last part.
headless/gpu_blender_check.sh, run there, unpacks and measures. Needs the zstd and xz commands and gcc.
"""
from __future__ import annotations

import argparse
import io
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
import zipfile
from pathlib import Path

NVCC_WHEEL = "nvidia-cuda-nvcc-cu12==12.8.93"  # its ptxas reads Blender 5.0.1's PTX (ISA 7.4)
OPENEXR_WHEEL = "openexr==3.5.3"
CUDA_ARCH = "sm_90"
STDLIB_LEFT_OUT = ("test", "idlelib", "tkinter", "ensurepip", "lib2to3", "unittest/test", "site-packages")
PACKAGES = ("numpy", "numpy.libs", "OpenEXR", "Imath.py", "flip_evaluator", "flip_evaluator.libs", "PIL",
            "pillow.libs", "xatlas", "bpy")
BPY_LEFT_OUT = ("5.0/python/lib/python3.11/site-packages/pxr", "5.0/python/lib/python3.11/site-packages/MaterialX",
                "5.0/python/lib/python3.11/site-packages/PyOpenColorIO",
                "5.0/datafiles/fonts/Noto Sans CJK Regular.woff2", "lib/usd")
BPY_LEFT_OUT_PATTERNS = ("kernel_gfx", "kernel_rt_gfx", "kernel_sm_", "libOpenImageDenoise_device_")
SYSTEM_LIBS = ("libEGL.so.1", "libGL.so.1", "libGLX.so.0", "libGLdispatch.so.0", "libOpenGL.so.0", "libX11.so.6",
               "libXrender.so.1", "libXfixes.so.3", "libXi.so.6", "libxkbcommon.so.0", "libSM.so.6", "libICE.so.6",
               "libxcb.so.1", "libXext.so.6", "libXau.so.6", "libXdmcp.so.6", "libbsd.so.0", "libmd.so.0",
               "libuuid.so.1")
SYSTEM_LIB_DIR = Path("/lib/x86_64-linux-gnu")


def _site_packages() -> Path:
    return Path(sysconfig.get_paths()["purelib"])


def kept_in_bpy(relative: str) -> bool:
    """Whether the payload keeps the file or folder `relative` (to the bpy package): not what an NVIDIA Linux
    machine never loads (AMD GPU kernels, other CUDA architectures, the denoiser's GPU devices, USD's Python, the
    core add-ons but Cycles)."""
    if "__pycache__" in relative or any(relative.startswith(p) for p in BPY_LEFT_OUT):
        return False
    if any(p in Path(relative).name for p in BPY_LEFT_OUT_PATTERNS):
        return False
    addons = "5.0/scripts/addons_core/"
    return not (relative.startswith(addons) and not relative[len(addons):].startswith("cycles"))


def _bpy_filter(info: tarfile.TarInfo):
    relative = info.name.split("site-packages/bpy/", 1)[1] if "site-packages/bpy/" in info.name else ""
    return info if kept_in_bpy(relative) else None


def _no_cache(info: tarfile.TarInfo):
    return None if "__pycache__" in info.name else info


def cycles_cubin(work: Path) -> bytes:
    """Cycles' CUDA kernels for CUDA_ARCH, zstd-compressed as Cycles reads them, from the PTX Blender ships."""
    lib = _site_packages() / "bpy" / "5.0" / "scripts" / "addons_core" / "cycles" / "lib"
    ptx = work / "kernel.ptx"
    ptx.write_bytes(subprocess.run(["zstd", "-dc", str(lib / "kernel_compute_75.ptx.zst")], check=True,
                                   capture_output=True).stdout)
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                    NVCC_WHEEL, "-d", str(work)], check=True)
    wheel = next(work.glob("nvidia_cuda_nvcc_cu12-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        ptxas = work / "ptxas"
        ptxas.write_bytes(z.read("nvidia/cuda_nvcc/bin/ptxas"))
    ptxas.chmod(0o755)
    cubin = work / f"kernel_{CUDA_ARCH}.cubin"
    print(f"ptxas: Cycles' kernels for {CUDA_ARCH} (about 8 minutes on 2 cores)", flush=True)
    subprocess.run([str(ptxas), f"-arch={CUDA_ARCH}", "-O3", str(ptx), "-o", str(cubin)], check=True)
    return subprocess.run(["zstd", "-19", "-c", str(cubin)], check=True, capture_output=True).stdout


def build_egl_device_display(out_dir: Path) -> Path:
    """headless/egl_device_display.c as out_dir/libEGL.so.1 beside the real glvnd library as libEGL_real.so.1: put
    out_dir first on LD_LIBRARY_PATH and EGL's default display becomes the first EGL device's. Needs gcc and EGL's
    headers (Debian: gcc, libegl-dev)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        stub = Path(tmp) / "libEGL_real.so.1"  # only for linking: records the real library as a dependency by name
        (Path(tmp) / "stub.c").write_text("void sglf_egl_real_stub(void) {}\n")
        subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(stub), str(Path(tmp) / "stub.c"),
                        "-Wl,-soname,libEGL_real.so.1"], check=True)
        subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(out_dir / "libEGL.so.1"),
                        str(Path(__file__).with_name("egl_device_display.c")), "-Wl,-soname,libEGL.so.1",
                        "-Wl,--no-as-needed", str(stub), "-ldl"], check=True)
    shutil.copy2((SYSTEM_LIB_DIR / "libEGL.so.1").resolve(), out_dir / "libEGL_real.so.1")
    return out_dir / "libEGL.so.1"


def build(out: Path, bakes=(), part_mib: int = 48, cubin: Path | None = None) -> list[Path]:
    """The payload as parts out/partK/payload.tar.xz.K; returns the parts."""
    site = _site_packages()
    prefix = Path(sys.base_prefix)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        sm = cubin.read_bytes() if cubin else cycles_cubin(work)
        archive = work / "payload.tar"
        with tarfile.open(archive, "w") as tar:
            tar.add(prefix / "bin" / version, f"p311/bin/{version}")
            for lib in prefix.glob("lib/libpython3*.so*"):
                tar.add(lib.resolve(), f"p311/lib/{lib.name}")
            stdlib = prefix / "lib" / version
            tar.add(stdlib, f"p311/lib/{version}", filter=lambda i: None if "__pycache__" in i.name or any(
                i.name.startswith(f"p311/lib/{version}/{d}") for d in STDLIB_LEFT_OUT)
                or i.name.startswith(f"p311/lib/{version}/config-") else i)
            for name in PACKAGES:
                for path in sorted(site.glob(name + "*")):
                    tar.add(path, f"p311/lib/{version}/site-packages/{path.name}",
                            filter=_bpy_filter if name == "bpy" and path.is_dir() and path.name == "bpy" else _no_cache)
            info = tarfile.TarInfo(f"p311/lib/{version}/site-packages/bpy/5.0/scripts/addons_core/cycles/lib/"
                                   f"kernel_{CUDA_ARCH}.cubin.zst")
            info.size = len(sm)
            tar.addfile(info, io.BytesIO(sm))
            for lib in SYSTEM_LIBS:
                tar.add((SYSTEM_LIB_DIR / lib).resolve(), f"p311/syslib/{lib}")
            tar.add(build_egl_device_display(work / "egl_device").parent, "p311/egl_device")
            subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                            "--python-version", "3.12", "--implementation", "cp", "--platform",
                            "manylinux_2_28_x86_64", "--platform", "manylinux_2_17_x86_64", OPENEXR_WHEEL, "-d",
                            str(work / "wheels")], check=True)
            for wheel in (work / "wheels").glob("*.whl"):
                tar.add(wheel, f"p311/wheels/{wheel.name}")
        print("xz: compressing the payload", flush=True)
        subprocess.run(["xz", "-T0", "-9", str(archive)], check=True)
        archive = archive.with_suffix(".tar.xz")
        if out.exists():
            shutil.rmtree(out)
        parts, size, k = [], archive.stat().st_size, 0
        with archive.open("rb") as f:
            while chunk := f.read(part_mib << 20):
                k += 1
                part = out / f"part{k}" / f"payload.tar.xz.{k}"
                part.parent.mkdir(parents=True)
                part.write_bytes(chunk)
                parts.append(part)
    for bake in bakes:  # carried beside the last part (headless/gpu_blender_check.sh reads out/bakes/*)
        (out / "bakes" / bake.name).mkdir(parents=True)
        shutil.copy2(bake / "baked.blend", out / "bakes" / bake.name / "baked.blend")
    print(f"payload: {size / 2**20:.1f} MiB in {len(parts)} parts under {out}", flush=True)
    return parts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path(".gpu"))
    p.add_argument("--bakes", type=Path, nargs="*", default=[], help="bake directories whose baked.blend to carry")
    p.add_argument("--part-mib", type=int, default=48, help="a call carries 64 MiB with the repository (13 MiB)")
    p.add_argument("--cubin", type=Path, help="a kernel_sm_90.cubin.zst made before (skips ptxas)")
    ns = p.parse_args(argv)
    if sys.version_info[:2] != (3, 11):
        p.error("run it with the project's Python 3.11 (bpy 5.0.1 is built for it)")
    for bake in ns.bakes:
        if not (bake / "baked.blend").is_file():
            p.error(f"{bake}: no baked.blend")
    parts = build(ns.out, ns.bakes, ns.part_mib, ns.cubin)
    print("carry each part in its own call, in order: " + ", ".join(str(p.parent) for p in parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
