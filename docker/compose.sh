#!/usr/bin/env bash
# `make compose-up` / `make compose-down`: the topology of docker/compose.yaml with docker compose, or with
# podman-compose (PODMAN_COMPOSE, default podman-compose on PATH), as project COMPOSE_PROJECT (default gmt).
#   docker/compose.sh up     start it and return once nginx answers; the gmt image (GMT_IMAGE, default
#                            gmt-service) must exist (make image). The redis and nginx images default to the
#                            public ones; where those can be neither found nor pulled, Debian-built ones
#                            (docker/local-images.sh) are used instead, and the script says so.
#   docker/compose.sh down   stop and remove its containers, network and volumes (the sessions with them).
# docker compose waits for each service's health checks itself (depends_on conditions, --wait). podman (4.3 here)
# runs health checks from systemd timers and podman-compose before 1.7 ignores the conditions: so the services
# are started in the order the conditions give, each stage once `podman healthcheck run` passes on the one before.
set -euo pipefail
. "$(dirname "$0")/lib.sh"
PROJECT=${COMPOSE_PROJECT:-gmt}
TIMEOUT=${COMPOSE_TIMEOUT:-300}
FILE=$DOCKER_DIR/compose.yaml
STAGES=("redis" "redis-replica redis-replica-2" "sentinel-1 sentinel-2 sentinel-3" "gmt-1 gmt-2" "nginx")

compose() {
  if [ "$ENGINE" = docker ]; then
    docker compose -p "$PROJECT" -f "$FILE" "$@"
  else
    "${PODMAN_COMPOSE:-podman-compose}" --in-pod false -p "$PROJECT" -f "$FILE" "$@"
  fi
}

# container SERVICE: the name of the project's container of that service.
container() {
  "$ENGINE" ps -a --filter "label=com.docker.compose.project=$PROJECT" \
    --filter "label=com.docker.compose.service=$1" --format '{{.Names}}' | head -n1
}

# wait_healthy SERVICE...: until every one's health check passes (its logs and an error if it exits first).
wait_healthy() {
  local deadline=$((SECONDS + TIMEOUT)) c
  for svc in "$@"; do
    c=$(container "$svc")
    until "$ENGINE" healthcheck run "$c" >/dev/null 2>&1; do
      if [ "$("$ENGINE" inspect --format '{{.State.Status}}' "$c")" != running ] || ((SECONDS > deadline)); then
        "$ENGINE" logs --tail 30 "$c" >&2 || true
        echo "error: $svc ($c) is not healthy; docker/compose.sh down removes the rest" >&2
        return 1
      fi
      sleep 1
    done
    echo "$svc is healthy" >&2
  done
}

# pick VARIABLE PUBLIC-IMAGE LOCAL-INDEX: the public image unless it can be neither found nor pulled.
pick() {
  if [ -n "${!1:-}" ]; then return; fi
  if has_image "$2" || "$ENGINE" pull -q "$2" >/dev/null 2>&1; then
    export "$1=$2"
  else
    local names
    read -r -a names < <("$DOCKER_DIR/local-images.sh")
    echo "note: $2 can be neither found nor pulled: using ${names[$3]} (docker/local-images.sh)" >&2
    export "$1=${names[$3]}"
  fi
}

case "${1:-}" in
  up)
    : "${GMT_AUTH_TOKEN:?set a token for the service: export GMT_AUTH_TOKEN=\$(openssl rand -hex 16)}"
    export GMT_IMAGE=${GMT_IMAGE:-gmt-service}
    has_image "$GMT_IMAGE" || { echo "error: no image $GMT_IMAGE: make image first" >&2; exit 1; }
    pick GMT_REDIS_IMAGE redis:7-alpine 1
    pick GMT_NGINX_IMAGE nginx:1.27-alpine 2
    if [ "$ENGINE" = docker ]; then
      compose up -d --no-build --wait --wait-timeout "$TIMEOUT"
    else
      for stage in "${STAGES[@]}"; do
        # shellcheck disable=SC2086  # one word per service
        # (podman's complaints that it cannot reach systemd, for health-check timers and syslog, left out)
        compose up -d --no-deps $stage 2>&1 >/dev/null | { grep -v -E 'systemd connection|connect to syslog' >&2 || true; }
        wait_healthy $stage
      done
    fi
    echo "REST http://127.0.0.1:${GMT_REST_PORT:-8000}  gRPC 127.0.0.1:${GMT_GRPC_PORT:-50051}  (nginx, project $PROJECT)"
    ;;
  down)
    export GMT_AUTH_TOKEN=${GMT_AUTH_TOKEN:-unused} # the file requires one, even to stop
    compose down -v >/dev/null 2>&1 || true
    left=$("$ENGINE" ps -a -q --filter "label=com.docker.compose.project=$PROJECT")
    [ -z "$left" ] || "$ENGINE" rm -f -v $left >/dev/null
    left=$("$ENGINE" ps -a -q --filter "label=com.docker.compose.project=$PROJECT")
    [ -z "$left" ] || { echo "error: containers of $PROJECT left: $left" >&2; exit 1; }
    echo "project $PROJECT: no container left" >&2
    ;;
  *)
    echo "usage: docker/compose.sh up|down" >&2
    exit 2
    ;;
esac
