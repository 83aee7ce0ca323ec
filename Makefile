# Two entry points, both self-contained on a fresh machine with Python 3.11:
#   make demo   set up .venv and run the main job on the embedded simulated site
#   make test   set up .venv and run the whole test suite
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
STAMP := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)

.PHONY: setup demo test bench clean

$(STAMP): pyproject.toml
	rm -f $(VENV)/.installed-*
	$(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q -e '.[all]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cristal demo --out runs/demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

clean:
	rm -rf $(VENV) runs .pytest_cache
