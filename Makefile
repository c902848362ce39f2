# Two commands do all set-up on a fresh machine: `make run` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= runs/main
# 2-core CI machines: keep XLA from oversubscribing the cores.
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=true
export PYTHONUNBUFFERED := 1

.PHONY: run test bench bootstrap clean

bootstrap: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c requirements.lock -e '.[dev]'
	touch $(STAMP)

# The main job. Today: gradient check of every bundled scene (later: the whole loop).
run: $(STAMP)
	$(VENV)/bin/twinrl gradcheck all --x64 --out $(OUT)

# Two workers, one test file per worker: JAX compiles (most of the suite's time) are largely
# single-threaded, so a second process keeps the second core busy.
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile

bench: $(STAMP)
	$(PY) bench/physics.py --out bench/results

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
