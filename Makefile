# Two set-up commands: `make demo` and `make test`. Each creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip >/dev/null
	$(PY) -m pip install -c constraints.txt -e '.[dev,fast]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/biopsynav demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

bench: $(STAMP)
	$(PY) benchmarks/fem_solve.py
	$(PY) benchmarks/generate.py
	$(PY) benchmarks/train_and_predict.py
	$(PY) benchmarks/tracking_latency.py

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
