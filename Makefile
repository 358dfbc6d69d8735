# Every target that needs Python creates or reuses .venv and installs into it the extra it needs (docs/install.md),
# at the versions of constraints.txt: `make serve` the `serve` extra, `make test` the `dev` extra (all tests).
# torch is pinned there as its CPU build: pip finds it in a local wheel directory (as here) or, elsewhere, on the
# PyTorch CPU index (export PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
CONSTRAINTS := constraints.txt
CHECKPOINT ?= checkpoints/halfcheetah-gmt
REST_PORT ?= 8000
GRPC_PORT ?= 50051

.PHONY: venv serve demo cluster cluster-down image compose-up compose-down test lint proto data train eval train-breakout eval-breakout data-breakout5 train-breakout5 eval-breakout5 data-breakout-dagger train-breakout-dagger eval-breakout-dagger data-hopper-pool train-hopper-pool data-hopper train-hopper eval-hopper data-walker2d train-walker2d eval-walker2d data-ant train-ant eval-ant bench constraints clean

$(VENV)/.installed-%: pyproject.toml $(CONSTRAINTS)
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c $(CONSTRAINTS) -e '.[$*]'
	@touch $@

venv: $(VENV)/.installed-dev

# More `gmt serve` flags: make serve SERVE_ARGS='--record-dir runs/recordings --auth-token T' (gmt serve --help).
SERVE_ARGS ?=
serve: $(VENV)/.installed-serve
	$(BIN)/gmt serve --rest-port $(REST_PORT) --grpc-port $(GRPC_PORT) $(SERVE_ARGS)

# With `make serve` running (another terminal, same REST_PORT / GRPC_PORT): install the `run` extra (MuJoCo,
# matplotlib) into .venv and drive HalfCheetah-v5 with halfcheetah-gmt through the server, goal `low`, `high` from
# step 300, `low` again from 600. Prints each goal segment's target and achieved speed, writes
# $(DEMO_OUT)/episode-0.{json,csv,png}. Over REST at SERVER (default http://localhost:$(REST_PORT)), or with
# TRANSPORT=grpc over the gRPC Control stream at GRPC_TARGET (default localhost:$(GRPC_PORT)). DEMO_ARGS replaces
# the goals and length: make demo DEMO_ARGS="--goal lowest --schedule highest@500 --steps 1000 --video".
SERVER ?= http://localhost:$(REST_PORT)
GRPC_TARGET ?= localhost:$(GRPC_PORT)
TRANSPORT ?= rest
DEMO_OUT ?= runs/demo
DEMO_ARGS ?= --goal low --schedule high@300,low@600 --steps 900 --seed 0
DEMO_VIA_rest = --server $(SERVER)
DEMO_VIA_grpc = --grpc $(GRPC_TARGET) --stream

demo: $(VENV)/.installed-run
	$(if $(DEMO_VIA_$(TRANSPORT)),,$(error TRANSPORT must be rest or grpc, not '$(TRANSPORT)'))
	$(BIN)/gmt run --env HalfCheetah-v5 --model halfcheetah-gmt $(DEMO_VIA_$(TRANSPORT)) $(DEMO_ARGS) \
		--out $(DEMO_OUT)

# A Redis primary (redis) and two replicas (redis-replica, redis-replica-2) watched by three sentinels (sentinel-1..3,
# quorum 2: a failed primary is replaced by a replica), two gmt replicas (gmt-1, gmt-2: --redis-url redis+sentinel://...,
# --store-min-replicas 1) and nginx (docker/nginx.conf), all on loopback; REST :$(REST_PORT) and gRPC :$(GRPC_PORT)
# through nginx. Returns once all are ready (Redis replicas in sync, sentinels agreeing). Pids, logs, Redis data and
# sentinel configs in run/cluster/. Needs nginx and redis-server (apt-get install nginx redis-server).
# More `gmt serve` flags: make cluster CLUSTER_ARGS="-- --max-batch 32"
cluster: $(VENV)/.installed-serve
	$(BIN)/gmt cluster up --rest-port $(REST_PORT) --grpc-port $(GRPC_PORT) $(CLUSTER_ARGS)

# Stops exactly the processes whose pids are in run/cluster/*.pid (nginx, gmt-*, sentinel-*, then the Redis servers).
cluster-down:
	$(BIN)/gmt cluster down

# Containers (docs/cluster.md), with docker or podman (ENGINE=docker|podman; default docker if its daemon answers).
# `make image`: the gmt image IMAGE on BASE (docker/image.sh: rebuilt only when its inputs changed; on the local
# Debian base of docker/local-images.sh where BASE can be neither found nor pulled). `make compose-up`: the topology
# of `make cluster` in containers (docker/compose.yaml): REST :$(REST_PORT) and gRPC :$(GRPC_PORT) on 127.0.0.1
# through nginx, once every stage is healthy; needs GMT_AUTH_TOKEN. `make compose-down` removes its containers,
# network and volumes. With podman, podman-compose (pinned in constraints.txt) is installed into .venv.
IMAGE ?= gmt-service
BASE ?= python:3.11-slim
COMPOSE_PROJECT ?= gmt
CONTAINER_ENV = ENGINE=$(ENGINE) COMPOSE_PROJECT=$(COMPOSE_PROJECT) PODMAN_COMPOSE=$(BIN)/podman-compose

image:
	$(CONTAINER_ENV) IMAGE=$(IMAGE) BASE=$(BASE) docker/image.sh

$(VENV)/.installed-podman-compose: $(CONSTRAINTS)
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -c $(CONSTRAINTS) podman-compose
	@touch $@

compose-up: $(VENV)/.installed-podman-compose
	$(CONTAINER_ENV) GMT_IMAGE=$(IMAGE) GMT_REST_PORT=$(REST_PORT) GMT_GRPC_PORT=$(GRPC_PORT) docker/compose.sh up

compose-down:
	$(CONTAINER_ENV) docker/compose.sh down

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: $(VENV)/.installed-dev lint
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

# Regenerate the committed gRPC stubs from proto/gmt/v1/*.proto (tests/test_proto.py checks they are current).
proto: $(VENV)/.installed-dev
	cd proto && ../$(BIN)/python -m grpc_tools.protoc -I. --python_out=. --grpc_python_out=. --pyi_out=. gmt/v1/policy.proto gmt/v1/admin.proto

data: $(VENV)/.installed-data
	$(BIN)/gmt data collect --env HalfCheetah-v5
	$(BIN)/gmt data collect --env Hopper-v5 --no-random  # see behaviour/hopper/TRAINED_WITH.md
	$(BIN)/gmt data collect --env Walker2d-v5 --no-random  # see behaviour/walker2d/TRAINED_WITH.md
	$(BIN)/gmt data collect --env Ant-v5 --no-random  # scripted gait levels, see behaviour/ant/TRAINED_WITH.md
	$(BIN)/gmt data collect --env ALE/Breakout-v5     # scripted RAM agents, ~3 min (docs/breakout-data.md)

# The exact command behind the shipped checkpoint (35 minutes on 2 threads here; see its PROVENANCE.md).
train: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/halfcheetah/mixed-v0 --out $(CHECKPOINT) --attention window --batch-size 32 \
		--steps 8000 --lr 5e-4 --warmup 500 --threads 2 --no-bf16 --seed 0 \
		--default-action-mode mean --switch-relabel-steps 20

eval: $(VENV)/.installed-eval
	$(BIN)/gmt eval $(CHECKPOINT) --seeds 15 --threads 2 --json $(CHECKPOINT)/eval.json \
		--markdown $(CHECKPOINT)/eval.md --plot $(CHECKPOINT)/eval.png

# The training settings both Breakout checkpoints share (each adds its data, goals and steps).
BREAKOUT_TRAIN = --statistic return --attention window --context-length 4 --sequence-length 8 --batch-size 64 --lr 5e-4 --warmup-steps 300 --threads 2 --seed 0 --log-every 50 --save-every 2000 --default-action-mode sample

# The exact commands behind the shipped checkpoints/breakout-gmt (its PROVENANCE.md): ~40 min on 2 cores.
train-breakout: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/breakout/mixed-v0 --out checkpoints/breakout-gmt --k 3 --steps 14000 $(BREAKOUT_TRAIN)

eval-breakout: $(VENV)/.installed-eval $(VENV)/.installed-atari
	$(MAKE) eval CHECKPOINT=checkpoints/breakout-gmt

# The exact commands behind checkpoints/breakout5-gmt (its PROVENANCE.md): ~4 min collection, ~44 min training.
data-breakout5: $(VENV)/.installed-data $(VENV)/.installed-atari
	$(BIN)/python -m gmt.datagen.breakout --recipe late

train-breakout5: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/breakout/late-v1 --out checkpoints/breakout5-gmt --k 5 --steps 12000 $(BREAKOUT_TRAIN)

eval-breakout5: $(VENV)/.installed-eval $(VENV)/.installed-atari
	$(MAKE) eval CHECKPOINT=checkpoints/breakout5-gmt
	$(BIN)/gmt eval checkpoints/breakout5-gmt --seeds 15 --threads 2 --action-mode argmax \
		--json checkpoints/breakout5-gmt/eval-argmax.json --markdown checkpoints/breakout5-gmt/eval-argmax.md

# The data and training behind checkpoints/breakout-dagger-gmt (its PROVENANCE.md): the lead-v1 levels (~6 min), more
# of them (~8 min), then two DAgger rounds (~15 min each on two cores): the committed models of
# behaviour/breakout-dagger-gmt play every goal and the scripted levels label their states; each round is merged
# with the scripted data into one dataset and a goal table (data/labels/). The models were trained on a GPU (the
# device machine: --device cuda --time-limit-s 120 stopped at step 8446); train-breakout-dagger runs the same
# 8446 steps on whatever device there is (hours on a CPU).
DAGGER = $(BIN)/python -m gmt.datagen.breakout_dagger
BD = gmt/breakout
data-breakout-dagger: $(VENV)/.installed-data $(VENV)/.installed-atari $(VENV)/.installed-train
	$(BIN)/python -m gmt.datagen.breakout --recipe lead
	$(BIN)/python -m gmt.datagen.breakout --recipe lead --episodes lead4=160 lead140=80 lead152=80 lead170=80 \
		--seed 1 --out-id $(BD)/lead-more-v1
	$(DAGGER) collect behaviour/breakout-dagger-gmt/round0-gmt --goals 4=lead4 0=lead170 1=lead152 --seeds 80 \
		--out-id $(BD)/lead-dagger-a-v1 & \
	$(DAGGER) collect behaviour/breakout-dagger-gmt/round0-gmt --goals 3=lead4 2=lead140 --seeds 80 \
		--out-id $(BD)/lead-dagger-b-v1 & wait
	$(DAGGER) merge $(BD)/lead-v1 $(BD)/lead-dagger-a-v1 $(BD)/lead-dagger-b-v1 --out-id $(BD)/lead-dagger-v1 --k 5 \
		--labels data/labels/breakout-dagger-1.json
	$(DAGGER) collect behaviour/breakout-dagger-gmt/round1-gmt --goals 4=lead4 0=lead170 1=lead152 --seeds 80 \
		--seed-base 20000 --action-mode argmax --out-id $(BD)/lead-dagger2-a-v1 & \
	$(DAGGER) collect behaviour/breakout-dagger-gmt/round1-gmt --goals 3=lead4 2=lead140 --seeds 80 \
		--seed-base 20000 --action-mode argmax --out-id $(BD)/lead-dagger2-b-v1 & wait
	$(DAGGER) merge $(BD)/lead-v1 $(BD)/lead-dagger-a-v1 $(BD)/lead-dagger-b-v1 $(BD)/lead-more-v1 \
		$(BD)/lead-dagger2-a-v1 $(BD)/lead-dagger2-b-v1 --out-id $(BD)/lead-dagger2-v1 --k 5 \
		--labels data/labels/breakout-dagger-2.json

train-breakout-dagger: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset $(BD)/lead-dagger2-v1 --labels data/labels/breakout-dagger-2.json \
		--out checkpoints/breakout-dagger-gmt --init-from behaviour/breakout-dagger-gmt/round1-gmt --statistic return \
		--k 5 --attention window --context-length 4 --sequence-length 8 --steps 8446 --lr 3e-4 --warmup-steps 100 \
		--seed 0 --log-every 200 --save-every 2000 --default-action-mode argmax --batch-size 256

eval-breakout-dagger: $(VENV)/.installed-eval $(VENV)/.installed-atari
	$(MAKE) eval CHECKPOINT=checkpoints/breakout-dagger-gmt
	$(BIN)/gmt eval checkpoints/breakout-dagger-gmt --seeds 15 --threads 2 --action-mode sample \
		--json checkpoints/breakout-dagger-gmt/eval-sample.json --markdown checkpoints/breakout-dagger-gmt/eval-sample.md

# The data and training behind checkpoints/hopper-gmt (its PROVENANCE.md): ~11 min collection and ~20 min
# training on one core each. The pool-started episodes start from states of behaviour/hopper3-gmt/pool-gmt, a
# three-goal GMT, while it cycles its goals every 100 steps; data-hopper-pool and train-hopper-pool remake that
# model (~14 and ~25 min) from behaviour/hopper3-gmt/two-goal-gmt, the two-goal hopper-gmt shipped until 2026-11-27.
data-hopper-pool: $(VENV)/.installed-data
	$(BIN)/gmt data collect --env Hopper-v5 --no-random --behaviour-dir behaviour/hopper3-gmt --episodes-per-level 200 \
		--pool-start slow=0.5 --pool-start medium=0.5 --pool-start fast=0.5 --plan slow=1.6,1.2,0.8 \
		--plan medium=2.6,2.06,1.6,1.2 --pool-checkpoint behaviour/hopper3-gmt/two-goal-gmt --out-id gmt/hopper/dagger3b-v0

train-hopper-pool: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/hopper/dagger3b-v0 --out behaviour/hopper3-gmt/pool-gmt --attention window \
		--batch-size 32 --lr 5e-4 --warmup-steps 500 --threads 1 --no-bf16 --seed 0 --steps 5000 --masking token \
		--max-timestep 1 --default-action-mode mean

data-hopper: $(VENV)/.installed-data
	$(BIN)/gmt data collect --env Hopper-v5 --no-random --behaviour-dir behaviour/hopper3-gmt --episodes-per-level 200 \
		--pool-start slow=0.5 --pool-start medium=0.5 --pool-start fast=0.5 --plan slow=1.6,1.2,0.8 \
		--plan medium=2.6,2.06,1.6,1.2 --pool-checkpoint behaviour/hopper3-gmt/pool-gmt --pool-cycle 100 \
		--out-id gmt/hopper/cycle100-v0

train-hopper: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/hopper/cycle100-v0 --out checkpoints/hopper-gmt --attention window \
		--batch-size 32 --lr 5e-4 --warmup-steps 500 --threads 1 --no-bf16 --seed 0 --steps 5000 --masking token \
		--max-timestep 1 --k 3 --default-action-mode mean --switch-relabel-steps 20

eval-hopper: $(VENV)/.installed-eval
	$(BIN)/gmt eval checkpoints/hopper-gmt --seeds 15 --threads 1 --json checkpoints/hopper-gmt/eval.json \
		--markdown checkpoints/hopper-gmt/eval.md --plot checkpoints/hopper-gmt/eval.png

# The data and training behind checkpoints/walker2d-gmt (its PROVENANCE.md): ~31 min collection and ~31 min
# training on one core each.
data-walker2d: $(VENV)/.installed-data
	$(BIN)/gmt data collect --env Walker2d-v5 --no-random --behaviour-dir behaviour/walker2d-gmt \
		--episodes-per-level 200 --plan slow=1.0,1.6,1.3,0.7 --plan fast=1.6,2.0,1.3 --plan-from-rest slow=1.1 \
		--out-id gmt/walker2d/c1016b-rt11-v0

train-walker2d: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/walker2d/c1016b-rt11-v0 --out checkpoints/walker2d-gmt --attention window \
		--batch-size 32 --lr 5e-4 --warmup-steps 500 --threads 1 --no-bf16 --seed 1 --steps 5000 --masking token \
		--max-timestep 1 --k 2 --default-action-mode sample

eval-walker2d: $(VENV)/.installed-eval
	$(BIN)/gmt eval checkpoints/walker2d-gmt --seeds 15 --threads 1 --json checkpoints/walker2d-gmt/eval.json \
		--markdown checkpoints/walker2d-gmt/eval.md --plot checkpoints/walker2d-gmt/eval.png

# The data and training behind checkpoints/ant-gmt (its PROVENANCE.md): ~3 min collection and ~21 min training on
# one core each. The behaviour is the scripted gait of behaviour/ant (`gmt data gait`, datagen/gait.py).
data-ant: $(VENV)/.installed-data
	$(BIN)/gmt data collect --env Ant-v5 --no-random --episodes-per-level 150 --pool-start slow=0.5 \
		--pool-start medium=0.5 --pool-start fast=0.5 --out-id gmt/ant/gait-455565-v0

train-ant: $(VENV)/.installed-train
	$(BIN)/gmt train --dataset gmt/ant/gait-455565-v0 --out checkpoints/ant-gmt --attention window --batch-size 32 \
		--lr 5e-4 --warmup-steps 500 --threads 1 --no-bf16 --seed 1 --steps 5000 --masking token \
		--max-timestep 1 --default-action-mode mean

eval-ant: $(VENV)/.installed-eval
	$(BIN)/gmt eval checkpoints/ant-gmt --seeds 15 --threads 1 --json checkpoints/ant-gmt/eval.json \
		--markdown checkpoints/ant-gmt/eval.md --plot checkpoints/ant-gmt/eval.png

# Figures as JSON (schema: benchmarks/__init__.py; results: docs/performance.md): engine vs K, serving over every
# transport beside `gmt serve --naive` (against the shipped HalfCheetah model), training GFLOP/s. Needs wrk (apt-get install wrk) for the REST load.
bench: $(VENV)/.installed-bench
	$(BIN)/gmt bench --checkpoint $(CHECKPOINT) --out bench.json

# After changing a dependency in pyproject.toml: install every extra, then pin exactly what is installed.
constraints:
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev,bench,atari]'
	$(BIN)/python tools/lock.py $(CONSTRAINTS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
