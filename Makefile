# lnnmpc — everything a user or CI needs runs through this file.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install train test lint fmt bench bench-env bench-cells clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# make train TASK=walker-run [AGENT=tdmpc2] [SEEDS=1] [STEPS=200000] [ENVS=1] [OBS="noise=0.1"] [EVAL_OBS=...]
TASK     ?= walker-run
AGENT    ?= cfc-zp-det
SEEDS    ?= 1
STEPS    ?= 200000
ENVS     ?= 1
OBS      ?=
EVAL_OBS ?= $(OBS)
TRAIN_ARGS ?=
train: $(STAMP)
	$(PY) -m lnnmpc.train.cli --task $(TASK) --agent $(AGENT) --seeds $(SEEDS) --steps $(STEPS) --envs $(ENVS) \
		--obs "$(OBS)" --eval-obs "$(EVAL_OBS)" $(TRAIN_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks experiments

test: lint
	$(VENV)/bin/pytest -q tests

# Benchmarks write JSON under benchmarks/results/ (meant for a GPU; see benchmarks/results/README.md).
bench-env: $(STAMP)
	$(PY) benchmarks/env_throughput.py

bench-cells: $(STAMP)
	$(PY) benchmarks/cells.py

bench: bench-env bench-cells

fmt: $(STAMP)
	$(VENV)/bin/ruff check --fix src tests benchmarks experiments

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache
