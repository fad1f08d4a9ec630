# divmorph: `make demo` runs the main job, `make test` runs the test suite.
# Both create (or refresh, when pyproject.toml or setup.py changes) the virtual environment in .venv.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Headless rendering, and the text encoder from its local copy (no network needed).
export MUJOCO_GL ?= egl
export HF_HUB_OFFLINE ?= 1
export TRANSFORMERS_OFFLINE ?= 1

.PHONY: demo tour test test-results lint install benchmarks clean

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch is pinned first: an unpinned torch would pull several GB of CUDA wheels.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet torch==2.13.0 -e ".[dev,zoo,ray,warp]"
	touch $(STAMP)

install: $(STAMP)

# The main job: the knowledge-diversion pipeline at its tiny "demo" budget (4 min 2 s on 2 idle
# cores from a fresh clone with an empty HOME, after the install; 2026-12-05).
demo: $(STAMP)
	$(VENV)/bin/divmorph pipeline --profile demo --out runs/demo

# A tour of the environments: scripted gaits on several robots, a table, a video and a picture
# (under a minute).
tour: $(STAMP)
	$(PY) -m unimal_envs.demo --out runs/tour

# The library's suite (after lint and types), one pytest worker per core, each test file on one worker (its
# module fixtures built once), on data it makes: 564 tests from a fresh clone with an empty HOME and robot
# cache (`.ci/run`, 2026-12-06) in 18 min 31 s of pytest with two training runs sharing the 2 cores (the
# suite with the evidence's tests: 6 min 57 s on 2 idle cores the day before); the batched backend's tests
# compile MuJoCo Warp's kernels on a machine's first run (~2 min more, then cached in ~/.cache/warp).
test: lint
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not shipped_results"

# The tests of the shipped runs under results/ (their models load and walk, their tables quote their
# data, the wheel fetches them): apart from the library's suite, which brings its own data.
test-results: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m shipped_results

# Lint and types (part of `make test`): ruff's rules and formatting over the repository, mypy over the packages
# (both configured in pyproject.toml; mypy's list of modules not yet typed only ever shrinks). About 20 s.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

benchmarks: $(STAMP)
	$(PY) benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) runs .pytest_cache
