# Sourced by docker/image.sh, local-images.sh and compose.sh: which container engine runs, and images rebuilt
# only when what they are built from changed.
#
# ENGINE: docker or podman (default: docker if its daemon answers, else podman). With podman, CONTAINERS_CONF
# defaults to docker/podman/containers.conf where runc is installed: runc as the runtime (crun refuses a hybrid
# cgroup setup) and no default ulimits (a sandbox may refuse setrlimit).

DOCKER_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(dirname "$DOCKER_DIR")

if [ -z "${ENGINE:-}" ]; then
  if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then
    ENGINE=docker
  elif command -v podman >/dev/null 2>&1; then
    ENGINE=podman
  else
    echo "error: neither docker nor podman is installed (apt-get install podman runc)" >&2
    exit 1
  fi
fi
if [ "$ENGINE" = podman ] && [ -z "${CONTAINERS_CONF:-}" ] && command -v runc >/dev/null 2>&1; then
  export CONTAINERS_CONF="$DOCKER_DIR/podman/containers.conf"
fi

# has_image NAME: whether the engine holds an image of that name.
has_image() {
  "$ENGINE" image inspect "$1" >/dev/null 2>&1
}

# inputs_hash WORDS... FILES-OR-FOLDERS...: a digest of the words given and of every file's path and content
# under the paths that exist (caches of Python left out).
inputs_hash() {
  local words=() paths=()
  for a in "$@"; do
    if [ -e "$a" ]; then paths+=("$a"); else words+=("$a"); fi
  done
  {
    printf '%s\n' "${words[@]}"
    find "${paths[@]}" -type f -not -path '*/__pycache__/*' -not -name '*.pyc' -print0 | sort -z \
      | xargs -0 sha256sum
  } | sha256sum | cut -c1-16
}

# built_from NAME HASH: whether image NAME exists and was built from inputs with this digest (label gmt.inputs).
built_from() {
  [ "$("$ENGINE" image inspect --format '{{ index .Config.Labels "gmt.inputs" }}' "$1" 2>/dev/null)" = "$2" ]
}

# image_id NAME: the image's id (a base's id is part of what an image on it is built from).
image_id() {
  "$ENGINE" image inspect --format '{{.Id}}' "$1"
}
