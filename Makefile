# Two entry points (see README): `make run` (main job) and `make test`.
# Both create .venv on first use and install torch==2.13.0 (CPU wheel) BEFORE the package,
# so that no dependency pulls a CUDA build of torch.
PY ?= python3
# The CPU wheel of torch. On this project's machines pip finds it on disk; elsewhere, set
# TORCH_INDEX=--index-url=https://download.pytorch.org/whl/cpu or plain PyPI may give a multi-GB CUDA build.
TORCH_INDEX ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# One torch thread and a passive OpenMP wait policy: torch's busy-waiting pool is 10x slower on a loaded 2-core box.
export OMP_NUM_THREADS ?= 1
export OMP_WAIT_POLICY ?= PASSIVE
export MKL_NUM_THREADS ?= 1

.PHONY: setup run test bench figures results clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet $(TORCH_INDEX) torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/python experiments/lasa_benchmark.py

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 tests

# glibc malloc otherwise returns and re-requests the field's temporaries every step (page-fault storm).
bench: $(STAMP)
	MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=1073741824 $(BIN)/python experiments/bench_core.py
	MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=1073741824 $(BIN)/python experiments/bench_engine.py

# Every published figure and summary table, redrawn from the stored tables and libraries in results/ (no fitting).
figures: $(STAMP)
	$(BIN)/python experiments/figures.py

# Recompute everything results/ holds: each command's publish preset writes its tables, the libraries the figures
# are drawn from (results/libraries) and its figures; then `figures` redraws them all from what was stored. MNIST is
# read from $$LFD_MNIST_DIR (default: the development copy beside the checkout; the package never assumes a path).
results: $(STAMP)
	$(BIN)/python experiments/segment_lasa.py +experiment=segment_lasa_publish
	$(BIN)/python experiments/segment_lasa.py +experiment=segment_lasa_map_publish
	$(BIN)/python experiments/lasa_tasks.py +experiment=lasa_tasks_publish
	$(BIN)/python experiments/lasa_benchmark.py +experiment=lasa_benchmark_publish
	rm -rf multirun/lasa_benchmark_paper
	$(BIN)/python experiments/lasa_benchmark.py +experiment=lasa_benchmark_paper hydra.sweep.dir=multirun/lasa_benchmark_paper progress=false
	$(BIN)/python experiments/report_benchmark.py multirun/lasa_benchmark_paper --name lasa_benchmark_paper
	LFD_MNIST_DIR=$${LFD_MNIST_DIR:-../shared/data/mnist} $(BIN)/python experiments/mnist.py publish=true
	$(BIN)/python experiments/scooping.py +experiment=scooping_publish progress=false
	$(BIN)/python experiments/figures.py

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
