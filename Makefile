# Two commands on a fresh machine (see README.md):
#   make demo   set up, then run the demo swarm on the embedded procedural scene
#   make test   set up, then run the test suite (what .ci/run runs)
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test setup clean

setup: $(STAMP)

# torch first, pinned: here `pip install torch==2.13.0` takes the local CPU build; a range
# would pull the newest CUDA wheels. The package then accepts the torch already installed.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/dinerf-agent scenario run quickstart --out runs/quickstart --force

test: $(STAMP)
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) runs .pytest_cache
