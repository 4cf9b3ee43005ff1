# ringscan: two commands do all the set-up on a fresh machine.
#   make demo   - system libraries, a virtual environment, then the main job on the
#                 embedded default (simulate a turntable scan with the virtual rig,
#                 reconstruct, fuse, mesh, write a preview PNG) into out/demo
#   make test   - the same set-up, then the test suite (what CI runs)
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
STAMP   = $(VENV)/.installed

.PHONY: demo test bench setup sysdeps clean

demo: setup
	$(BIN)/ringscan demo --out out/demo

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/ringscan bench

setup: sysdeps $(STAMP)

sysdeps:
	@bash tools/install_system_deps.sh

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

clean:
	rm -rf $(VENV) out build *.egg-info
