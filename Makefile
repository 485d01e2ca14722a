# Two entry points: `make demo` and `make test`. Both create .venv on a fresh
# machine. torch is installed first, pinned, so that no CUDA wheels are pulled.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo test bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e '.[dev]' --config-settings editable_mode=compat
	touch $(STAMP)

demo: install
	$(PY) examples/demo.py

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/bench_storage.py
	$(PY) benchmarks/bench_recall.py
	$(PY) benchmarks/bench_sampler.py
	$(PY) benchmarks/bench_collector.py

clean:
	rm -rf memory outputs .pytest_cache
