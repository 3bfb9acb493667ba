# Two set-up commands: `make demo` and `make test`. Each creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test interop browser-check lint bench bench-demo bench-ucdavis bench-suite bench-truth clean venv lock

venv: $(STAMP)

# every dependency at the exact version and hash of requirements.lock (`make lock` refreshes
# it from pyproject.toml's ranges and constraints.txt's torch pin), then the package itself
$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --require-hashes -r requirements.lock
	$(PY) -m pip install --no-deps -e .
	touch $(STAMP)

LOCK_FLAGS := --quiet --generate-hashes --allow-unsafe --no-emit-index-url --no-emit-find-links \
	--strip-extras --extra dev --extra fast --extra peer -c constraints.txt

lock:
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install pip-tools
	$(VENV)/bin/pip-compile $(LOCK_FLAGS) --upgrade -o requirements.lock pyproject.toml

demo: $(STAMP)
	$(VENV)/bin/biopsynav demo

# two workers (pytest-xdist), one test file each at a time, the longest files first
# (tests/conftest.py): CI's machine has 2 cores. A worker that dies ends the run at once
# (--max-worker-restart 0): pytest-xdist 3.8 replacing it under --dist loadfile can wait forever
# (pytest-xdist issues 784, 1323)
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --max-worker-restart 0

# `biopsynav serve` against the OpenIGTLink C++ library (tests/interop): installs Debian's
# libopenigtlink-dev, cmake and g++ when missing.
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
IGTL_CMAKE := /usr/lib/openigtlink/OpenIGTLinkConfig.cmake

interop: $(STAMP)
	@test -f $(IGTL_CMAKE) && command -v cmake >/dev/null && command -v g++ >/dev/null || \
		$(SUDO) apt-get install -y libopenigtlink-dev cmake g++ || \
		($(SUDO) apt-get update && $(SUDO) apt-get install -y libopenigtlink-dev cmake g++)
	BIOPSYNAV_INTEROP=1 $(PY) -m pytest -q -m interop tests/interop

# report.html in headless Chromium (tests/report/test_report_browser.py): installs Debian's
# chromium when missing.
browser-check: $(STAMP)
	@command -v chromium >/dev/null || $(SUDO) apt-get install -y chromium || \
		($(SUDO) apt-get update && $(SUDO) apt-get install -y chromium)
	BIOPSYNAV_BROWSER=1 $(PY) -m pytest -q -m browser tests/report

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

# the benchmarks of BENCHMARKS.md, each writing its result file under benchmarks/results/;
# then `python benchmarks/figures.py --write` renders README's and BENCHMARKS.md's tables.
# Run them alone: two jobs on 2 cores slow each other down several times.
BENCH_DIR ?= /tmp/biopsynav-bench
bench: $(STAMP)
	$(PY) benchmarks/fem_solve.py
	$(PY) benchmarks/generate.py
	$(PY) benchmarks/bf16_cpu.py
	$(PY) benchmarks/error_bound.py

bench-demo: $(STAMP)
	rm -rf $(BENCH_DIR)/phantom
	$(PY) benchmarks/time_to_model.py --case phantom --workdir $(BENCH_DIR) --keep
	$(PY) benchmarks/train_and_predict.py $(BENCH_DIR)/phantom --no-train
	$(PY) benchmarks/tracking_latency.py $(BENCH_DIR)/phantom

bench-ucdavis: $(STAMP)
	rm -rf $(BENCH_DIR)/ucdavis
	$(PY) benchmarks/time_to_model.py --case ucdavis --workdir $(BENCH_DIR) --keep

bench-suite: $(STAMP)
	$(PY) benchmarks/suite_time.py

bench-truth: $(STAMP)
	$(PY) benchmarks/truth.py $(CASE) --lesions 0

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
