# The README's two commands (`make dataset`, `make test`) set everything up on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
PIPELINE ?= pipelines/default.yaml
OUT ?= data
# Test workers (pytest-xdist): the tests are single-threaded, so one per core nearly halves the
# suite on 2 cores. Tests go to whichever worker is free (load). Until 2026-12-04 whole files
# did (loadfile), so that a file's tests shared the Taichi kernel variants they compile (20-30 s
# each for the body-collision frame kernel then; a worker cannot load what the other compiled
# until it exits, when Taichi writes its offline cache). Since Taichi's CFG pass is off those
# compile in 2-5 s (docs/simulator.md, "Compile time"), and balancing by test pays more: with no
# kernels cached, one after the other on an AMD EPYC (2026-12-04), 10.3 min by test against
# 11.4 by file (on 2026-11-30, with the slow compiles, 21.9 by test against 19.7 by file).
TEST_WORKERS ?= auto

.PHONY: install dataset test lint bench bench-quick clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch 2.13.0 first: its CPU build is on disk; a bare `torch` would pull GBs of CUDA packages.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	# Anny's first instantiation builds its data cache (1-3 min): once here, so that the first
	# dataset run and the test suite's workers do not wait for it.
	$(PY) -c "from datagen.body.anny_model import default_body_model; default_body_model()"
	touch $(STAMP)

install: $(STAMP)

dataset: install
	$(VENV)/bin/datagen dataset --pipeline $(PIPELINE) --out $(OUT)
	# Strict: the recipe rejects (and lists in the card) a sequence over a QA bound, so what is
	# written must pass every check, QA bounds included.
	$(VENV)/bin/datagen validate $(OUT)

lint: install
	$(VENV)/bin/ruff check datagen models tests benchmarks templates

test: lint
	$(VENV)/bin/pytest -q -n $(TEST_WORKERS) --dist load

bench: install
	$(PY) -m benchmarks.run_all

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
