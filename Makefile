# The two commands of README.md: `make demo` and `make test`.
# Both set up everything on a fresh Debian machine with Python 3.11:
# the Debian libraries Open3D and off-screen VTK need, a .venv, and the
# project with its Python dependencies (pyproject.toml).

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_DIR ?= demo-study
# The demo's knee: the test phantom's field of view sampled at this spacing (mm), between the test grid (5 mm)
# and the paper's (1.25 mm), so that the render reads as anatomy; `make demo DEMO_SPACING=5` is quicker.
DEMO_SPACING ?= 2.5
# Debian packages Open3D (libusb, libgomp) and off-screen VTK (GL, EGL, OSMesa) load at run time.
DEB_PACKAGES := libusb-1.0-0 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libgomp1
# The test set-up adds headless Chromium: a test opens the HTML report in it and checks its screenshot, and the
# viewer's tests drive it through chromedriver (Selenium); skipped, with the reason, where they cannot be installed.
TEST_DEB_PACKAGES := chromium chromium-driver

# Shell: the packages of $(1) that dpkg does not list as installed, in $$missing.
missing_of = missing=""; for p in $(1); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; done

.PHONY: demo test lint docs test-slow system-deps test-deps venv clean help bench bench-ants

help:
	@echo "make demo       set up, build a phantom knee study in $(DEMO_DIR)/ and run the pipeline on it (bones, pose,"
	@echo "                weights, registrations, an EVD model from them; the truth only validates), deform it to a"
	@echo "                45° bend ($(DEMO_DIR)/bend45.nii.gz), render it ($(DEMO_DIR)/bend45.png) and animate a"
	@echo "                bend-and-straighten ($(DEMO_DIR)/knee.mp4)"
	@echo "make test       set up, then run the gates (make lint), build the docs (make docs) and the test suite"
	@echo "                (slow tests excluded)"
	@echo "make lint       ruff (lint and format) and import-linter's layering contract"
	@echo "make docs       the documentation site (warnings and broken references are errors): open docs/_build/html/index.html"
	@echo "make test-slow  paper-size tests (minutes)"
	@echo "make bench      add the benchmarks' peers to .venv (itk-elastix, psutil)"
	@echo "make bench-ants ANTs SyN for benchmarks/bench_registration.py, in its own .venv-ants (antspyx pins an"
	@echo "                older NumPy/SciPy than the project's)"
	@echo "make clean      remove .venv, .venv-ants and $(DEMO_DIR)/"

system-deps:
	@$(call missing_of,$(DEB_PACKAGES)); \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "Installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	  else \
	    echo "Missing Debian packages:$$missing"; \
	    echo "Install them with:  sudo apt-get install$$missing"; \
	    exit 1; \
	  fi; \
	fi
	@$(PYTHON) -c "import ensurepip, venv" 2>/dev/null || { \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv; \
	  else echo "Python's venv module is missing: sudo apt-get install python3-venv"; exit 1; fi; }

test-deps:
	@$(call missing_of,$(TEST_DEB_PACKAGES)); \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "Installing Debian packages for the tests:$$missing"; \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; } \
	      || echo "Could not install$$missing: the browser tests (HTML report, viewer) will be skipped"; \
	  else \
	    echo "Not installed:$$missing (sudo apt-get install$$missing); the browser tests (HTML report, viewer) will be skipped"; \
	  fi; \
	fi

# Python byte-compiles a module when it first imports it and keeps the result in __pycache__; an environment
# with PYTHONDONTWRITEBYTECODE set (some images and CI runners set it) would compile every module again in every
# process (about 2.5 s of VTK, SciPy, Open3D ... a process, and the demo and the suite start dozens). The venv is
# the project's own, so its recipes write the cache.
unexport PYTHONDONTWRITEBYTECODE

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "$(PYTHON) not found: install Python 3.11 (python3.11, python3.11-venv) or run make PYTHON=/path/to/python3.11"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@# --no-compile: Python byte-compiles a module when it is first imported (above); pip would compile every module
	@# of every package (VTK's, Open3D's, Sphinx's ...), most of which the workbench never imports
	@# (docs/measurements/pipeline-benchmarks.md, "On a quiet machine")
	$(PY) -m pip install --quiet --no-compile -e '.[test,docs]'
	@touch $(STAMP)

venv: system-deps $(STAMP)

demo: venv
	@start=$$(date +%s); set -e; \
	$(VENV)/bin/workbench phantom knee --out $(DEMO_DIR) --spacing $(DEMO_SPACING) --force; \
	$(VENV)/bin/workbench run $(DEMO_DIR) --until model; \
	echo "deform: the model posed to a 45 deg bend, beside the remaining stages (its output follows them)"; \
	$(VENV)/bin/workbench deform $(DEMO_DIR) --pose examples/knee_bend45.json --out $(DEMO_DIR)/bend45.nii.gz --grow \
	  --force > $(DEMO_DIR)/bend45.log 2>&1 & deform=$$!; \
	trap 'kill $$deform 2>/dev/null' EXIT INT TERM; \
	$(VENV)/bin/workbench run $(DEMO_DIR); \
	if ! wait $$deform; then cat $(DEMO_DIR)/bend45.log; echo "workbench deform failed"; exit 1; fi; \
	trap - EXIT INT TERM; \
	cat $(DEMO_DIR)/bend45.log; \
	$(VENV)/bin/workbench render $(DEMO_DIR)/bend45.nii.gz --labels $(DEMO_DIR)/bend45_labels.nii.gz --clip z:0.5 \
	  --zoom 1.15 --out $(DEMO_DIR)/bend45.png --size 960x720 --force; \
	$(VENV)/bin/workbench animate $(DEMO_DIR) --out $(DEMO_DIR)/knee.mp4 --force; \
	echo; echo "outputs in $(DEMO_DIR)/:"; \
	echo "  study.json                  the manifest: every stage's settings, inputs, outputs and timings"; \
	echo "  poses/ skinning/ init/ registration/ model/ validation/   the stages' outputs (3D Slicer, ITK-SNAP, ParaView)"; \
	echo "  bend45.nii.gz, bend45.png   the template posed by EVD to a 45 deg bend, and its render (bones, cut open)"; \
	echo "  knee.mp4                    bend and straighten"; \
	echo "demo took $$(( $$(date +%s) - start )) s"

# The gates: ruff's lint and format, and import-linter's layering (workbench → validation → registration →
# deformation, pyproject.toml); `make lint` runs them alone.
lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports

# The documentation site (docs/), Sphinx with warnings as errors and every cross-reference checked (-n); `make test`
# builds it after the gates.  The generated pages and the built site are made anew each time (a module that moved
# leaves no stale page behind).
docs: venv
	rm -rf docs/api/generated docs/results/generated docs/_build
	$(VENV)/bin/sphinx-build -n -W --keep-going -q -b html docs docs/_build/html
	@echo "docs: open docs/_build/html/index.html"

test: venv test-deps lint docs
	$(VENV)/bin/pytest -n 2 --dist loadfile

test-slow: venv test-deps
	$(VENV)/bin/pytest -n 2 --dist loadfile -m slow

bench: venv
	$(PY) -m pip install --quiet -e '.[test,bench]'

# antspyx needs NumPy < 2.4 and an older SciPy: installed beside the project it would downgrade them, so it
# gets an environment of its own, called by registration.baselines.ants_syn with image files.
bench-ants: bench
	@test -x .venv-ants/bin/python || $(PYTHON) -m venv .venv-ants
	.venv-ants/bin/python -m pip install --quiet antspyx

clean:
	rm -rf $(VENV) .venv-ants $(DEMO_DIR) docs/_build docs/api/generated
