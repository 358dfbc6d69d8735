#!/usr/bin/env bash
# `make image`: build the gmt image (docker/Dockerfile) as IMAGE (default gmt-service) on BASE (default the public
# python:3.11-slim). Skipped when IMAGE was already built from the same inputs (the Dockerfile, constraints.txt,
# pyproject.toml, the package's folders and the checkpoints, the base image's id; label gmt.inputs).
# Where BASE can be neither found nor pulled (no registry), the image is built on the local Debian base of
# docker/local-images.sh instead, and the script says so.
# With podman, the build sees this machine's pip configuration (`pip config list`, environment included) and the
# files and folders it names (certificates, constraints, local indexes and wheel folders), read-only: pip in the
# build installs what pip here would. Docker builds use the public indexes (PyPI, the PyTorch CPU index).
set -euo pipefail
. "$(dirname "$0")/lib.sh"
IMAGE=${IMAGE:-gmt-service}
BASE=${BASE:-python:3.11-slim}
PYTHON=${PYTHON:-python3}

if ! has_image "$BASE" && ! "$ENGINE" pull -q "$BASE" >/dev/null 2>&1; then
  read -r local_base _ < <("$DOCKER_DIR/local-images.sh")
  echo "note: $BASE can be neither found nor pulled: building on $local_base (docker/local-images.sh)" >&2
  BASE=$local_base
fi

build_args=(--build-arg BASE="$BASE")
[ "$ENGINE" = podman ] && build_args+=(--format docker) # OCI images have no HEALTHCHECK
if [ "$ENGINE" = podman ] && config=$("$PYTHON" -m pip config list 2>/dev/null) && [ -n "$config" ]; then
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  # One [global] (and [install], ...) section from every scope pip reads, the environment's (":env:") included.
  "$PYTHON" - "$tmp/pip.conf" "$config" <<'PY'
import ast, sys
sections = {}
for line in sys.argv[2].splitlines():
    key, sep, value = line.strip().partition("=")
    if sep:
        section, _, name = key.rpartition(".")
        section = "global" if section in (":env:", "") else section
        sections.setdefault(section, {})[name] = ast.literal_eval(value)
with open(sys.argv[1], "w") as f:
    for section, values in sections.items():
        f.write(f"[{section}]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()))
PY
  build_args+=(-v "$tmp/pip.conf:/etc/pip.conf:ro")
  for word in $(sed -n 's/^[a-z-]* = //p' "$tmp/pip.conf"); do
    path=${word#file://}
    # a local index (file://.../simple): its files may lie beside it, so its parent folder
    [[ $word == file://* ]] && path=$(dirname "$path")
    if [[ $path == /* ]] && [ -e "$path" ]; then build_args+=(-v "$path:$path:ro"); fi
  done
  # torch's CPU build from where pip here finds it, when that is a local index or wheel folder
  if grep -q -E '^(find-links|index-url|extra-index-url) = ' "$tmp/pip.conf"; then
    TORCH_INDEX=${TORCH_INDEX-}
  fi
fi
[ -n "${TORCH_INDEX+set}" ] && build_args+=(--build-arg TORCH_INDEX="$TORCH_INDEX")

cd "$ROOT"
hash=$(inputs_hash "$(image_id "$BASE")" "$ENGINE" "torch-index=${TORCH_INDEX-default}" docker/Dockerfile \
  docker/Dockerfile.dockerignore constraints.txt pyproject.toml README.md proto model service clients common \
  datagen benchmarks cluster checkpoints)
if built_from "$IMAGE" "$hash"; then
  echo "$IMAGE is up to date (inputs $hash)" >&2
else
  echo "building $IMAGE on $BASE with $ENGINE (inputs $hash)" >&2
  "$ENGINE" build "${build_args[@]}" --label gmt.inputs="$hash" -t "$IMAGE" -f docker/Dockerfile .
fi
"$ENGINE" image inspect --format "$IMAGE: {{.Size}} bytes" "$IMAGE"
