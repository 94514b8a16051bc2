# Two commands on a fresh machine (see README.md):
#   make demo   set up, then run the demo swarm on the embedded procedural scene
#   make test   set up, then run the test suite (what .ci/run runs)
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test setup clean browser

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

test: $(STAMP) browser
	$(PY) -m pytest -q

# The viewer's test drives Debian's Chromium (playwright downloads no browser). Installed here when
# we may (root with apt-get); otherwise that one test is skipped and says why.
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || \
	  echo "note: no chromium (apt-get install -y chromium): the viewer's browser test will be skipped"; }

clean:
	rm -rf $(VENV) runs .pytest_cache
