# ringscan: two commands do all the set-up on a fresh machine.
#   make demo   - system libraries, a virtual environment, then the main job on the
#                 embedded default (simulate a turntable scan with the virtual rig,
#                 reconstruct, fuse, mesh, write a preview PNG) into out/demo
#   make test   - the same set-up, then the test suite (what CI runs)
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
STAMP   = $(VENV)/.installed
# Test processes (pytest-xdist; each file stays on one process). Three on a 2-core machine: many
# tests wait on child processes (workers, Ray, emulated devices, the renderer), and a third process
# fills that idle time (the suite: 255 s against 285 s with two, same machine and commit). Each
# holds Warp, Open3D and a scan in memory (~1.5 GB): on an 8 GB machine use TEST_WORKERS=2.
TEST_WORKERS ?= 3

.PHONY: demo test docs-check bench setup sysdeps clean FORCE

demo: setup
	$(BIN)/ringscan demo --out out/demo

# PYTHONDONTWRITEBYTECODE emptied for the suite: with it set (as on some machines) every test process
# rewrote and compiled every test module afresh (~6 s a process).
test: setup
	$(BIN)/lint-imports
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# Every command block of README.md and docs/ run as written (benchmarks/run_doc_blocks.py: the slow
# ones the suite only parses and checks, ~60 min on a 2-core machine; see docs/index.md).
docs-check: setup
	$(BIN)/python benchmarks/run_doc_blocks.py

bench: setup
	$(BIN)/ringscan bench

setup: sysdeps $(STAMP)

sysdeps:
	@bash tools/install_system_deps.sh

# A strict editable install (import-linter sees the sub-packages only in one) links
# each module file: a module added or removed needs a reinstall, so the stamp also
# depends on the list of module files (rewritten only when it changes).
MODULES := $(sort $(wildcard src/ringscan/*.py kernels/*.py pipeline/*.py pipeline/*/*.py pipeline/*/*/*.py hardware/*.py hardware/*/*.py tools/*.py tools/*/*.py))

$(VENV)/.modules: FORCE
	@mkdir -p $(VENV)
	@echo '$(MODULES)' | cmp -s - $@ || echo '$(MODULES)' > $@

$(STAMP): pyproject.toml $(VENV)/.modules
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]' --config-settings editable_mode=strict
	@touch $(STAMP)

clean:
	rm -rf $(VENV) out build *.egg-info
