#!/bin/sh
# Build the C++ Control-stream client: clients/cpp/build.sh [OUT_DIR] (default build/cpp) -> OUT_DIR/control_loop,
# whose path is the last line printed (messages go to stderr). Rebuilt only when its source, the proto, this
# script, the compiler or the gRPC / protobuf versions changed.
# Needs a C++17 compiler, pkg-config, protoc with the gRPC C++ plugin, and gRPC's and protobuf's C++ libraries
# (Debian: apt-get install g++ pkg-config protobuf-compiler protobuf-compiler-grpc libgrpc++-dev libprotobuf-dev).
# The message and stub code is generated from proto/gmt/v1/policy.proto into OUT_DIR, never committed.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
out=${1:-$root/build/cpp}
cxx=${CXX:-g++}
fail() { echo "build.sh: $*" >&2; exit 1; }
command -v "$cxx" >/dev/null 2>&1 || fail "no C++ compiler '$cxx' (apt-get install g++)"
command -v pkg-config >/dev/null 2>&1 || fail "pkg-config not found (apt-get install pkg-config)"
command -v protoc >/dev/null 2>&1 || fail "protoc not found (apt-get install protobuf-compiler)"
plugin=$(command -v grpc_cpp_plugin) || fail "grpc_cpp_plugin not found (apt-get install protobuf-compiler-grpc)"
pkg-config --exists protobuf || fail "protobuf's C++ library not found (apt-get install libprotobuf-dev)"
pkg-config --exists grpc++ || fail "gRPC's C++ library not found (apt-get install libgrpc++-dev)"
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
