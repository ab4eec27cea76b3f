#!/usr/bin/env bash
# What needs Blender on a lent GPU machine, in one call (docs/design-additions.md §49), from the repository root:
#   1. unpacks the parts headless/gpu_payload.py made (Python 3.11, bpy, Cycles' sm_90 kernels) from PARTS;
#   2. checks that EEVEE renders, on EGL's default display or else on the first EGL device (its frame times are
#      skipped where it renders on neither);
#   3. Production bakes of room and courtyard on OptiX (--device cuda), end to end with the evaluation (Cycles' only
#      where EEVEE does not render), training on CUDA in the machine's Python 3.12 with torch for TRAINING_BUDGET_S
#      seconds, side by side on six cores each;
#   4. beside them on four cores, EEVEE's frame time at 1920x1080 of the carried bakes (BAKES/*/baked.blend): with
#      the bake, its evaluator muted and without it (headless/eevee_frame_time.py).
# Everything shares one GPU: stage and frame times are upper bounds.
# Starts nothing new after DEADLINE_S seconds and cuts what runs then; results go to OUT (JSON, logs).
set -u
OUT=${OUT:-gpu_out}
PARTS=${PARTS:-/opt/sglf/parts}
BAKES=${BAKES:-.gpu/bakes}
DEADLINE_S=${DEADLINE_S:-500}
TRAINING_BUDGET_S=${TRAINING_BUDGET_S:-20}
ROOT=${ROOT:-/opt/sglf}
P=$ROOT/p311
START=$(date +%s)
mkdir -p "$OUT" "$OUT/logs" $ROOT
FRAME_ARGS=${FRAME_ARGS:---samples 1,33 --repeats 2}  # "--resolution 64x36 ...": a try without a GPU
left() { echo $(( DEADLINE_S - ($(date +%s) - START) )); }
stamp() { echo "[$(( $(date +%s) - START )) s] $*"; }
on_cores() { if taskset -c "$1" true 2>/dev/null; then taskset -c "$@"; else shift; "$@"; fi; }  # where it can
unxz() { if command -v xz >/dev/null; then xz -dc -T0; else
  python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer)"; fi; }

if [ ! -x $P/bin/python3.11 ]; then
  stamp "unpacking $(ls "$PARTS" | wc -l) parts"
  ls "$PARTS"/payload.tar.xz.* | sort -t. -k4 -n | xargs cat | unxz | tar x -C $ROOT || exit 1
fi
export LD_LIBRARY_PATH=$P/lib:$P/syslib:/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
for j in /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json /usr/share/glvnd/egl_vendor.d/10_nvidia.json; do
  if [ -f $j ]; then export __EGL_VENDOR_LIBRARY_FILENAMES=$j; break; fi
done
# OpenEXR for the machine's Python, which trains; Python 3.11 skips its cp312 module and keeps its own
python3 -m pip install -q --no-index --no-deps --no-compile --target $ROOT/py312 $P/wheels/*.whl \
  >"$OUT/logs/pip.log" 2>&1
export PYTHONPATH=$ROOT/py312 SGLF_TORCH_PYTHON=$(command -v python3) PYTHONUNBUFFERED=1
PY=$P/bin/python3.11
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; $PY --version;
  python3 -c "import torch, OpenEXR; print('torch', torch.__version__, torch.cuda.is_available())"; } \
  >"$OUT/logs/machine.txt" 2>&1
stamp "machine: $(tr '\n' ' ' <"$OUT/logs/machine.txt")"

production() {  # scene, cores
  on_cores "$2" timeout "$(left)" $PY headless/bake.py --scene demo:$1 --preset production --device cuda \
    --training-budget "$TRAINING_BUDGET_S" $([ -n "$EEVEE_OK" ] || echo --no-eevee-evaluation) \
    --out /tmp/production_$1 >"$OUT/logs/production_$1.log" 2>&1
  stamp "Production $1 rc $?"
  cp /tmp/production_$1/report.json "$OUT/production_$1.json" 2>/dev/null
}
# EEVEE needs a GPU context (bpy's headless EGL one on the default display): a tiny measurement first, then the same
# with EGL's default display made the first EGL device's (headless/egl_device_display.c); a machine where neither
# renders is named in seconds and its bakes evaluate with Cycles only
probe() {  # log name
  SGLF_EGL_DEVICE_LOG=1 timeout -s ABRT 60 $PY -X faulthandler headless/eevee_frame_time.py "$BAKES/spheres" \
    --resolution 64x36 --samples 1,2 --repeats 1 >"$OUT/logs/eevee_probe_$1.log" 2>&1
}
EEVEE_OK=""
if probe default_display; then
  EEVEE_OK=default_display
elif [ -f $P/egl_device/libEGL.so.1 ] && LD_LIBRARY_PATH=$P/egl_device:$LD_LIBRARY_PATH probe egl_device; then
  EEVEE_OK=egl_device
  export LD_LIBRARY_PATH=$P/egl_device:$LD_LIBRARY_PATH
fi
stamp "EEVEE probe: $([ -n "$EEVEE_OK" ] && echo "renders ($EEVEE_OK)" || echo 'no render (logs/eevee_probe_*.log)')"

stamp "Production room and courtyard on OptiX (cores 4-9, 10-15), training $TRAINING_BUDGET_S s on CUDA"
production room 4-9 &
production courtyard 10-15 &
if [ -n "$EEVEE_OK" ]; then
  stamp "EEVEE frame times on cores 0-3, beside the Production bakes"
  on_cores 0-3 timeout "$(( $(left) - 60 ))" $PY headless/eevee_frame_time.py "$BAKES"/* $FRAME_ARGS \
    --report "$OUT/frame_time.json" >"$OUT/logs/frame_time.log" 2>&1
  stamp "frame times rc $?: $(grep -c ' frame ' "$OUT/logs/frame_time.log") set-ups measured"
fi
wait
tar czf "$OUT/logs.tar.gz" -C "$OUT" logs && rm -rf "$OUT/logs"
stamp "done"
