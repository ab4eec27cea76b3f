# Two commands for a newcomer: `make demo` and `make test`. Both create .venv and install pinned deps.
PYTHON_BOOTSTRAP ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cat requirements.txt requirements-extension.txt | cksum | cut -d' ' -f1)
DEMO_OUT ?= bake_out/spheres
HAIR_DATA ?= hair_data
# one test file per core, the longest first (tests/conftest.py LONGEST_FIRST)
PYTEST_PARALLEL := -n auto --dist loadfile --no-loadscope-reorder

.PHONY: demo test test-fast browser egl-build blender-lts bench check-math farm-demo gpu-check gpu-payload extension hair-model clean

$(STAMP): requirements.txt requirements-extension.txt
	$(PYTHON_BOOTSTRAP) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m headless.build_extension --download-wheels $(VENV)/wheels
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

# The main job on the embedded demo scene: the whole bake of demo:spheres at the Draft preset
# (capture, render, train, apply, evaluate), then the extension build. Prints where the report and the
# baked .blend are.
demo: $(STAMP)
	$(PY) -m shaders.check_math --quick
	$(PY) headless/bake.py --scene demo:spheres --preset draft --out $(DEMO_OUT) --midpoints 128
	$(PY) -m headless.build_extension --out dist
	@echo "report: $(DEMO_OUT)/report.html   baked scene: $(DEMO_OUT)/baked.blend"

# Debian packages $(1), installed as root or with sudo; the package lists are updated only if the first try fails.
apt_install = SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get install -y --no-install-recommends $(1) >/dev/null 2>&1 || \
	  { $$SUDO apt-get update -qq && $$SUDO apt-get install -y --no-install-recommends $(1); }

# The report test opens report.html in Debian's chromium through chromedriver: installed here when missing.
browser:
	@command -v chromium >/dev/null && command -v chromedriver >/dev/null || { \
	  $(call apt_install,chromium chromium-driver); }

# The EGL stand-in's test (tests/test_gpu_check.py) compiles headless/egl_device_display.c: gcc and EGL's headers,
# installed here when missing.
egl-build:
	@command -v gcc >/dev/null && test -f /usr/include/EGL/eglext.h || { \
	  $(call apt_install,gcc libc6-dev libegl-dev); }

# The Blender LTS releases as modules for tests/test_blender_versions.py (bpy from PyPI), made once before the suite.
BLENDER_LTS := 4.5.15 4.2.23
blender-lts: $(STAMP)
	@$(PY) tests/blender_environments.py $(BLENDER_LTS) >/dev/null

test: $(STAMP) browser egl-build blender-lts
	$(PY) -m pytest -q $(PYTEST_PARALLEL)

test-fast: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_PARALLEL) -m "not slow"

check-math: $(STAMP)
	$(PY) -m shaders.check_math

bench: $(STAMP)
	$(PY) -m pip install --quiet -r requirements-bench.txt
	$(PY) -m headless.bench

# Reproduces models/hair_*.onnx: 270 pairs (66 min on 2 cores, measured), then Base with the input blend and the
# FLIP term at 4 spp (30 min), Large (twice the channels, 55 min) and Base at 2 and 1 spp (6 min each). Step
# budgets: the steps the shipped Base models made in 1800 s and 360 s on this 2-core CPU, so a faster or busier
# machine trains the same amount. Resumable: rerun continues the dataset where it stopped. Blender's hair generator
# does not give the same strands twice, so a rerun reproduces the dataset's statistics, not its pixels.
hair-model: $(STAMP)
	$(PY) headless/hair_dataset.py --out $(HAIR_DATA)
	$(PY) -m hair.train --data $(HAIR_DATA)/train --config base+blend --flip-weight 0.3 --steps 21000 --out models/hair_base.onnx
	$(PY) -m hair.train --data $(HAIR_DATA)/train --config large+blend --flip-weight 0.3 --steps 21000 --out models/hair_large.onnx
	$(PY) -m hair.train --data $(HAIR_DATA)/train --config base+blend@2spp --flip-weight 0.3 --steps 4044 --out models/hair_base@2spp.onnx
	$(PY) -m hair.train --data $(HAIR_DATA)/train --config base+blend@1spp --flip-weight 0.3 --steps 5057 --out models/hair_base@1spp.onnx

# The farm template run locally (docs/farms.md): one process per task, demo:spheres at Draft, 3 render tasks.
FARM_OUT ?= bake_out/farm
farm-demo: $(STAMP)
	$(VENV)/bin/openjd run farm/openjd/sg_lightfield_bake.yaml -p BlendFile=demo:spheres -p OutputDir=$(abspath $(FARM_OUT)) \
	  -p Preset=draft -p TileCount=3 -p Python=$(abspath $(PY)) -p Repository=$(CURDIR)
	@echo "report: $(FARM_OUT)/report.html   baked scene: $(FARM_OUT)/baked.blend"

# The GPU path's measurements (headless/gpu_check.py, docs/design-additions.md §37): room's Draft light fields
# rendered here once and exported to numpy, then training, a Production-sized epoch and the refits on the CPU and on
# CUDA when torch sees one. On a lent GPU machine: carry $(GPU_CHECK)/room_draft.npz and headless/, training/,
# shaders/, bake_directory/ and sg_launch.py, then `python headless/gpu_check.py --data .../room_draft.npz` there.
GPU_CHECK ?= bake_out/gpu_check
gpu-check: $(STAMP)
	test -f $(GPU_CHECK)/room_draft.npz || { \
	  $(PY) headless/bake.py --scene demo:room --preset draft --out $(GPU_CHECK)/room --stages capture,render && \
	  $(PY) headless/gpu_check.py --export $(GPU_CHECK)/room --out $(GPU_CHECK)/room_draft.npz; }
	$(PY) headless/gpu_check.py --data $(GPU_CHECK)/room_draft.npz --report $(GPU_CHECK)/report.json

# What needs Blender on a lent GPU machine (headless/gpu_blender_check.sh, docs/design-additions.md §49): Draft bakes
# of the demo scenes here, and Python 3.11 with bpy, Cycles' sm_90 kernels (ptxas, about 8 min on 2 cores) and the
# bakes' .blend files packed in .gpu/partK (48 MiB each: a call carries 64 MiB with the repository). Carry each part
# in its own call, copying it to /opt/sglf/parts, then run `bash headless/gpu_blender_check.sh` with the last one.
GPU_BAKES ?= bake_out/gpu_bakes
gpu-payload: $(STAMP)
	for s in spheres room courtyard materials; do test -f $(GPU_BAKES)/$$s/baked.blend || \
	  $(PY) headless/bake.py --scene demo:$$s --preset draft --out $(GPU_BAKES)/$$s --stages capture,render,train,apply \
	  || exit 1; done
	$(PY) -m headless.gpu_payload --out .gpu --bakes $(foreach s,spheres room courtyard materials,$(GPU_BAKES)/$(s))

extension: $(STAMP)
	$(PY) -m headless.build_extension --out dist

clean:
	rm -rf $(VENV) .venv-blender dist .pytest_cache .hypothesis
