# Two commands for a newcomer: `make demo` and `make test`. Both create .venv and install pinned deps.
PYTHON_BOOTSTRAP ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cksum requirements.txt | cut -d' ' -f1)
DEMO_OUT ?= bake_out/spheres

.PHONY: demo test test-fast bench check-math extension clean

$(STAMP): requirements.txt
	$(PYTHON_BOOTSTRAP) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

# Until every bake stage lands, the demo runs the stages that exist on demo:spheres (plan, capture,
# render, train), the SG math check and the extension build.
demo: $(STAMP)
	$(PY) -m shaders.check_math --quick
	$(PY) headless/bake.py --scene demo:spheres --preset draft --out $(DEMO_OUT) --stages capture,render,train --midpoints 128
	$(PY) -m headless.build_extension --out dist

test: $(STAMP)
	$(PY) -m pytest -q

test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

check-math: $(STAMP)
	$(PY) -m shaders.check_math

bench: $(STAMP)
	$(PY) -m headless.bench

extension: $(STAMP)
	$(PY) -m headless.build_extension --out dist

clean:
	rm -rf $(VENV) dist .pytest_cache .hypothesis
