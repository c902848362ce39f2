# Two commands do all set-up on a fresh machine: `make run` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= runs/main
# 2-core CI machines: keep XLA from oversubscribing the cores.
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=true
export PYTHONUNBUFFERED := 1

.PHONY: run test bench bootstrap clean gradcheck docs

bootstrap: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c requirements.lock -e '.[dev]'
	touch $(STAMP)

# The main job: the whole loop (Real2Sim -> Learn@Sim -> Sim2Real) on its default task,
# cartpole_swingup's real twin: summary.json, report.md, plots and final.mp4 in $(OUT).
# --resume: a second `make run` continues an interrupted run (or re-reports a finished one).
# `make gradcheck` checks the gradients of every bundled scene against finite differences.
run: $(STAMP)
	$(VENV)/bin/twinrl run --resume --out $(OUT)

gradcheck: $(STAMP)
	$(VENV)/bin/twinrl gradcheck all --x64 --out runs/gradcheck

# Two workers, one test file per worker: JAX compiles (most of the suite's time) are largely
# single-threaded, so a second process keeps the second core busy.
# --no-loadscope-reorder: xdist otherwise hands files out by their number of tests, not in
# collection order, so tests/conftest.py's longest-first order had no effect (a 2-test
# 178 s file ran near the end; per-file times of a fresh-clone run, replayed through
# xdist's scheduling: 1,836 s for the longer worker by test count, 1,735 s longest first).
# Tests: XLA's LLVM backend at optimisation level 0 compiles about twice as fast (measured on
# tests/learn/test_trajopt.py, cold cache: 363 s -> 200 s) and the suite is compile-bound. Suite
# only: code compiled so runs slower (the renderer's 64x64 forward+gradient, one core, with both
# flags below: 86 -> 30 frames/s). Fusion emitters off is twinrl's default anyway (set on import,
# twinrl/jaxconfig.py: with them on, MJX's kinematics inside a rollout's scan takes time
# exponential in the arm's depth); it also halves compile times.
# One LLVM module per executable instead of XLA's default split into parts compiled on parallel
# threads: with two workers on two cores the threads only contend, and the split's own overhead
# costs more than it saves (a peg insertion episode's value_and_grad at -O0, 2 cores: compile CPU
# time 16.7 s -> 12.6-15.0 s).
TEST_XLA_FLAGS := --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false \
	--xla_cpu_parallel_codegen_split_count=1
test: $(STAMP)
	XLA_FLAGS="$(XLA_FLAGS) $(TEST_XLA_FLAGS)" $(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder

# The documentation site (MkDocs + Material + mkdocstrings, pinned in the `docs` extra) into
# site/; --strict fails on any broken link or reference. The CLI page is generated from the
# parser and the benchmarks page from bench/results/*.json (python bench/pages.py).
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install --quiet -c requirements.lock -e '.[docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -d site

bench: $(STAMP)
	$(PY) bench/physics.py --out bench/results

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
