# Every target that needs Python creates or reuses .venv and installs the project into it first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CHECKPOINT ?= checkpoints/halfcheetah-gmt
REST_PORT ?= 8000
GRPC_PORT ?= 50051

.PHONY: venv serve test lint proto data train eval bench clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	@touch $(STAMP)

venv: $(STAMP)

serve: $(STAMP)
	$(BIN)/gmt serve --rest-port $(REST_PORT) --grpc-port $(GRPC_PORT)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: $(STAMP) lint
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

# Regenerate the committed gRPC stubs from proto/gmt/v1/policy.proto (tests/proto checks they are current).
proto: $(STAMP)
	cd proto && ../$(BIN)/python -m grpc_tools.protoc -I. --python_out=. --grpc_python_out=. --pyi_out=. gmt/v1/policy.proto

data: $(STAMP)
	$(BIN)/gmt data collect --env HalfCheetah-v5
	$(BIN)/gmt data collect --env Hopper-v5
	$(BIN)/gmt data collect --env Walker2d-v5
	$(BIN)/gmt data collect --env Ant-v5 --no-random  # see behaviour/ant/TRAINED_WITH.md

# The exact command behind the shipped checkpoint (about 31 minutes on one core; see its PROVENANCE.md).
train: $(STAMP)
	$(BIN)/gmt train --dataset gmt/halfcheetah/mixed-v0 --out $(CHECKPOINT) --steps 20000 --lr 5e-4 \
		--warmup 1000 --threads 1 --seed 0

eval: $(STAMP)
	$(BIN)/gmt eval $(CHECKPOINT) --seeds 15 --threads 1 --json $(CHECKPOINT)/eval.json \
		--markdown $(CHECKPOINT)/eval.md --plot $(CHECKPOINT)/eval.png

# Figures as JSON (schema: service/bench.py; results: docs/performance.md): engine vs K, serving over every
# transport beside `gmt serve --naive`, training GFLOP/s. Needs wrk (apt-get install wrk) for the REST load.
bench: $(STAMP)
	$(BIN)/gmt bench --out bench.json

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
