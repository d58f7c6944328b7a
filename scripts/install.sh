#!/usr/bin/env bash
# Installs slamreloc and what its tests need into the current Python environment.
# - the system library open3d needs (libusb-1.0) on Debian/Ubuntu, when run as root;
# - torch: a local CPU wheel if this machine ships one (/opt/wheels), else pip's normal choice;
# - the package itself (editable) with its test extras.
set -euo pipefail
PY=${PYTHON:-python3}
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so"; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "warning: libusb-1.0 not found; open3d needs it (apt-get install libusb-1.0-0)" >&2
  fi
fi
if ! $PY -c "import torch" 2>/dev/null; then
  wheel=$(ls /opt/wheels/torch-*+cpu-*.whl 2>/dev/null | head -n1 || true)
  if [ -n "$wheel" ]; then
    $PY -m pip install -q "$wheel" || $PY -m pip install -q "torch>=2.1"
  else
    $PY -m pip install -q "torch>=2.1"
  fi
fi
$PY -m pip install -q -e ".[test]"
# Optional: Debian's chromium for the viewer's browser test (skipped without it).
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "warning: could not install chromium; the viewer's browser test will be skipped" >&2
fi
# Optional: gRPC C++, protobuf, OpenSSL and CMake for the C++ client (clients/cpp; its test is skipped
# without them).
if ! { command -v cmake && command -v g++ && command -v protoc && command -v grpc_cpp_plugin \
        && pkg-config --exists grpc++ protobuf openssl; } >/dev/null 2>&1 \
    && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq cmake g++ \
     pkg-config libgrpc++-dev libprotobuf-dev protobuf-compiler protobuf-compiler-grpc libssl-dev \
     >/dev/null) \
    || echo "warning: could not install gRPC C++ and CMake; the C++ client's test will be skipped" >&2
fi
