# The two entry points of the README. Both create ./.venv and install into it first.
PY ?= python3.11
VENV := .venv
SHARED ?= ../shared

$(VENV)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e '.[dev]'
	touch $@

install: $(VENV)/.installed

demo: install  ## reconstruct a synthetic scene from 3 views on the CPU; outputs in demo-output/
	$(VENV)/bin/cmc demo --out demo-output

test: install  ## the whole test suite (what CI runs)
	$(VENV)/bin/ruff check cmc service worker tests bench
	CMC_SHARED_DIR=$(SHARED) $(VENV)/bin/python -m pytest -q

bench-fern: install  ## LLFF fern, fast preset, CPU (about 5 minutes), then regenerate bench/RESULTS.md
	CMC_LPIPS_DIR=$(SHARED)/weights $(VENV)/bin/cmc bench llff --data $(SHARED)/datasets/llff \
		--scenes fern --preset fast --out bench/fern_fast_cpu.json --save-dir bench/runs
	$(VENV)/bin/python bench/make_results.py

.PHONY: install demo test bench-fern
