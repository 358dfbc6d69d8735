# Every target that needs Python creates or reuses .venv and installs the project into it first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CHECKPOINT ?= checkpoints/halfcheetah-gmt
REST_PORT ?= 8000
GRPC_PORT ?= 50051

.PHONY: venv serve test lint proto proto-check data train eval bench clean

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
	$(BIN)/gmt data collect --env Ant-v5

train: $(STAMP)
	$(BIN)/gmt train --dataset gmt/halfcheetah/mixed-v0 --out $(CHECKPOINT)

eval: $(STAMP)
	$(BIN)/gmt eval $(CHECKPOINT) --seeds 15 --json $(CHECKPOINT)/eval.json --plot $(CHECKPOINT)/eval.png

bench: $(STAMP)
	$(BIN)/gmt bench

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
