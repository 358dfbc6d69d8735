#!/usr/bin/env bash
# Images from Debian bookworm built on this machine, for where no registry can be reached (the tests, CI):
#   - LOCAL_BASE (localhost/gmt-local/python:3.11-bookworm): Debian's Python 3.11 with venv and CA certificates,
#     made by mmdebstrap from the Debian mirror (~20 s) and kept: reused whenever present;
#   - LOCAL_REDIS (localhost/gmt-local/redis:bookworm): Debian's redis-server on it (docker/local/redis.Dockerfile);
#   - LOCAL_NGINX (localhost/gmt-local/nginx:bookworm): Debian's nginx on it, rendering templates as the public
#     nginx image does (docker/local/nginx.Dockerfile).
# The last two are rebuilt only when their Dockerfile or the base changed. Prints the three names.
set -euo pipefail
. "$(dirname "$0")/lib.sh"
LOCAL_BASE=${LOCAL_BASE:-localhost/gmt-local/python:3.11-bookworm}
LOCAL_REDIS=${LOCAL_REDIS:-localhost/gmt-local/redis:bookworm}
LOCAL_NGINX=${LOCAL_NGINX:-localhost/gmt-local/nginx:bookworm}

if ! has_image "$LOCAL_BASE"; then
  command -v mmdebstrap >/dev/null 2>&1 || { echo "error: mmdebstrap is needed (apt-get install mmdebstrap)" >&2; exit 1; }
  echo "building $LOCAL_BASE from Debian bookworm (mmdebstrap)" >&2
  mmdebstrap --quiet --variant=minbase --include=python3,python3-venv,ca-certificates bookworm - \
    | "$ENGINE" import - "$LOCAL_BASE" >/dev/null
fi
base_id=$(image_id "$LOCAL_BASE")
for kind in redis nginx; do
  name=LOCAL_${kind^^}
  name=${!name}
  hash=$(inputs_hash "$base_id" "$DOCKER_DIR/local/$kind.Dockerfile" "$DOCKER_DIR/local/nginx-entrypoint.sh")
  if ! built_from "$name" "$hash"; then
    echo "building $name on $LOCAL_BASE" >&2
    "$ENGINE" build --quiet --build-arg BASE="$LOCAL_BASE" --label gmt.inputs="$hash" -t "$name" \
      -f "$DOCKER_DIR/local/$kind.Dockerfile" "$DOCKER_DIR/local" >/dev/null
  fi
done
echo "$LOCAL_BASE $LOCAL_REDIS $LOCAL_NGINX"
