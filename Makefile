# The two entry points of the README. Both create ./.venv and install into it first.
PY ?= python3.11
VENV := .venv
SHARED ?= ../shared

$(VENV)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e '.[dev]'
	$(VENV)/bin/python -c 'from cmc.kernel_cache import warm_up_kernels; warm_up_kernels()'  # compiled once, here
	touch $@

install: $(VENV)/.installed

demo: install  ## reconstruct a synthetic scene from 3 views on the CPU; outputs in demo-output/
	$(VENV)/bin/cmc demo --out demo-output

chromium:  ## Debian's chromium for the viewer tests (apt-get, as root); without it they skip, except under CI
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } || \
		echo "chromium is not installed: the viewer tests will be skipped"

jq:  ## jq for the README walk-through test (apt-get, as root); without it that test skips, except under CI
	@command -v jq >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq jq >/dev/null; } || \
		echo "jq is not installed: the README walk-through test will be skipped"

test: install chromium jq  ## the whole test suite (what CI runs)
	$(VENV)/bin/ruff check cmc service worker tests bench
	$(VENV)/bin/ruff format --check .
	CMC_SHARED_DIR=$(SHARED) $(VENV)/bin/python -m pytest -q

bench-fern: install  ## LLFF fern, fast preset, CPU (about 5 minutes): bench/reports/current/bench_fern.md, to compare with bench/RESULTS.md
	CMC_LPIPS_DIR=$(SHARED)/weights $(VENV)/bin/cmc bench llff --data $(SHARED)/datasets/llff \
		--scenes fern --preset fast --out bench/reports/current/bench_fern.json --save-dir bench/runs
	cat bench/reports/current/bench_fern.md

deployment-test: install  ## build the images, start docker-compose.yml, run every job and fault check (bench/deployment_test.py; 11 min on 2 cores, Docker needed)
	$(VENV)/bin/python bench/deployment_test.py $(if $(wildcard $(SHARED)/tools/offline-docker),--offline-docker $(SHARED)/tools/offline-docker)

.PHONY: install chromium jq demo test bench-fern deployment-test
