#!/bin/sh
# Build the C++ Control-stream client: clients/cpp/build.sh [OUT_DIR] (default build/cpp) -> OUT_DIR/control_loop,
# whose path is the last line printed (messages go to stderr). Rebuilt only when its source, the proto, this
# script, the compiler or the gRPC / protobuf versions changed. `build.sh --check` prints the Debian packages this
# machine lacks to build it (nothing: it can be built) and exits 0 when there are none, 1 otherwise.
# Needs a C++17 compiler, pkg-config, protoc with the gRPC C++ plugin, and gRPC's and protobuf's C++ libraries
# (Debian: apt-get install g++ pkg-config protobuf-compiler protobuf-compiler-grpc libgrpc++-dev libprotobuf-dev).
# The message and stub code is generated from proto/gmt/v1/policy.proto into OUT_DIR, never committed.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
cxx=${CXX:-g++}
missing=""
command -v "$cxx" >/dev/null 2>&1 || missing="$missing g++"
command -v pkg-config >/dev/null 2>&1 || missing="$missing pkg-config"
command -v protoc >/dev/null 2>&1 || missing="$missing protobuf-compiler"
command -v grpc_cpp_plugin >/dev/null 2>&1 || missing="$missing protobuf-compiler-grpc"
if command -v pkg-config >/dev/null 2>&1; then
  pkg-config --exists protobuf || missing="$missing libprotobuf-dev"
  pkg-config --exists grpc++ || missing="$missing libgrpc++-dev"
fi
if [ "${1:-}" = "--check" ]; then
  echo "${missing# }"
  [ -z "$missing" ]
  exit
fi
[ -z "$missing" ] || { echo "build.sh: missing; apt-get install${missing}" >&2; exit 1; }
plugin=$(command -v grpc_cpp_plugin)
out=${1:-$root/build/cpp}
mkdir -p "$out"
bin="$out/control_loop"
stamp="$out/control_loop.stamp"
versions="$("$cxx" --version | head -n 1) grpc++ $(pkg-config --modversion grpc++) protobuf $(pkg-config --modversion protobuf)"
if [ -x "$bin" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$versions" ] && [ "$bin" -nt "$here/control_loop.cc" ] \
  && [ "$bin" -nt "$root/proto/gmt/v1/policy.proto" ] && [ "$bin" -nt "$0" ]; then
  echo "$bin"  # up to date
  exit 0
fi
protoc -I "$root/proto" --cpp_out="$out" --grpc_out="$out" --plugin=protoc-gen-grpc="$plugin" \
  "$root/proto/gmt/v1/policy.proto"
# shellcheck disable=SC2046 # pkg-config's flags are separate words
"$cxx" -O2 -std=c++17 -I "$out" "$here/control_loop.cc" "$out/gmt/v1/policy.pb.cc" "$out/gmt/v1/policy.grpc.pb.cc" \
  $(pkg-config --cflags --libs grpc++ protobuf) -o "$bin.$$"
mv "$bin.$$" "$bin"
echo "$versions" > "$stamp"
echo "$bin"
