# One-command set-up: `make demo` runs the main job, `make test` runs the suite. Both create .venv first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench setup clean default-model calibrations docs

$(STAMP): pyproject.toml Makefile
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null 2>&1 || echo "warning: could not install libusb-1.0-0 (open3d fusion needs it)"; \
	  else echo "warning: libusb-1.0-0 missing and not root: install it for open3d fusion"; fi; fi
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU wheel of torch is pinned here; the package itself only asks for a range.
	$(PY) -m pip install -q "torch==2.13.0" "zfpy==1.0.1" "numcodecs-wasm-sperr==0.2.3"
	$(PY) -m pip install -q -e ".[fusion,plot,scale,s3,test,view,sz3,sign,fast]"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/sdfcodec demo --out demo-out --overwrite

# two workers (pytest-xdist): most tests are single-threaded Python or wait on subprocesses; about 1.5-2x on 2 cores.
# Bytecode is written even where the environment sets PYTHONDONTWRITEBYTECODE (this project's machines do): the
# suite starts ~300 Python processes (workers, subprocess and CLI tests), each of which otherwise compiled every
# sdfcodec module it imported, and pytest's assertion rewriting is cached only as bytecode. __pycache__ is ignored
# by git. Measured on 4 subprocess-heavy test files: 88-100 s with the variable set, 72 s without.
# --dist loadfile: each test file on one worker, so a file's module fixtures (a study's run, a fused walk, the
# hostile maps) are built once, not once per worker: the whole suite, warm, back to back on the 2-core machine,
# 335 s and 607 CPU-s with the default distribution, 314 s and 557 CPU-s by file.
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -q -n 2 --dist loadfile

# Render the generated pages of docs/ (results, search, rate-distortion, eval, scale, the CLI and API reference)
# from the committed JSON and the code; `make docs` after a re-measurement (tests/test_docs_pages.py checks them).
docs: $(STAMP)
	$(PY) docs/generate/pages.py

# Retrain the shipped eigenshapes (plugins/sdfcodec_pca/models/pca-128.npz) and rewrite docs/default-model.*
default-model: $(STAMP)
	$(PY) examples/train_default_model.py

# Recompute the calibrations shipped for the shipped codecs (sdfcodec/search/shipped-calibrations.json)
calibrations: $(STAMP)
	$(PY) examples/ship_calibrations.py

bench: $(STAMP)
	$(VENV)/bin/sdfcodec bench

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
