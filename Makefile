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

.PHONY: venv serve demo cluster cluster-down image compose-up compose-down test lint proto cpp-client data train eval bench constraints clean

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
# --store-min-replicas 1) and nginx (cluster/nginx.conf), all on loopback; REST :$(REST_PORT) and gRPC :$(GRPC_PORT)
# through nginx. Returns once all are ready (Redis replicas in sync, sentinels agreeing). Pids, logs, Redis data and
# sentinel configs in run/cluster/. Needs nginx and redis-server (apt-get install nginx redis-server).
# More `gmt serve` flags: make cluster CLUSTER_ARGS="-- --idle-timeout 60"; tuning knobs by environment: GMT_MAX_BATCH=32 make cluster
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

# The C++ Control-stream client (clients/cpp: one session's robot loop in C++, a starting point for a controller
# and the C++ row of `gmt bench --sections stream`) -> build/cpp/control_loop. Needs g++, pkg-config, protoc with
# gRPC's C++ plugin and library (apt-get install g++ pkg-config protobuf-compiler protobuf-compiler-grpc
# libgrpc++-dev libprotobuf-dev); its message code is generated from proto/ at build time.
cpp-client:
	clients/cpp/build.sh

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

# Any checkpoint: make eval CHECKPOINT=checkpoints/hopper-gmt (a Breakout one installs the `atari` extra too). The
# commands behind every other shipped checkpoint, data to evaluation, are the Remake section of its PROVENANCE.md.
eval: $(VENV)/.installed-eval $(if $(findstring breakout,$(CHECKPOINT)),$(VENV)/.installed-atari)
	$(BIN)/gmt eval $(CHECKPOINT) --seeds 15 --threads 2 --json $(CHECKPOINT)/eval.json \
		--markdown $(CHECKPOINT)/eval.md --plot $(CHECKPOINT)/eval.png

# Figures as JSON (schema: benchmarks/__init__.py; results: docs/performance.md): engine vs K, serving over every
# transport beside `GMT_NAIVE=1 gmt serve` (against the shipped HalfCheetah model), training GFLOP/s. Needs wrk (apt-get install wrk) for the REST load.
bench: $(VENV)/.installed-bench
	$(BIN)/gmt bench --checkpoint $(CHECKPOINT) --out bench.json

# After changing a dependency in pyproject.toml: install every extra, then pin exactly what is installed.
constraints:
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev,bench,atari]'
	$(BIN)/python tools/lock.py $(CONSTRAINTS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build/cpp
