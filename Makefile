# make run: create .venv if missing, install, run the main experiment on its default.
PY      ?= python3.11
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
export WANDB_MODE ?= offline
export WANDB_SILENT ?= true
export XLA_PYTHON_CLIENT_PREALLOCATE ?= false
export NO_MKDOCS_2_WARNING ?= 1

.PHONY: install run test test-install test-slow test-slurm docs bench lint sweep study study-lab pendulum clean

$(STAMP): pyproject.toml
	@test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev]"
	@touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/python -m hds.run +experiment=sim2real_friction

# Two workers, a test file each (its session's compiled fixtures stay in one process), the
# longest files first (tests/conftest.py: LONGEST_FIRST). The longest end-to-end tests, each
# with a cheaper test of the same behaviour in make test, are marked slow and run in
# `make test-slow`: a whole sim2real loop and its resume, domain randomization against fixed
# values, HDS end to end through the command line, the corrected and real simulators closing the
# gap, a training on the tree engine, the corrected simulator's active excitation, the mjx
# backend, sweeps on joblib's and submitit's launchers, the bench's scaling and sections runs, a
# discovery on each tree-engine system and on EMPS, retraining on a corrected simulator, HDS's
# beta sweep and model-share ramp, the noise-decay sweep, sharding, a toy effect's training, more
# improvement steps. That keeps `make test` (what CI runs) under 10 minutes on 2 cores with an
# empty compilation cache.
# TEST_WORKERS=0 runs them in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m "not slow"

# A wheel of this checkout installed into a fresh venv (its dependencies read from .venv's)
# composes and runs from another directory: tests/test_install.py (CI runs it after make test)
test-install: $(STAMP)
	$(BIN)/python -m pytest -q -n 0 tests/test_install.py

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m slow

# the user guide's site (docs/, mkdocs.yml) into site/; --strict: a broken link, a missing page
# or an API name that no longer exists fails the build
DOCS_STAMP := $(VENV)/.installed-docs
$(DOCS_STAMP): pyproject.toml $(STAMP)
	$(BIN)/python -m pip install -q -e ".[dev,docs]"
	@touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(BIN)/mkdocs build --strict --quiet

# A single-node SLURM cluster on this machine (root; installs slurm-wlm, slurmdbd, munge and
# mariadb-server with apt-get), sweeps through hydra/launcher=slurm on it, the cluster stopped
# after (docs/cluster.md: ~11 min on 2 cores, so not in CI).
test-slurm: $(STAMP)
	bash tests/slurm/up.sh
	$(BIN)/python tests/slurm/check.py; rc=$$?; bash tests/slurm/down.sh; exit $$rc

bench: $(STAMP)
	$(BIN)/python -m bench.run

lint: $(STAMP)
	$(BIN)/ruff check hds tests bench experiments
	$(BIN)/ruff format --check hds tests bench experiments

sweep: $(STAMP)
	$(BIN)/python -m hds.run -m +experiment=sim2real_friction real.friction_gap=0,0.5,1,2

# The study of experiments/sim2real_friction: its sweeps (resumable: finished jobs are skipped;
# delete $(STUDY_RUN) to start over): friction gaps (the methods whose training reads the plant,
# then those trained once and evaluated on every friction plant: plant_free/), then the other
# effects' plants (policies that depend on the plant, then those trained once), the sim2real
# loop at 20, 80 and 40 N (closed-loop PODS), then at 20 and 80 N with HDS (its model refitted
# on each round's deployments), then on each other effect's plant, then one report of all, its figures and GIF (closed-loop PODS from the
# frictionless simulator, plant_free/1, on the 80 N plant, its eval plant x4) into
# experiments/sim2real_friction/results; the oracle at the loop's total budget and schedule (450 epochs) at
# 20, 80 and 40 N (40 N added last, so finished jobs keep their numbers) and on the other
# effects' plants, and the swing-up at
# 20, 40 and 80 N (the corrected simulator and the oracle at each, the frictionless simulator
# and domain randomization once: plant_free/, open-loop PODS as published once: open_loop/,
# then HDS, then the loop at each, its rounds
# trained from scratch), each reported apart (GIF: the frictionless simulator's policy,
# plant_free/0, at 20 N).
STUDY_RUN := outputs/study/sim2real_friction
# the study's configs live beside it (experiments/sim2real_friction/conf/experiment/), added to
# Hydra's search path: +experiment=sim2real_study* composes as from hds/conf/experiment/
STUDY_CONF := --config-dir experiments/sim2real_friction/conf
STUDY_SWINGUP := outputs/study/swingup
STUDY_ORACLE := outputs/study/oracle_budget
# the oracle at the loop's budget and schedule: 450 epochs, its effects met after the first
# third (round 0's 150 epochs) and grown in over 30 (a round's ramp)
STUDY_ORACLE_BUDGET := method=oracle algo.epochs=450 'anneal.effect_ramp=[0.33,0.4]'
STUDY_LOOP := $(BIN)/python -m hds.loop env.backend=analytic seeds=5 method=pods_cl_effects
STUDY_HDS_LOOP := $(BIN)/python -m hds.loop env.backend=analytic seeds=5 method=hds
STUDY_SWINGUP_LOOP := $(BIN)/python -m hds.loop $(STUDY_CONF) +experiment=sim2real_study_swingup_loop
STUDY_EFFECT_PLANTS := gain offset deadzone delay lag mass viscous sensor_bias friction_gain
study: $(STAMP)
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study hydra.sweep.dir=$(STUDY_RUN)
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_friction_shared \
		hydra.sweep.dir=$(STUDY_RUN)/plant_free
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_effects hydra.sweep.dir=$(STUDY_RUN)/effects
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_shared hydra.sweep.dir=$(STUDY_RUN)/shared
	$(STUDY_LOOP) real.friction_gap=1 hydra.run.dir=$(STUDY_RUN)/loop/x1
	$(STUDY_LOOP) real.friction_gap=4 hydra.run.dir=$(STUDY_RUN)/loop/x4
	$(STUDY_LOOP) real.friction_gap=2 hydra.run.dir=$(STUDY_RUN)/loop/x2
	$(STUDY_HDS_LOOP) real.friction_gap=1 hydra.run.dir=$(STUDY_RUN)/loop/hds_x1
	$(STUDY_HDS_LOOP) real.friction_gap=4 hydra.run.dir=$(STUDY_RUN)/loop/hds_x4
	for plant in $(STUDY_EFFECT_PLANTS); do \
		$(STUDY_LOOP) real=$$plant hydra.run.dir=$(STUDY_RUN)/loop/$$plant || exit 1; done
	$(BIN)/python -m hds.report dir=$(STUDY_RUN) out=experiments/sim2real_friction/results \
		gif=plant_free/1 gif_plant=x4
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study $(STUDY_ORACLE_BUDGET) \
		real.friction_gap=1,4,2 hydra.sweep.dir=$(STUDY_ORACLE)
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_effects $(STUDY_ORACLE_BUDGET) \
		hydra.sweep.dir=$(STUDY_ORACLE)/effects
	$(BIN)/python -m hds.report dir=$(STUDY_ORACLE) out=experiments/sim2real_friction/results/oracle_450
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_swingup hydra.sweep.dir=$(STUDY_SWINGUP)
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_swingup_shared \
		hydra.sweep.dir=$(STUDY_SWINGUP)/plant_free
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_swingup_open_loop \
		hydra.sweep.dir=$(STUDY_SWINGUP)/open_loop
	$(BIN)/python -m hds.run $(STUDY_CONF) +experiment=sim2real_study_swingup_hds hydra.sweep.dir=$(STUDY_SWINGUP)/hds
	for gap in 1 2 4; do \
		$(STUDY_SWINGUP_LOOP) real.friction_gap=$$gap hydra.run.dir=$(STUDY_SWINGUP)/loop/x$$gap \
		|| exit 1; done
	$(BIN)/python -m hds.report dir=$(STUDY_SWINGUP) out=experiments/sim2real_friction/results/swingup gif=plant_free/0

# The lab study (experiments/lab_study/README.md, issue 38.4): on draws of the lab plant
# families (docs/lab-plants.md), per task: the methods trained once for the family (the raw
# simulator, domain randomization over the family's distribution) evaluated on every draw, the
# one-shot corrected simulator and the oracle per draw, then per draw the sim2real loop (3
# rounds) without and with HDS's hybrid model (the two side by side, as the sweeps run two
# jobs at a time on 2 cores; their round 0 restores the raw simulator's shared job, the same
# training, loop.start_from), then the study's table. Resumable: finished jobs
# and loop rounds are skipped (delete $(LAB_RUN) to start over). 5 draws for the balance tasks,
# 3 for the swing-ups; 3 seeds each. LAB_TASKS=cartpole_balance runs one task; LAB_DRAWS="5 6 7"
# runs those draws of every task instead (the shared sweep trains on the first, its own plant,
# and evaluates on the others: eval_plants); LAB_RUN=<dir> writes elsewhere.
LAB_RUN ?= outputs/study/lab
LAB_CONF := --config-dir experiments/lab_study/conf
LAB_TASKS ?= cartpole_balance cartpole_swingup furuta_balance furuta_swingup
LAB_DRAWS ?=
study-lab: $(STAMP)
	for task in $(LAB_TASKS); do \
		case $$task in furuta*) fam=_furuta real=lab_furuta;; *) fam= real=lab_cartpole;; esac; \
		draws="$(LAB_DRAWS)"; \
		[ -n "$$draws" ] || case $$task in *swingup) draws="0 1 2";; *) draws="0 1 2 3 4";; esac; \
		own=$${draws%% *}; others=; for k in $$draws; do [ $$k = $$own ] || \
			others="$$others +real@eval_plants.d$$k=$$real eval_plants.d$$k.draw=$$k"; done; \
		set -- $(LAB_CONF) env=$$task; out=$(LAB_RUN)/$$task; t=lab_task_$$task; \
		$(BIN)/python -m hds.run -m "$$@" "+experiment=[lab_study$$fam,$$t]" \
			real.draw=$$(echo $$draws | tr ' ' ,) hydra.sweep.dir=$$out/per_draw || exit 1; \
		$(BIN)/python -m hds.run -m "$$@" "+experiment=[lab_study$${fam}_shared,$$t]" \
			real.draw=$$own $$others hydra.sweep.dir=$$out/shared || exit 1; \
		for k in $$draws; do \
			$(BIN)/python -m hds.loop "$$@" "+experiment=[lab_study_loop$$fam,$$t]" \
				real.draw=$$k loop.start_from=$$out/shared/0 \
				hydra.run.dir=$$out/loop/d$$k & plain=$$!; \
			$(BIN)/python -m hds.loop "$$@" "+experiment=[lab_study_loop$$fam,$$t]" \
				real.draw=$$k loop.start_from=$$out/shared/0 dynamics=residual \
				hydra.run.dir=$$out/hybrid/d$$k & hybrid=$$!; \
			wait $$plain && wait $$hybrid || exit 1; done; done
	$(BIN)/python experiments/lab_study/report.py $(LAB_RUN)

# Gap discovery on the real multi-arm pendulum against its authors' fit
# (experiments/multiarm_pendulum/README.md; needs ../shared/data/multiarm_pendulum)
pendulum: $(STAMP)
	$(BIN)/python experiments/multiarm_pendulum/run.py

clean:
	rm -rf $(VENV) outputs/runs outputs/multiruns
