# Two set-up commands: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test docs bench gpu-check clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/cantilever.py --device cpu --num-frames 48 --stage-path out/cantilever.usda --headless
	@echo "warpfem is installed in .venv: run 'source .venv/bin/activate' for the warpfem command (or call .venv/bin/warpfem)"

test: $(STAMP)
	$(PY) -m pytest -q tests

# The documentation site (docs/*.md + API reference from the docstrings) into out/site; `make test`
# builds it too (tests/test_docs.py, warnings are errors). `.venv/bin/mkdocs serve` to browse.
docs: $(STAMP)
	$(PY) -m mkdocs build --strict

# Whole benchmark suite -> kernels_bench/results/summary.{json,md}. QUICK=1: small sizes; SKIP=stability
# (comma-separated names) to leave benchmarks out; DEVICE=cuda:0. The newton peer comparison runs when
# `pip install -e ".[peer]"` was done, and is skipped otherwise.
bench: $(STAMP)
	$(PY) kernels_bench/run_all.py --device $(or $(DEVICE),cpu) $(if $(QUICK),--quick,) $(if $(SKIP),--skip $(SKIP),)

# On a machine with a CUDA GPU, in at most 8 minutes: the device test subset (tests/device_subset.txt)
# on cuda:0 and the force/assembly, step-pipeline, scale and peer benchmarks, JSON into
# kernels_bench/results/cuda/ (docs/design.md, "Devices"). Without a GPU: one line, nothing run.
gpu-check: $(STAMP)
	$(PY) kernels_bench/gpu_check.py

clean:
	rm -rf $(VENV) out .pytest_cache
