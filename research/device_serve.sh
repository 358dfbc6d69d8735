#!/usr/bin/env bash
# Serving figures on the device machine (one GPU, 16 cores), in one call (issue 58): the GPU parity test on the
# GPU, `gmt bench --sections device` for HalfCheetah and Breakout (the engine and `gmt serve --device cuda`
# against the default CPU path), and `--sections cluster` at 1/2/4/8 replicas on its 16 cores.
#
# Prepared here (docs/performance.md, "On a GPU"):
#   .whl/     the wheels the machine's python3 (3.12, torch, numpy, grpcio's old cousins) lacks or has in other
#             versions, and this package's own wheel (`pip wheel --no-deps --no-build-isolation . -w .whl`)
#   .devbin/  wrk, nginx and redis-server from this machine's Debian packages, each behind a wrapper that
#             points it at its own libraries in .devbin/lib (never exported to python3, whose torch brings its own)
# Run there, both folders carried: `bash research/device_serve.sh`. Everything it writes is under $OUT: one JSON
# and one log per part, and this script's log (the tool brings back 8 files).
# A dry run here: INSTALL=0 DEVICE=cpu HC_SESSIONS=1,4 BO_SESSIONS=1 REPLICAS=1 SECONDS_PER=1 bash research/device_serve.sh
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
DEVICE=${DEVICE:-cuda}
HC_SESSIONS=${HC_SESSIONS:-1,64,256,1024,4096}
BO_SESSIONS=${BO_SESSIONS:-1,16,64}
REPLICAS=${REPLICAS:-1,2,4,8}
SECONDS_PER=${SECONDS_PER:-4}
exec > >(tee "$OUT/device_serve.log") 2>&1
log() { echo "[$(date +%T)] $*"; }

if [ "${INSTALL:-1}" = 1 ]; then
  log "install"
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PATH=$PWD/.devbin/bin:$PATH
GMT="python3 -m gmt.service.cli"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
nproc
python3 -c "import gmt, torch, grpc, fastapi; print(gmt.__file__, 'torch', torch.__version__, 'grpc', grpc.__version__, torch.cuda.is_available() and torch.cuda.get_device_name())" || exit 1
wrk --version | head -1; redis-server --version; nginx -v

part() {  # name limit_s command...: one part, its stderr to $OUT/<name>.log, bounded
  local name=$1 limit=$2; shift 2
  log "$name"
  timeout "$limit" "$@" 2>"$OUT/$name.log" >/dev/null
  log "$name exit $?"
  grep '^\[bench\]' "$OUT/$name.log" | tail -20
}
log "parity test"
python3 -m pytest -q -o addopts="" -p no:cacheprovider --tb=short tests/model/test_device.py 2>&1 | tail -30
part device-halfcheetah 200 $GMT bench --checkpoint checkpoints/halfcheetah-gmt --sections device --device "$DEVICE" \
  --sessions "$HC_SESSIONS" --seconds "$SECONDS_PER" --out "$OUT/device-halfcheetah.json"
part device-breakout 100 $GMT bench --checkpoint checkpoints/breakout-gmt --sections device --device "$DEVICE" \
  --sessions "$BO_SESSIONS" --seconds "$SECONDS_PER" --out "$OUT/device-breakout.json"
part cluster 180 $GMT bench --checkpoint checkpoints/halfcheetah-gmt --sections cluster --replicas "$REPLICAS" \
  --sessions 256 --seconds "$SECONDS_PER" --out "$OUT/cluster.json"
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader || true
ls -la "$OUT"
