# Two commands for a fresh Debian machine with python3 and make (README.md):
#   make run   -- create .venv, execute every notebook against the virtual leg -> reports/
#   make test  -- same venv, run the whole test suite (notebook execution included)

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
export PYDEVD_DISABLE_FILE_VALIDATION := 1
# Notebook kernels always draw with matplotlib's inline backend (leglib.notebooks.execute sets
# it for them), so reports carry their figures. Only the test and benchmark processes
# themselves are headless (Agg); no MPLBACKEND is exported to kernels from here.
HEADLESS := MPLBACKEND=Agg
# JupyterLab refuses to start as root without --allow-root
LAB_ROOT := $(shell [ "$$(id -u)" = 0 ] && echo --allow-root)

.PHONY: run test venv sysdeps bench robustness clean lab lint hooks

venv: $(STAMP)

$(STAMP): environment.txt pyproject.toml
	@$(MAKE) --no-print-directory sysdeps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r environment.txt
	@# setuptools prints a ten-line notice on every editable install (a folder in the working
	@# directory named like the package may shadow it: here that folder is the package itself);
	@# its output is shown in full only when the install fails
	@out=$$($(BIN)/python -m pip install --quiet --no-deps -e . 2>&1) || { echo "$$out"; exit 1; }; \
	  echo "leglib installed editable from $$(pwd) (setuptools' notice about a folder named like the package is about leglib/ itself)"
	@# leglib's bytecode written now, as pip writes an installed package's (an editable install
	@# writes none, and an environment with PYTHONDONTWRITEBYTECODE never does): each process
	@# that imports leglib (a notebook kernel, a test worker) loads it instead of compiling
	@# 28,000 lines (0.37 CPU-s of a kernel's 2.2 s of imports)
	$(BIN)/python -m compileall -q leglib
	@# the numba kernels compiled now, with a line per group, not silently at their first use
	$(BIN)/python -m leglib compile
	touch $(STAMP)

# System packages, installed with apt-get when missing and we are root (otherwise a warning):
#   libusb-1.0-0  -- the odrive package's native part (only the usb backend needs it)
#   chromium      -- the browser test of the notebooks' widgets (tests/test_browser.py)
sysdeps:
	@missing=""; \
	ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so' || missing="$$missing libusb-1.0-0"; \
	command -v chromium >/dev/null || [ -x /usr/bin/chromium ] || missing="$$missing chromium"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing$$missing (apt-get)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$$missing >/dev/null; \
	  else echo "warning: missing system packages:$$missing (apt-get install$$missing);" \
	    "the usb backend needs libusb, the browser test chromium"; fi; \
	fi

run: $(STAMP)
	$(BIN)/python -m leglib run --out reports

# pytest-xdist workers (JOBS=1: one process, as plain `pytest`); the browser tests share one
# JupyterLab and stay on one worker (xdist_group "lab")
JOBS ?= auto
test: $(STAMP)
	@$(MAKE) --no-print-directory sysdeps
	$(HEADLESS) $(BIN)/python -m pytest -q -n $(JOBS) --dist loadgroup

bench: $(STAMP)
	$(HEADLESS) $(BIN)/python -m benchmarks

# every method on every twin plant (a few minutes) -> reports/robustness/
robustness: $(STAMP)
	$(HEADLESS) $(BIN)/python -m leglib robustness --out reports/robustness

lab: $(STAMP) hooks
	$(BIN)/jupyter lab notebooks/ $(LAB_ROOT)

lint: $(STAMP)
	$(BIN)/ruff check leglib tests benchmarks

# in a git checkout: the commit hooks (.pre-commit-config.yaml) and a clean filter that strips
# notebook outputs on `git add` (JupyterLab autosaves outputs into notebooks/)
hooks: $(STAMP)
	@if [ -d .git ]; then \
	  $(BIN)/pre-commit install --install-hooks >/dev/null && \
	  git config filter.nbstripout.clean "$(abspath $(BIN))/nbstripout --keep-id -t" && \
	  git config filter.nbstripout.smudge cat && \
	  git config filter.nbstripout.required true && \
	  echo "hooks installed: ruff and nbstripout on commit, outputs stripped on git add"; fi

clean:
	rm -rf $(VENV) reports/*.ipynb reports/*.html reports/figures reports/metrics
