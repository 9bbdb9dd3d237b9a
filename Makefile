# Two set-up commands: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/cantilever.py --device cpu --num-frames 48 --stage-path out/cantilever.usda --headless

test: $(STAMP)
	$(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) kernels_bench/bench_forces.py --device cpu

clean:
	rm -rf $(VENV) out .pytest_cache
