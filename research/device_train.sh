#!/usr/bin/env bash
# Train on the device machine (one GPU, 16 cores), in one call: set up, measure the CPU beside the GPU, train.
#
# Prepared here (docs/training.md, "On a GPU"):
#   .whl/      the wheels the machine lacks (its python3 has torch, numpy, h5py, scikit-learn, typer, tqdm) and
#              this package's own wheel (`pip wheel --no-deps . -w .whl`)
#   .devdata/  packed datasets (`python -m research.carry_dataset pack ...`), one folder per dataset id leaf
# Run there, both folders carried:
#   REV=<commit> DATASET=gmt/breakout/react-v1 LIMIT=390 bash research/device_train.sh RUN_ARGS_A -- RUN_ARGS_B
# Optional: PACKS (dataset ids to unpack from .devdata/<leaf>, default $DATASET), PREPARE (a command run after
# unpacking, e.g. `python3 -m gmt.datagen.breakout_dagger merge ...`, with `gmt` importable), DATASET_B (run B's
# dataset, default $DATASET).
# REV (the clean commit the wheel was built from) goes into each checkpoint's code_revision.
# Each run is `gmt train --dataset $DATASET --device cuda --time-limit-s $LIMIT --out $OUT/<name> ARGS`, the two
# at once on the one GPU (each is mostly kernel launches at these sizes); the first argument of each is its name.
# Meanwhile `gmt train --device cpu` of the first run's arguments on 12 threads for CPU_STEPS steps gives the
# same machine's CPU figure (CPU_STEPS=0: none). Everything it writes is under $OUT: a log and a tar per run (the tool
# brings back 8 files).
set -u
OUT=${OUT:-/tmp/out}
LIMIT=${LIMIT:-390}
CPU_STEPS=${CPU_STEPS:-30}
DEVICE=${DEVICE:-cuda}          # cpu for a dry run here
WHEELS=${WHEELS:-.whl/*.whl}
log() { echo "[$(date +%T)] $*"; }

log "install"
# shellcheck disable=SC2086
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site $WHEELS || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 GMT_DATA_DIR=$PWD/data/minari GMT_CODE_REVISION=${REV:-unknown}
gmt() { python3 -c 'from gmt.service.cli import main; main()' "$@"; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import gmt, torch; print(gmt.__file__, 'torch', torch.__version__, torch.cuda.is_available() and torch.cuda.get_device_name())" || exit 1

for id in ${PACKS:-$DATASET}; do
  log "unpack $id"
  python3 -m research.carry_dataset unpack ".devdata/${id##*/}" "data/minari/$id" --workers 16 || exit 1
done
if [ -n "${PREPARE:-}" ]; then
  log "prepare: $PREPARE"
  bash -c "$PREPARE" || exit 1
fi

# split "A args -- B args"
A=() B=() side=A
for x in "$@"; do
  if [ "$x" = "--" ]; then side=B; continue; fi
  if [ $side = A ]; then A+=("$x"); else B+=("$x"); fi
done
run() {  # name dataset device threads args...
  local name=$1 ds=$2 dev=$3 th=$4; shift 4
  gmt train --dataset "$ds" --device "$dev" --threads "$th" --out "$OUT/$name" "$@" \
    >"$OUT/$name.log" 2>&1
  log "$name exit $?"
}
log "train"
run "${A[0]}" "$DATASET" "$DEVICE" 2 --time-limit-s "$LIMIT" "${A[@]:1}" &
[ ${#B[@]} -gt 0 ] && run "${B[0]}" "${DATASET_B:-$DATASET}" "$DEVICE" 2 --time-limit-s "$LIMIT" "${B[@]:1}" &
[ "$CPU_STEPS" -gt 0 ] && run cpu-baseline "$DATASET" cpu 12 "${A[@]:1}" --steps "$CPU_STEPS" --log-every 10 &
wait
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader || true
for f in "$OUT"/*.log; do echo "== $f"; tr '\r' '\n' <"$f" | grep -v '^\s*$' | tail -4; done
for d in "$OUT"/*/; do n=$(basename "$d"); tar cf "$OUT/$n.tar" -C "$OUT" "$n" && rm -rf "$d"; done
ls -la "$OUT"
