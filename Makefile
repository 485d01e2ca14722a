# Two entry points: `make demo` and `make test`. Both create .venv on a fresh
# machine and install with the exact versions of constraints/ci-py311.txt
# (torch 2.13.0, the CPU build on this machine's disk, so no CUDA wheels are
# pulled). pyproject.toml itself only states ranges. `make demo` installs what
# the demo needs (the package with its [recipes] extra: hydra, matplotlib);
# `make test` installs [dev] (every extra, pytest, ruff, moto, ...), on top of
# the demo's install if there is one. Each install has its own stamp.
PYTHON ?= python3
CONSTRAINTS ?= constraints/ci-py311.txt
VENV   ?= .venv
PY     := $(VENV)/bin/python
TORCH_STAMP := $(VENV)/.installed-torch
DEMO_STAMP  := $(VENV)/.installed-recipes
DEV_STAMP   := $(VENV)/.installed-dev

.PHONY: install install-demo demo test test-full lint bench clean

install: $(DEV_STAMP)
install-demo: $(DEMO_STAMP)

# the venv, pip and torch first: the CPU build the constraints name, before anything pulls another
$(TORCH_STAMP): $(CONSTRAINTS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -c $(CONSTRAINTS) torch
	touch $(TORCH_STAMP)

# the package with one extra: .installed-recipes -> '.[recipes]', .installed-dev -> '.[dev]'
$(VENV)/.installed-%: pyproject.toml $(CONSTRAINTS) $(TORCH_STAMP)
	$(PY) -m pip install -c $(CONSTRAINTS) -e '.[$*]' --config-settings editable_mode=compat
	touch $@

# SAC+HER on FetchReach with a short budget, over a persistent memory. Run it
# again: fresh networks learn from the stored memory first, and it prints how
# many fewer frames they needed.
DEMO_ARGS ?= memory.path=memory/demo/FetchReach-v4.zarr logger.target_success=0.95 \
	collector.total_frames=3000 hydra.run.dir=outputs/demo
demo: install-demo
	$(PY) recipes/her/train.py $(DEMO_ARGS)

# two pytest workers (pytest-xdist): most tests wait on subprocesses, so two
# workers on two cores take ~0.8x the wall time of one. PYTEST_ARGS="-n 0": serial.
PYTEST_ARGS ?= -n 2 --durations=25
test: install
	$(VENV)/bin/ruff check torchrl_robotmem tests benchmarks examples recipes tools experiments
	$(PY) -m pytest -q $(PYTEST_ARGS)

# everything, the tests marked `full` too (second tests of capabilities the default tier covers: about
# 8 more minutes); every landing runs it. `make test-full PYTEST_ARGS="-n 2 -m full"`: those alone.
test-full: install
	ROBOTMEM_FULL=1 $(MAKE) --no-print-directory test

lint: install
	$(VENV)/bin/ruff check torchrl_robotmem tests benchmarks examples recipes tools experiments

bench: install
	$(PY) benchmarks/bench_storage.py
	$(PY) benchmarks/bench_recall.py
	$(PY) benchmarks/bench_sampler.py
	$(PY) benchmarks/bench_collector.py
	$(PY) benchmarks/bench_learning.py all

clean:
	rm -rf memory outputs .pytest_cache
