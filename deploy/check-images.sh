#!/usr/bin/env bash
# Build the container images of deploy/ for real and check the CPU image's filesystem.
#
#   deploy/check-images.sh             build both Dockerfiles, check, clean up (see deploy/README.md)
#   deploy/check-images.sh --no-cuda   the CPU image only
#   deploy/check-images.sh --keep-build-stage   keep the CUDA build-stage image too (for --checks-only)
#   deploy/check-images.sh --checks-only        no builds: check the images an earlier run left
#   deploy/check-images.sh --clean     remove every image, container and file this script made
#
# What it does (Debian 12 host, root; no container runtime needed, no registry reached):
#   1. installs podman and mmdebstrap from Debian's packages if missing;
#   2. makes the base images the Dockerfiles name, locally, unless they are already in podman's storage:
#      debian:bookworm-slim  with mmdebstrap (minbase, merged /usr, docs/man/locales left out, like the
#                            official slim image), imported as localhost/debian:bookworm-slim;
#      rust:1.95-bookworm    mmdebstrap bookworm with the build tools of buildpack-deps:bookworm that a
#                            build uses (gcc, g++, make, libc6-dev, git, curl, ...: a subset, see the
#                            README) plus this machine's Rust 1.95 toolchain laid out as the official
#                            image does (RUSTUP_HOME=/usr/local/rustup, CARGO_HOME=/usr/local/cargo,
#                            minimal profile), imported as localhost/rust:1.95-bookworm;
#      (where this machine trusts a TLS-inspecting proxy's CA, the rust image trusts it too, pip included);
#   3. `podman build --isolation chroot --pull=never` of deploy/Dockerfile (both stages) and of the build
#      stage of deploy/Dockerfile.cuda (its runtime base, nvidia/cuda, cannot be made here: see below),
#      cold (no cache mounts);
#   4. checks the CPU image: its metadata (user, entrypoint, ports, volume), its files and their shared
#      libraries; then, in a chroot of its filesystem (a container created and mounted, never run), as the
#      image's user with the image's environment: `pntr-server --help`, the server on the demo map (at
#      PNTR_DB=/maps/map.pntrmap, /maps bound read-only as compose.yaml does), gRPC health SERVING, one
#      localization with the image's own `pntr` client, the request counted on /metrics, a clean stop on
#      SIGTERM;
#   5. checks the CUDA build stage's output: the server was built with the `cuda` feature, the GPU ONNX
#      Runtime and its CUDA provider are there (their CUDA/cuDNN libraries listed), and the server, run in
#      a chroot of that stage with PNTR_DEVICE=cuda on this GPU-less machine, falls back to the CPU, serves
#      and localizes;
#   6. removes its containers and the build-stage images (unless --keep-build-stage); keeps the base
#      images and the CPU image (localhost/pntr-server:check) for the next run (`--clean` removes them).
#
# Environment: PNTR_CHECK_WORK (logs and temporary files; default /var/tmp/pntr-check-images),
# PNTR_CHECK_STORAGE (a folder for podman's storage instead of /var/lib/containers/storage),
# PNTR_CHECK_MAP and PNTR_CHECK_DATASET (default: the demo map and dataset in out/demo, `make demo`),
# PNTR_CHECK_MIN_FREE_GB (refuse to start with less free disk; default 8: a build stage peaks at about 5 GB
# in podman's storage; a build is stopped if less than 1 GiB is left).
set -Eeuo pipefail
# Read whole before it runs, so that editing this file during a long build cannot derail the run.
{

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${PNTR_CHECK_WORK:-/var/tmp/pntr-check-images}"
MAP="${PNTR_CHECK_MAP:-$ROOT/out/demo/synth000-xfeat-mnn.pntrmap}"
DATASET="${PNTR_CHECK_DATASET:-$ROOT/out/demo}"
SCENE=synth000
QUERY=0
MIN_FREE_GB="${PNTR_CHECK_MIN_FREE_GB:-8}"
PY="$ROOT/.deps/venv/bin/python"
# Podman's storage: its default (/var/lib/containers/storage), or PNTR_CHECK_STORAGE (e.g. a tmpfs such
# as /dev/shm/pntr-check-images when the disk is short: a build stage peaks at about 5 GB).
STORAGE="${PNTR_CHECK_STORAGE:-}"
PODMAN_OPTS=()
if [ -n "$STORAGE" ]; then
  mkdir -p "$STORAGE/storage" "$STORAGE/run"
  PODMAN_OPTS=(--root "$STORAGE/storage" --runroot "$STORAGE/run")
fi
podman() { command podman "${PODMAN_OPTS[@]}" "$@"; }
STORE_DIR="${STORAGE:-/var/lib/containers}"
# Free space, KiB, where podman stores and in $WORK (the smaller).
free_kib() {
  local a b
  a=$(df --output=avail -k "$STORE_DIR" 2>/dev/null | tail -1 || df --output=avail -k / | tail -1)
  b=$(df --output=avail -k "$WORK" 2>/dev/null | tail -1 || echo "$a")
  echo $((a < b ? a : b))
}
free_gib() { echo $(($(free_kib) / 1024 / 1024)); }
storage_report() {
  echo "podman storage $(du -sh "$(podman info --format '{{.Store.GraphRoot}}')" 2>/dev/null | cut -f1), work $(du -sh "$WORK" 2>/dev/null | cut -f1), free $(free_gib) GiB (storage in $STORE_DIR, work in $WORK)"
}

SLIM=localhost/debian:bookworm-slim
RUST=localhost/rust:1.95-bookworm
RUST_VERSION=1.95.0
CPU_IMAGE=localhost/pntr-server:check
CUDA_BUILD_IMAGE=localhost/pntr-check:cuda-build
CUDA_BASE=nvidia/cuda:13.0.0-cudnn-runtime-ubuntu24.04
STANDIN_LABEL=pntr.check-images.standin
TAG=pntr-check-images   # prefix of the containers this script creates

WITH_CUDA=1
CLEAN=0
KEEP_STAGE=0
CHECKS_ONLY=0
for a in "$@"; do
  case "$a" in
    --no-cuda) WITH_CUDA=0 ;;
    --clean) CLEAN=1 ;;
    --keep-build-stage) KEEP_STAGE=1 ;;
    --checks-only) CHECKS_ONLY=1 KEEP_STAGE=1 ;;
    -h | --help) sed -n '2,/^set -E/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "check-images: unknown argument $a (see --help)" >&2; exit 2 ;;
  esac
done

T0=$(date +%s)
log() { printf '[check-images %s +%ss] %s\n' "$(date +%H:%M:%S)" "$(($(date +%s) - T0))" "$*" >&2; }
die() { log "FAILED: $*"; exit 1; }
trap 'log "FAILED: line $LINENO: \"$BASH_COMMAND\" exited $?"' ERR
RESULTS=()
FAILED=0
pass() { RESULTS+=("PASS  $*"); log "PASS: $*"; }
fail() { RESULTS+=("FAIL  $*"); FAILED=1; log "FAIL: $*"; }
# timed NAME CMD...: run CMD, log its wall time; its status is returned.
timed() {
  local name=$1 t rc=0
  shift
  t=$(date +%s)
  log "$name ..."
  "$@" || rc=$?
  log "$name: $([ $rc -eq 0 ] && echo done || echo "FAILED (exit $rc)") in $(($(date +%s) - t)) s"
  return $rc
}

[ "$(id -u)" -eq 0 ] || die "run as root (podman's chroot builds, mmdebstrap and the chroot checks need it)"

# --- cleanup on any exit: stop servers, unmount, remove this run's containers ----------------------
SERVER_PIDS=()
MOUNTS=()      # mount points to unmount, in order of mounting
CONTAINERS=()  # containers created here (mounted with `podman mount`)
BUILDING=0     # the pid of the `podman build` running, or 0
# An interrupted `podman build --isolation chroot` leaves its RUN step's processes running (chrooted in the
# build's working container) and the working containers in storage: end those processes, by id, and
# remove the working containers.
stop_interrupted_build() {
  local p r graphroot
  graphroot=$(podman info --format '{{.Store.GraphRoot}}')
  if [ "$BUILDING" -gt 0 ] && kill -0 "$BUILDING" 2>/dev/null; then
    log "stopping podman build (pid $BUILDING)"
    kill -TERM "$BUILDING"
    wait "$BUILDING" 2>/dev/null
  fi
  for p in /proc/[0-9]*; do
    r=$(readlink "$p/root" 2>/dev/null) || continue
    case "$r" in "$graphroot"/*/merged) log "ending build process ${p#/proc/} ($(tr '\0' ' ' <"$p/cmdline" | cut -c1-80))"; kill -TERM "${p#/proc/}" 2>/dev/null ;; esac
  done
  sleep 2
  for c in $(podman ps -a --external --format '{{.ID}} {{.Names}}' | awk '$2 ~ /-working-container$/ {print $1}'); do
    podman rm -f "$c" >/dev/null
  done
}
cleanup() {
  local rc=$? i
  set +e
  [ "$BUILDING" -eq 0 ] || stop_interrupted_build
  for pid in "${SERVER_PIDS[@]}"; do
    if kill -0 "$pid" 2>/dev/null; then kill -KILL "$pid" 2>/dev/null; wait "$pid" 2>/dev/null; fi
  done
  for ((i = ${#MOUNTS[@]} - 1; i >= 0; i--)); do
    mountpoint -q "${MOUNTS[i]}" && umount "${MOUNTS[i]}"
  done
  for c in "${CONTAINERS[@]}"; do
    podman umount "$c" >/dev/null 2>&1
    podman rm -f "$c" >/dev/null 2>&1
  done
  exit $rc
}
trap cleanup EXIT
trap 'log "interrupted"; exit 130' INT TERM

image_exists() { podman image exists "$1"; }

if [ "$CLEAN" -eq 1 ]; then
  type -P podman >/dev/null || { log "podman is not installed: nothing to clean"; exit 0; }
  for c in $(podman ps -a --format '{{.Names}}' | grep "^$TAG-" || true); do podman rm -f "$c" >/dev/null; done
  stop_interrupted_build
  for i in "$CUDA_BUILD_IMAGE" "$CPU_IMAGE" "$RUST" "$SLIM"; do
    if image_exists "$i"; then
      if [ "$i" = "$RUST" ] || [ "$i" = "$SLIM" ]; then
        [ -n "$(podman image inspect --format "{{index .Labels \"$STANDIN_LABEL\"}}" "$i")" ] || continue
      fi
      podman rmi -f "$i" >/dev/null && log "removed image $i"
    fi
  done
  podman image prune -f >/dev/null
  rm -rf "$WORK" && log "removed $WORK"
  [ -z "$STORAGE" ] || { rm -rf "$STORAGE"; log "removed $STORAGE"; }
  d=/var/lib/containers
  [ -z "$STORAGE" ] || d=$(dirname "$STORAGE")
  log "free where podman stores: $(df -h --output=avail "$d" | tail -1 | tr -d ' ')"
  exit 0
fi

# --- 1. tools -----------------------------------------------------------------------------------------
if ! type -P podman >/dev/null || ! type -P mmdebstrap >/dev/null; then
  timed "apt: installing podman and mmdebstrap" bash -c \
    'apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends podman mmdebstrap >/dev/null'
fi
log "$(podman --version), mmdebstrap $(mmdebstrap --version | awk '{print $2}'), storage driver $(podman info --format '{{.Store.GraphDriverName}}')"
[ -f "$MAP" ] || die "no map at $MAP: run \`make demo\` (or set PNTR_CHECK_MAP)"
[ -d "$DATASET" ] || die "no dataset at $DATASET: run \`make demo\` (or set PNTR_CHECK_DATASET)"
[ -x "$PY" ] && "$PY" -c 'import grpc' 2>/dev/null \
  || die "$PY with grpcio is missing (the health check uses it): run scripts/setup.sh"
mkdir -p "$WORK/logs" "$WORK/tmp"
# mmdebstrap's root file system and podman's layer blobs while it imports or commits: in $WORK.
export TMPDIR="$WORK/tmp"
log "$(storage_report)"
[ "$(free_gib)" -ge "$MIN_FREE_GB" ] \
  || die "only $(free_gib) GiB free (need ${MIN_FREE_GB}: a build stage holds a release build of the workspace; PNTR_CHECK_STORAGE and PNTR_CHECK_WORK can put podman's storage and the temporary files elsewhere)"

# --- 2. base images -----------------------------------------------------------------------------------
MIRRORS=("deb http://deb.debian.org/debian bookworm main"
  "deb http://deb.debian.org/debian bookworm-updates main"
  "deb http://deb.debian.org/debian-security bookworm-security main")
# As debuerreotype's images: merged /usr without the usrmerge package, no apt translations.
MMDEBSTRAP=(mmdebstrap --mode=root --variant=minbase --format=tar
  --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr
  --aptopt='Acquire::Languages "none"'
  --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/info/*'
  --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-include=/usr/share/doc/*/copyright'
  --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/locale/locale.alias'
  --dpkgopt='path-exclude=/usr/share/groff/*' --dpkgopt='path-exclude=/usr/share/lintian/*'
  --dpkgopt='path-exclude=/usr/share/linda/*')
BASE_PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin

make_slim() {
  "${MMDEBSTRAP[@]}" bookworm - "${MIRRORS[@]}" 2>"$WORK/logs/mmdebstrap-slim.log" \
    | podman import --change 'CMD ["bash"]' --change "ENV PATH=$BASE_PATH" \
      --change "LABEL $STANDIN_LABEL=\"made by deploy/check-images.sh with mmdebstrap (minbase), not the Docker Hub image\"" \
      - "$SLIM" >/dev/null
}

# The toolchain to put in the rust image: this machine's 1.95.
find_toolchain() {
  local sysroot
  sysroot=$(rustup run "$RUST_VERSION" rustc --print sysroot 2>/dev/null || rustc --print sysroot)
  sysroot=$(readlink -f "$sysroot")
  "$sysroot/bin/rustc" --version | grep "^rustc ${RUST_VERSION%.*}\." >/dev/null \
    || die "the Rust toolchain at $sysroot is $("$sysroot/bin/rustc" --version), not $RUST_VERSION"
  echo "$sysroot"
}

make_rust() {
  local toolchain rustup_bin
  toolchain=$(find_toolchain)
  rustup_bin=$(readlink -f "$(command -v rustup)")
  log "rust image: toolchain from $toolchain ($("$toolchain/bin/rustc" --version)), rustup from $rustup_bin"
  # The packages of buildpack-deps:bookworm's curl and scm layers and the compilers and headers of its
  # last layer that a build can use; the image-format and database -dev packages are left out.
  local pkgs=ca-certificates,curl,gnupg,netbase,wget,git,openssh-client,procps,autoconf,automake,bzip2
  pkgs+=,dpkg-dev,file,g++,gcc,libc6-dev,libssl-dev,libtool,make,patch,unzip,xz-utils,zlib1g-dev,python3
  local tc=/usr/local/rustup/toolchains/$RUST_VERSION-x86_64-unknown-linux-gnu
  # A machine that reaches PyPI and crates.io through a TLS-inspecting proxy trusts the proxy's CA (in
  # /usr/local/share/ca-certificates) and points pip at the system's bundle (pip has its own otherwise):
  # so does this build image, or the build stage could not download. The runtime base gets none of it.
  local ca_hooks=()
  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    log "rust image: adding this machine's extra CA certificates: $(cd /usr/local/share/ca-certificates && echo *.crt)"
    ca_hooks=(--customize-hook='cp /usr/local/share/ca-certificates/*.crt "$1/usr/local/share/ca-certificates/"'
      --customize-hook='chroot "$1" update-ca-certificates'
      --customize-hook='printf "[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n" >"$1/etc/pip.conf"')
  fi
  "${MMDEBSTRAP[@]}" --include="$pkgs" "${ca_hooks[@]}" \
    --customize-hook="mkdir -p \"\$1$tc\" \"\$1/usr/local/cargo/bin\"" \
    --customize-hook="cp -a '$toolchain/.' \"\$1$tc/\"" \
    --customize-hook="install -m 0755 '$rustup_bin' \"\$1/usr/local/cargo/bin/rustup\"" \
    --customize-hook="for p in cargo cargo-clippy cargo-fmt cargo-miri clippy-driver rls rust-analyzer rust-gdb rust-gdbgui rust-lldb rustc rustdoc rustfmt; do ln \"\$1/usr/local/cargo/bin/rustup\" \"\$1/usr/local/cargo/bin/\$p\"; done" \
    --customize-hook="chroot \"\$1\" env RUSTUP_HOME=/usr/local/rustup CARGO_HOME=/usr/local/cargo PATH=/usr/local/cargo/bin:$BASE_PATH sh -ec 'rustup set profile minimal; rustup default $RUST_VERSION-x86_64-unknown-linux-gnu; for c in rust-docs clippy rustfmt; do rustup component remove \$c 2>/dev/null || true; done; rustup --version; cargo --version; rustc --version'" \
    --customize-hook="chmod -R a+w \"\$1/usr/local/rustup\" \"\$1/usr/local/cargo\"" \
    bookworm - "${MIRRORS[@]}" 2>"$WORK/logs/mmdebstrap-rust.log" \
    | podman import --change 'CMD ["bash"]' \
      --change "ENV RUSTUP_HOME=/usr/local/rustup" --change "ENV CARGO_HOME=/usr/local/cargo" \
      --change "ENV PATH=/usr/local/cargo/bin:$BASE_PATH" --change "ENV RUST_VERSION=$RUST_VERSION" \
      --change "LABEL $STANDIN_LABEL=\"made by deploy/check-images.sh: mmdebstrap bookworm + build tools + this machine's Rust $RUST_VERSION (and extra CAs), not the Docker Hub image\"" \
      - "$RUST" >/dev/null
}

for pair in "$SLIM:make_slim" "$RUST:make_rust"; do
  img=${pair%:*} fn=${pair##*:}
  if image_exists "$img"; then
    log "base image $img present ($(podman image inspect --format '{{.Size}}' "$img" | numfmt --to=iec)); kept"
  else
    timed "base image $img (mmdebstrap, podman import; log in $WORK/logs)" "$fn" \
      || { tail -n 30 "$WORK"/logs/mmdebstrap-*.log >&2; die "could not make $img"; }
  fi
done
# One ENV per variable (podman import takes `ENV a=1 b=2` as one variable).
podman image inspect --format '{{range .Config.Env}}{{println .}}{{end}}' "$RUST" | grep -x 'CARGO_HOME=/usr/local/cargo' >/dev/null \
  || die "$RUST lacks CARGO_HOME=/usr/local/cargo: remove it (podman rmi $RUST) and run again"

# --- 3. builds ----------------------------------------------------------------------------------------
# No build-time volumes (-v): podman leaves their mount points (empty folders and files) in every stage's
# layers, the runtime image's too; so no cache mounts either, each build starts cold as `docker build` does.
BUILD=(podman build --isolation chroot --pull=never --layers --force-rm)

build_log() {
  local logf=$1
  shift
  log "  ${*} (output: $logf)"
  # In the background, so that a signal to this script is handled at once (bash runs traps only
  # between foreground commands).
  # Stopped if the disk nearly fills (the machine is shared): under 1 GiB free.
  "$@" >"$logf" 2>&1 &
  BUILDING=$!
  while kill -0 "$BUILDING" 2>/dev/null; do
    if [ "$(free_kib)" -lt 1048576 ]; then
      log "less than 1 GiB free: stopping the build"
      stop_interrupted_build
      BUILDING=0
      return 1
    fi
    sleep 5
  done
  wait "$BUILDING" || { BUILDING=0; tail -n 40 "$logf" >&2; return 1; }
  BUILDING=0
  grep -E '^(STEP|COMMIT|-->)' "$logf" | tail -n 3 >&2 || true
}
if [ "$CHECKS_ONLY" -eq 1 ]; then
  image_exists "$CPU_IMAGE" || die "--checks-only: no $CPU_IMAGE to check"
  log "--checks-only: checking the $CPU_IMAGE built $(podman image inspect --format '{{.Created}}' "$CPU_IMAGE")"
else
  timed "podman build -f deploy/Dockerfile -t $CPU_IMAGE" \
    build_log "$WORK/logs/build-cpu.log" "${BUILD[@]}" -f "$ROOT/deploy/Dockerfile" -t "$CPU_IMAGE" "$ROOT" \
    || die "the CPU image did not build (log: $WORK/logs/build-cpu.log)"
  image_exists "$CPU_IMAGE" || die "podman build ended without $CPU_IMAGE (killed from outside?); log: $WORK/logs/build-cpu.log"
fi
pass "CPU image builds (deploy/Dockerfile, both stages): $CPU_IMAGE, $(podman image inspect --format '{{.Size}}' "$CPU_IMAGE" | numfmt --to=iec)"

# --- 4. checks ----------------------------------------------------------------------------------------
free_port() { "$PY" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

# mount_rootfs IMAGE NAME: create (never start) a container of IMAGE and mount it at $ROOTFS.
ROOTFS=""
mount_rootfs() {
  local c="$TAG-$2" m
  podman rm -f "$c" >/dev/null 2>&1 || true
  podman create --name "$c" "$1" >/dev/null
  CONTAINERS+=("$c")
  m=$(podman mount "$c")
  [ -d "$m/etc" ] || die "podman mount $c gave '$m'"
  # What a container runtime would give the process: /proc, /sys (read-only), /dev.
  mount -t proc proc "$m/proc"
  MOUNTS+=("$m/proc")
  mount -t sysfs -o ro sysfs "$m/sys"
  MOUNTS+=("$m/sys")
  mount --bind /dev "$m/dev"
  MOUNTS+=("$m/dev")
  ROOTFS=$m
}

# bind_ro SRC DEST: a read-only bind mount.
bind_ro() {
  mountpoint -q "$2" && return 0
  mkdir -p "$2"
  mount --bind "$1" "$2"
  MOUNTS+=("$2")
  mount -o remount,bind,ro "$2"
}

# The gRPC health check (grpc.health.v1.Health/Check) with grpcio, no generated code: the request is
# HealthCheckRequest{service}, the answer HealthCheckResponse{status} (field 1, SERVING = 1).
HEALTH_PY='
import os, sys, time, grpc
addr, service, pid, limit = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
name = service.encode()
req = (b"\x0a" + bytes([len(name)]) + name) if name else b""
check = grpc.insecure_channel(addr).unary_unary("/grpc.health.v1.Health/Check")
names = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}
start, last = time.time(), "no answer"
while time.time() - start < limit:
    if not os.path.exists(f"/proc/{pid}"):
        sys.exit(f"the server exited (last health answer: {last})")
    try:
        r = check(req, timeout=2)
        status = r[1] if len(r) >= 2 and r[0] == 0x08 else 0
        last = names.get(status, str(status))
        if status == 1:
            print(f"health({service!r}) = SERVING after {time.time() - start:.1f} s")
            sys.exit(0)
    except grpc.RpcError as e:
        last = str(e.code())
    time.sleep(0.25)
sys.exit(f"not SERVING after {limit:.0f} s (last answer: {last})")
'

# The localization must be LOCALIZED, close to the ground truth (the demo query 0 is within 2 cm).
LOCALIZED_PY='
import json, sys
r = json.load(sys.stdin)
gt = r.get("ground_truth") or {}
err = gt.get("translation_error_m")
print("status=%s confidence=%.3f inliers=%s translation_error_m=%s rotation_error_deg=%s total_ms=%s" % (
    r["status"], r["confidence"], r["inliers"], err, gt.get("rotation_error_deg"), r["stage_ms"].get("total")))
sys.exit(0 if r["status"] == "LOCALIZED" and err is not None and err < 0.25 else 1)
'

METRICS_PY='
import re, sys, urllib.request
text = urllib.request.urlopen(f"http://{sys.argv[1]}/metrics", timeout=10).read().decode()
ok = [l for l in text.splitlines() if re.match(r"pntr_requests_total\{[^}]*code=\"OK\"", l)]
n = sum(float(l.rsplit(" ", 1)[1]) for l in ok)
print("pntr_requests_total{code=\"OK\"} = %g" % n)
sys.exit(0 if n >= 1 else 1)
'

# serve_and_check LABEL ROOTFS USERSPEC CLIENT_ROOTFS ENV...: start the image's entrypoint in a chroot of
# ROOTFS as USERSPEC with exactly ENV (plus loopback addresses), wait for health SERVING, localize one demo
# query with the `pntr` client of CLIENT_ROOTFS (the dataset bound read-only at /mnt/pntr-demo there),
# scrape /metrics, stop with SIGTERM. Checks recorded under LABEL.
SERVER_LOG=""
serve_and_check() {
  local label=$1 rootfs=$2 userspec=$3 client_rootfs=$4 entry=$5
  shift 5
  local env=("$@") gport mport pid out out2="" summary=""
  gport=$(free_port)
  mport=$(free_port)
  SERVER_LOG="$WORK/logs/server-$label.log"
  env=("${env[@]}" "PNTR_ADDR=127.0.0.1:$gport" "PNTR_METRICS_ADDR=127.0.0.1:$mport")
  log "$label: starting $entry in a chroot of $rootfs as $userspec on 127.0.0.1:$gport (metrics :$mport); log $SERVER_LOG"
  env -i "${env[@]}" chroot --userspec="$userspec" "$rootfs" "$entry" >"$SERVER_LOG" 2>&1 &
  pid=$!
  SERVER_PIDS+=("$pid")
  local t=$(date +%s)
  if out=$("$PY" -c "$HEALTH_PY" "127.0.0.1:$gport" "" "$pid" 180 2>&1) \
    && out2=$("$PY" -c "$HEALTH_PY" "127.0.0.1:$gport" pntr.v1.Localizer "$pid" 10 2>&1); then
    pass "$label: gRPC health SERVING ($out; $out2)"
  else
    fail "$label: gRPC health: $out $out2"
    tail -n 20 "$SERVER_LOG" >&2
    kill -KILL "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
    return 0
  fi
  bind_ro "$DATASET" "$client_rootfs/mnt/pntr-demo"
  if out=$(env -i "${env[@]}" chroot --userspec="$userspec" "$client_rootfs" /usr/local/bin/pntr localize \
    --addr "127.0.0.1:$gport" --dataset /mnt/pntr-demo --scene "$SCENE" --query "$QUERY" --json 2>&1) \
    && summary=$(printf '%s' "$out" | "$PY" -c "$LOCALIZED_PY" 2>&1); then
    pass "$label: localize $SCENE query $QUERY through the server: $summary"
  else
    fail "$label: localize $SCENE query $QUERY: ${summary:-$out}"
  fi
  if out=$("$PY" -c "$METRICS_PY" "127.0.0.1:$mport" 2>&1); then
    pass "$label: /metrics counts the request: $out"
  else
    fail "$label: /metrics: $out"
  fi
  kill -TERM "$pid" 2>/dev/null || true
  local src=0
  wait "$pid" || src=$?
  if [ "$src" -eq 0 ] && grep -q "stopped" "$SERVER_LOG"; then
    pass "$label: stops cleanly on SIGTERM (exit 0); served $(($(date +%s) - t)) s"
  else
    fail "$label: exit status $src after SIGTERM"
  fi
}

check_cpu_image() {
  local img=$CPU_IMAGE m user entry gid="" home=""
  user=$(podman image inspect --format '{{.Config.User}}' "$img")
  entry=$(podman image inspect --format '{{range .Config.Entrypoint}}{{.}} {{end}}' "$img" | sed 's/ $//')
  local ports volumes
  ports=$(podman image inspect --format '{{range $p, $v := .Config.ExposedPorts}}{{$p}} {{end}}' "$img")
  volumes=$(podman image inspect --format '{{range $p, $v := .Config.Volumes}}{{$p}} {{end}}' "$img")
  mapfile -t ENV < <(podman image inspect --format '{{range .Config.Env}}{{println .}}{{end}}' "$img" | sed '/^$/d')
  log "image config: user=$user entrypoint=[$entry] ports=[$ports] volumes=[$volumes]"
  printf '    %s\n' "${ENV[@]}" >&2
  if [ "$user" = 10001 ] && [ "$entry" = /usr/local/bin/pntr-server ] \
    && [[ " $ports" == *" 50051/tcp "* ]] && [[ " $ports" == *" 9464/tcp "* ]] && [ "$volumes" = "/maps " ]; then
    pass "CPU image config: USER 10001, ENTRYPOINT pntr-server, ports 50051 and 9464, volume /maps"
  else
    fail "CPU image config: user=$user entrypoint=$entry ports=$ports volumes=$volumes"
  fi
  getenv() { printf '%s\n' "${ENV[@]}" | sed -n "s/^$1=//p"; }
  mount_rootfs "$img" cpu
  m=$ROOTFS
  CPU_ROOTFS=$m
  log "CPU image filesystem mounted at $m"
  # Files, and that the build stage did not leak into the runtime image.
  local missing=()
  for f in /usr/local/bin/pntr-server /usr/local/bin/pntr "$(getenv ORT_DYLIB_PATH)" "$(getenv OPENVINO_DYLIB_PATH)" \
    "$(getenv PNTR_MODELS)"/{xfeat_backbone.onnx,xfeat_backbone_int8.onnx,lighterglue.onnx,aliked_n16.onnx,README.md}; do
    [ -f "$m$f" ] || missing+=("$f")
  done
  for f in /src /usr/local/cargo /usr/bin/gcc /usr/bin/cc; do [ ! -e "$m$f" ] || missing+=("$f (should not be there)"); done
  if [ ${#missing[@]} -eq 0 ]; then
    pass "CPU image files: pntr-server, pntr, $(getenv ORT_DYLIB_PATH), $(getenv OPENVINO_DYLIB_PATH), models; no build stage, compiler or toolchain"
  else
    fail "CPU image files: ${missing[*]}"
  fi
  # Shared libraries of the binaries and of ONNX Runtime (loaded at run time with dlopen) all resolve.
  local nf
  local ov_dir ov_libs=()
  ov_dir=$(dirname "$(getenv OPENVINO_DYLIB_PATH)")
  for f in "$m$ov_dir"/lib*.so*; do [ -f "$f" ] && ov_libs+=("${f#"$m"}"); done
  nf=$(for f in /usr/local/bin/pntr-server /usr/local/bin/pntr "$(getenv ORT_DYLIB_PATH)" "${ov_libs[@]}"; do
    chroot "$m" /usr/bin/ldd "$f" | grep 'not found' | sed "s#^#$f: #"
  done || true)
  [ -z "$nf" ] && pass "CPU image: every shared library of pntr-server, pntr, ONNX Runtime and OpenVINO resolves (ldd)" \
    || fail "CPU image: unresolved libraries: $nf"
  # The image's user.
  local uid=$user
  IFS=: read -r _ _ _ gid _ home _ < <(awk -F: -v u="$uid" '$3 == u' "$m/etc/passwd") || true
  [ -n "${gid:-}" ] || { fail "CPU image: no /etc/passwd entry for uid $uid"; return 0; }
  [ "$(stat -c %u "$m/maps")" = "$uid" ] && pass "CPU image: /maps belongs to uid $uid (gid $gid)" \
    || fail "CPU image: /maps belongs to uid $(stat -c %u "$m/maps"), not $uid"
  ENV+=("HOME=$home")
  # --help as the image's user.
  local out
  if out=$(env -i "${ENV[@]}" chroot --userspec="$uid:$gid" "$m" "$entry" --help 2>&1) \
    && grep -q '^Usage: pntr-server' <<<"$out"; then
    pass "CPU image: pntr-server --help runs in a chroot as $uid:$gid ($(grep -c -- '^ *--' <<<"$out") options listed)"
  else
    fail "CPU image: pntr-server --help: $out"
  fi
  # The demo map at the image's PNTR_DB, in a folder bound read-only on /maps (as compose.yaml mounts ../maps).
  local db
  db=$(getenv PNTR_DB)
  [ "$(dirname "$db")" = /maps ] || { fail "CPU image: PNTR_DB=$db is not in the /maps volume"; return 0; }
  mkdir -p "$WORK/maps"
  install -m 0644 "$MAP" "$WORK/maps/$(basename "$db")"
  bind_ro "$WORK/maps" "$m/maps"
  log "demo map $MAP ($(du -h "$MAP" | cut -f1)) at $db, /maps bound read-only"
  serve_and_check cpu "$m" "$uid:$gid" "$m" "$entry" "${ENV[@]}"
}
CPU_ROOTFS=""
t=$(date +%s)
log "checks of $CPU_IMAGE ..."
check_cpu_image
log "checks of $CPU_IMAGE: done in $(($(date +%s) - t)) s"

# --- 5. CUDA image ------------------------------------------------------------------------------------
check_cuda_build() {
  local m f
  mount_rootfs "$CUDA_BUILD_IMAGE" cuda-build
  m=$ROOTFS
  log "CUDA build stage mounted at $m; /out:"
  (cd "$m/out" && find . -type f -printf '    %p %s\n' | sort >&2)
  local missing=()
  for f in pntr-server lib/libonnxruntime.so.1.31.1 lib/libonnxruntime_providers_shared.so \
    lib/libonnxruntime_providers_cuda.so models/xfeat_backbone.onnx models/lighterglue.onnx models/aliked_n16.onnx; do
    [ -f "$m/out/$f" ] || missing+=("$f")
  done
  [ ${#missing[@]} -eq 0 ] && pass "CUDA build stage: /out has pntr-server, the onnxruntime-gpu 1.31.1 library, its CUDA provider, the models" \
    || fail "CUDA build stage: missing in /out: ${missing[*]}"
  if grep -q "CUDA execution provider unavailable" "$m/out/pntr-server" \
    && ! grep -q 'built without the `cuda` feature' "$m/out/pntr-server"; then
    pass "CUDA build stage: pntr-server is built with the cuda feature"
  else
    fail "CUDA build stage: pntr-server is not built with the cuda feature"
  fi
  if [ -f "$m/out/lib/libonnxruntime_providers_cuda.so" ]; then
    local needed
    needed=$(chroot "$m" readelf -d /out/lib/libonnxruntime_providers_cuda.so | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p' \
      | grep -E 'cu|nv' | tr '\n' ' ')
    log "the CUDA provider needs (from $CUDA_BASE, absent here): $needed"
    RESULTS+=("INFO  the CUDA provider links: $needed")
  fi
  # The GPU build of the server on this GPU-less machine: asks for CUDA, falls back to the CPU, serves.
  # As root in the build stage's filesystem (its runtime stage cannot be built); the client is the CPU image's.
  [ -n "$CPU_ROOTFS" ] || { fail "CUDA build stage: no CPU image filesystem for the client"; return 0; }
  install -m 0644 "$MAP" "$m/tmp/map.pntrmap"
  serve_and_check cuda-build-stage "$m" 0:0 "$CPU_ROOTFS" /out/pntr-server \
    PATH="$BASE_PATH" HOME=/root ORT_DYLIB_PATH=/out/lib/libonnxruntime.so.1.31.1 LD_LIBRARY_PATH=/out/lib \
    PNTR_MODELS=/out/models PNTR_DEVICE=cuda PNTR_DB=/tmp/map.pntrmap PNTR_LOG=info
  if grep -q "CUDA execution provider unavailable; running on the CPU" "$SERVER_LOG"; then
    # The server's log carries ANSI colours between a field's name and its value: strip them first.
    pass "CUDA build stage: PNTR_DEVICE=cuda without a GPU falls back to the CPU: $(sed 's/\x1b\[[0-9;]*m//g' "$SERVER_LOG" | grep -m1 -o 'error=.*' | cut -c1-200 || true)"
  else
    fail "CUDA build stage: no CPU fallback message in $SERVER_LOG"
  fi
}

if [ "$WITH_CUDA" -eq 1 ] && [ "$CHECKS_ONLY" -eq 0 ]; then
  # The CPU build stage's layers are not needed any more; the CUDA build stage needs the room.
  podman image prune -f >/dev/null
  log "removed the CPU build-stage layers before the CUDA build: $(free_gib) GiB free"
fi
if [ "$WITH_CUDA" -eq 1 ] && [ "$(free_gib)" -lt 6 ] && ! { [ "$CHECKS_ONLY" -eq 1 ] && image_exists "$CUDA_BUILD_IMAGE"; }; then
  fail "CUDA image build stage not built: $(free_gib) GiB free, it needs about 6"
elif [ "$WITH_CUDA" -eq 1 ]; then
  if { [ "$CHECKS_ONLY" -eq 1 ] && image_exists "$CUDA_BUILD_IMAGE" || timed "podman build --target build -f deploy/Dockerfile.cuda -t $CUDA_BUILD_IMAGE" \
    build_log "$WORK/logs/build-cuda.log" "${BUILD[@]}" --target build -f "$ROOT/deploy/Dockerfile.cuda" \
    -t "$CUDA_BUILD_IMAGE" "$ROOT"; } && image_exists "$CUDA_BUILD_IMAGE"; then
    pass "CUDA image build stage builds (deploy/Dockerfile.cuda --target build)"
    t=$(date +%s)
    check_cuda_build
    log "checks of the CUDA build stage: done in $(($(date +%s) - t)) s"
  else
    fail "CUDA image build stage (log: $WORK/logs/build-cuda.log)"
  fi
  msg="CUDA runtime stage not built: its base $CUDA_BASE is NVIDIA's CUDA 13 + cuDNN 9 runtime on Ubuntu 24.04; Docker Hub, nvcr.io and NVIDIA's apt repository are out of reach here, and a look-alike made from other packages would not be that image"
  RESULTS+=("SKIP  $msg")
  log "SKIPPED: $msg"
else
  RESULTS+=("SKIP  CUDA image (--no-cuda)")
fi

# --- 6. clean up: this run's containers (trap), build-stage images; keep the bases and the CPU image --------
cleanup_images() {
  local c
  for ((i = ${#MOUNTS[@]} - 1; i >= 0; i--)); do
    if mountpoint -q "${MOUNTS[i]}"; then umount "${MOUNTS[i]}"; fi
  done
  MOUNTS=()
  for c in "${CONTAINERS[@]}"; do
    podman umount "$c" >/dev/null 2>&1 || true
    podman rm -f "$c" >/dev/null
  done
  CONTAINERS=()
  if [ "$KEEP_STAGE" -eq 0 ]; then
    ! image_exists "$CUDA_BUILD_IMAGE" || podman rmi -f "$CUDA_BUILD_IMAGE" >/dev/null
    podman image prune -f >/dev/null
  else
    log "--keep-build-stage: $CUDA_BUILD_IMAGE kept"
  fi
}
t=$(date +%s)
cleanup_images
log "removed this run's containers and build-stage images in $(($(date +%s) - t)) s"
log "images kept:"
podman images --format '    {{.Repository}}:{{.Tag}} {{.Size}}' >&2
log "$(storage_report)"

echo
echo "deploy/check-images.sh: $(date -u +%FT%TZ), $(nproc) CPUs, wall time $(($(date +%s) - T0)) s"
printf '  %s\n' "${RESULTS[@]}"
if [ "$FAILED" -ne 0 ]; then
  echo "RESULT: FAILED (logs in $WORK/logs)"
  exit 1
fi
echo "RESULT: PASSED"
exit 0
}
