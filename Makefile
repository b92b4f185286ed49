# lnnmpc — everything a user or CI needs runs through this file.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install train recipes eval video report compare paired tables test lint fmt bench bench-env bench-cells clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# make train TASK=walker-run [AGENT=tdmpc2] [SEEDS=1] [STEPS=200000] [ENVS=1] [OBS="noise=0.1"] [EVAL_OBS=...]
#            [TRAIN_ARGS="--set plan_horizon=5 --eval-every 20000 ..."]       (python -m lnnmpc.train.cli train -h)
#            [TRAIN_ARGS="--eval-prior"]: every evaluation also plays its episodes with the policy prior alone
#            [TRAIN_ARGS="--eval-policies"]: every evaluation also keeps its policy, policies/policy-<step>.npz
#            [TRAIN_ARGS="--deterministic"]: XLA's deterministic GPU ops, so a launch replays bit for bit (slower)
# make train RESUME=<run folder> [STEPS=...]        continue a run exactly where its newest checkpoint left it
# make train RECIPE=sparse [SEEDS=3] [TASK=...]      a task's measured best settings (`make recipes` lists them);
#            TASK, AGENT, ENVS, OBS and EVAL_OBS come from the recipe unless given on the command line
TASK     ?= walker-run
AGENT    ?= cfc-zp-det
SEEDS    ?= 1
STEPS    ?= 200000
ENVS     ?= 1
OBS      ?=
EVAL_OBS ?= $(OBS)
TRAIN_ARGS ?=
RESUME   ?=
RECIPE   ?=
# $(call given,VAR): non-empty where VAR was set on the command line or in the environment, not by this file
given = $(filter command line environment,$(origin $(1)))
train: $(STAMP)
ifneq ($(RESUME),)
	$(PY) -m lnnmpc.train.cli train --resume "$(RESUME)" $(if $(filter command line,$(origin STEPS)),--steps $(STEPS)) \
		$(TRAIN_ARGS)
else ifneq ($(RECIPE),)
	$(PY) -m lnnmpc.train.cli train --recipe "$(RECIPE)" --seeds $(SEEDS) --steps $(STEPS) \
		$(if $(call given,TASK),--task $(TASK)) $(if $(call given,AGENT),--agent $(AGENT)) \
		$(if $(call given,ENVS),--envs $(ENVS)) $(if $(call given,OBS),--obs "$(OBS)") \
		$(if $(call given,EVAL_OBS),--eval-obs "$(EVAL_OBS)") $(TRAIN_ARGS)
else
	$(PY) -m lnnmpc.train.cli train --task $(TASK) --agent $(AGENT) --seeds $(SEEDS) --steps $(STEPS) \
		--envs $(ENVS) --obs "$(OBS)" --eval-obs "$(EVAL_OBS)" $(TRAIN_ARGS)
endif

recipes: $(STAMP)
	$(PY) -m lnnmpc.train.cli recipes

# make eval RUN=<run folder> [OBS=...] [EPISODES=10] [BACKEND=mjx|dm_control] [CHECKPOINT=<env step>]
#           [ACTOR=prior]: the policy prior alone acts (no MPPI), to see what planning adds
#           [PLANNER="plan_horizon=5 iterations=12"]: plan with other MPPI settings than the run trained with
#           [EVAL_SEED=k]: the episodes' seed (default 0); evaluations with one seed play the same episodes
#           [DETERMINISTIC=1]: XLA's deterministic GPU ops, so that the evaluation replays on a GPU (slower)
RUN        ?=
EPISODES   ?= 10
BACKEND    ?= mjx
CHECKPOINT ?=
ACTOR      ?=
PLANNER    ?=
eval: $(STAMP)
	$(PY) -m lnnmpc.train.cli eval "$(RUN)" --episodes $(EPISODES) --backend $(BACKEND) \
		$(if $(filter command line,$(origin OBS)),--obs "$(OBS)") $(if $(CHECKPOINT),--checkpoint $(CHECKPOINT)) \
		$(if $(ACTOR),--actor $(ACTOR)) $(foreach setting,$(PLANNER),--planner $(setting)) \
		$(if $(EVAL_SEED),--seed $(EVAL_SEED)) $(if $(DETERMINISTIC),--deterministic)

# make video RUN=<run folder> [OUT=episode.mp4|.gif] [CHECKPOINT=...] [ACTOR=prior]  (offscreen OpenGL: Mesa EGL by default)
# [FILMS=N [FALLS=R]]: N episodes into a folder, keeping those whose return ended below R
# [DETERMINISTIC=1]: XLA's deterministic GPU ops for the planner (as make eval)
OUT ?=
video: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) -m lnnmpc.train.cli video "$(RUN)" $(if $(OUT),--out "$(OUT)") \
		$(if $(CHECKPOINT),--checkpoint $(CHECKPOINT)) $(if $(FILMS),--episodes $(FILMS)) \
		$(if $(FALLS),--falls-below $(FALLS)) $(if $(ACTOR),--actor $(ACTOR)) $(if $(DETERMINISTIC),--deterministic)

# make report RUN=<run folder>: redraw curve.png and summary.md
report: $(STAMP)
	$(PY) -m lnnmpc.train.cli report "$(RUN)"

# make compare RUNS="<run folder> <run folder> ..." OUT=curves.png [LABELS="'raw inputs' 'symlog inputs'"]
#              [METRICS=value_loss,reward_loss] [POOL="3 seeds"] [EVAL_COLUMN=prior_return]
#   learning curves of several runs on one plot (and the numbers in curves.csv); METRICS adds train.csv panels;
#   POOL=LABEL adds one curve of all the runs' seeds together (one configuration, other master seeds)
#   EVAL_COLUMN=prior_return plots the policy prior's returns (runs trained with TRAIN_ARGS="--eval-prior")
RUNS    ?=
LABELS  ?=
METRICS ?=
POOL    ?=
EVAL_COLUMN ?=
compare: $(STAMP)
	$(PY) -m lnnmpc.train.compare $(RUNS) --out "$(or $(OUT),curves.png)" $(if $(LABELS),--labels $(LABELS)) \
		$(if $(METRICS),--metrics $(METRICS)) $(if $(POOL),--pool "$(POOL)") \
		$(if $(EVAL_COLUMN),--eval-column $(EVAL_COLUMN))

# make paired CSVS="a.csv b.csv ..." [LABELS="'a' 'b'"] [PLOT=paired.png] [COMMON=1]
#   evaluations of several policies on the same episodes (make eval, one EVAL_SEED) compared episode by episode
#   against the first: mean difference ± standard error, episodes more / less, correlation
# make paired RUNS="runs/a runs/b ..." [STEP=200128|all] [EVALUATION=K]
#   the same for runs' training-time evaluations (same task and master seed: the same episodes at each evaluation);
#   EVALUATION=K pairs each run's K-th evaluation (-1 the last) for runs evaluated at other steps (action repeat)
paired: $(STAMP)
	$(PY) -m lnnmpc.train.paired $(if $(RUNS),--runs $(RUNS),$(CSVS)) $(if $(STEP),--step $(STEP)) \
		$(if $(EVALUATION),--evaluation $(EVALUATION)) \
		$(if $(LABELS),--labels $(LABELS)) $(if $(PLOT),--plot "$(PLOT)") $(if $(COMMON),--common)

# make tables RUNS="<run folder> <run folder> ..." [LABELS="'a' 'b'"] [FALLS=400]
#   markdown tables of several runs: every evaluation (mean ± std, std over seeds, seed means), the speed and
#   the commands that started them; FALLS=R adds each run's last evaluation split at return R (walker falls);
#   POOL=LABEL adds one column of all the runs' seeds together (one configuration, other master seeds);
#   EVALS=NAME reads each run's evals/NAME (what `make eval` wrote) instead of the training's eval.csv
FALLS ?=
tables: $(STAMP)
	$(PY) -m lnnmpc.train.tables $(RUNS) $(if $(LABELS),--labels $(LABELS)) $(if $(FALLS),--falls-below $(FALLS)) \
		$(if $(POOL),--pool "$(POOL)") $(if $(EVALS),--evals "$(EVALS)")

# make experiment NAME=table5_3 [ARGS="--seeds 3 --agents tdmpc2,cfc-zp-det --steps 200000 --dry-run"]
#   trains (resumes) the study's grid, evaluates it and writes experiments/results/studies/NAME.{csv,md}
#   studies: table5_3 table5_4 table5_5 table5_6 fig5_18 fig5_19  (python -m lnnmpc.experiments.run -h)
.PHONY: experiment
NAME ?=
ARGS ?=
experiment: $(STAMP)
	$(PY) -m lnnmpc.experiments.run $(NAME) $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks experiments

# the 15 slowest tests close the report: CI's budget for make test is 15 minutes on 2 CPU cores
test: lint
	$(VENV)/bin/pytest -q -n 2 --dist loadfile --durations=15 tests

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
