#!/usr/bin/env sh
# Build the C++ Control-stream client: clients/cpp/build.sh [OUT_DIR] (default build/cpp) -> OUT_DIR/control_loop.
# Needs a C++17 compiler, protoc with the gRPC C++ plugin, and gRPC's C++ library
# (Debian: apt-get install g++ pkg-config protobuf-compiler protobuf-compiler-grpc libgrpc++-dev).
# The message and stub code is generated from proto/gmt/v1/policy.proto into OUT_DIR, never committed.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
out=${1:-$root/build/cpp}
mkdir -p "$out"
bin="$out/control_loop"
if [ -x "$bin" ] && [ "$bin" -nt "$here/control_loop.cc" ] && [ "$bin" -nt "$root/proto/gmt/v1/policy.proto" ] \
  && [ "$bin" -nt "$0" ]; then
  echo "$bin"  # up to date
  exit 0
fi
plugin=$(command -v grpc_cpp_plugin) || { echo "build.sh: grpc_cpp_plugin not found (apt-get install protobuf-compiler-grpc)" >&2; exit 1; }
pkg-config --exists grpc++ protobuf || { echo "build.sh: gRPC's C++ library not found (apt-get install libgrpc++-dev)" >&2; exit 1; }
protoc -I "$root/proto" --cpp_out="$out" --grpc_out="$out" --plugin=protoc-gen-grpc="$plugin" "$root/proto/gmt/v1/policy.proto"
# shellcheck disable=SC2046 # pkg-config's flags are separate words
${CXX:-g++} -O2 -std=c++17 -I "$out" "$here/control_loop.cc" "$out/gmt/v1/policy.pb.cc" \
  "$out/gmt/v1/policy.grpc.pb.cc" $(pkg-config --cflags --libs grpc++ protobuf) -o "$bin.tmp"
mv "$bin.tmp" "$bin"
echo "$bin"
