#!/usr/bin/env bash
# What slow Foxglove viewers cost the robots (BENCHMARKS.md, "Slow Foxglove viewers"): two builds'
# pntr-server --foxglove alternately, each with no viewer and with VIEWERS viewers that subscribe to
# every channel and never read (scripts/stalled_viewer.py), `pntr bench --concurrency 2` against it;
# prints frames/s, latency and the server's resident memory before, at the end and after the viewers left.
#
#   bash scripts/bench_live_view.sh OLD_BIN_DIR NEW_BIN_DIR DATASET MAP [ROUNDS] [VIEWERS]
#
# OLD_BIN_DIR and NEW_BIN_DIR hold `pntr` and `pntr-server` (release builds); DATASET is a dataset in
# the HPointLoc layout whose queries are sent (e.g. `pntr synth --scenes 1 --points-per-scene 12
# --queries-per-point 2 --seed 3`) and MAP its map (`pntr build-db --dataset DATASET`).
set -u
OLD=${1:?usage: bench_live_view.sh OLD_BIN_DIR NEW_BIN_DIR DATASET MAP [ROUNDS] [VIEWERS]}
NEW=${2:?} DATA=${3:?} MAP=${4:?} ROUNDS=${5:-2} VIEWERS=${6:-2}
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY=${PNTR_PYTHON:-$ROOT/.deps/venv/bin/python}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$ROOT/.deps/onnxruntime/libonnxruntime.so.1.31.1}
export OPENVINO_DYLIB_PATH=${OPENVINO_DYLIB_PATH:-$ROOT/.deps/openvino/libopenvino_c.so.2641}
export PNTR_MODELS=${PNTR_MODELS:-$ROOT/models}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
rss() { awk '/VmRSS/{print int($2 / 1024)}' "/proc/$1/status"; }
for r in $(seq 1 "$ROUNDS"); do
  for viewers in 0 "$VIEWERS"; do
    for which in old new; do
      bin=$OLD; [ "$which" = new ] && bin=$NEW
      "$bin/pntr-server" --db "$MAP" --addr 127.0.0.1:0 --metrics-addr 127.0.0.1:0 --workers 2 \
        --foxglove 127.0.0.1:0 > "$TMP/server.txt" 2> "$TMP/server.log" &
      pid=$!
      until grep -qs listening "$TMP/server.txt"; do kill -0 $pid || { cat "$TMP/server.log"; exit 1; }; sleep 0.2; done
      addr=$(awk '{print $4}' "$TMP/server.txt")
      ws=$(grep -o 'ws://[^ ]*' "$TMP/server.txt")
      until "$NEW/pntr" info --addr "$addr" > /dev/null 2>&1; do kill -0 $pid || exit 1; sleep 0.5; done
      vpid=
      if [ "$viewers" -gt 0 ]; then
        "$PY" "$ROOT/scripts/stalled_viewer.py" "$ws" --viewers "$viewers" > "$TMP/viewer.txt" 2>&1 &
        vpid=$!
        until grep -qs subscribed "$TMP/viewer.txt"; do kill -0 $vpid || { cat "$TMP/viewer.txt"; exit 1; }; sleep 0.2; done
      fi
      rss0=$(rss $pid)
      "$NEW/pntr" bench --addr "$addr" --dataset "$DATA" --concurrency 2 --duration 20 --warmup 3 \
        --frames 100 --json "$TMP/bench.json" > /dev/null 2>&1
      rss1=$(rss $pid)
      if [ -n "$vpid" ]; then kill $vpid; wait $vpid 2> /dev/null; fi
      sleep 2
      rss2=$(rss $pid)
      kill $pid; wait $pid 2> /dev/null
      "$PY" - "$TMP/bench.json" "round $r, $viewers viewers, $which" "$rss0" "$rss1" "$rss2" <<'PY'
import json, sys
b = json.load(open(sys.argv[1]))
what, rss0, rss1, rss2 = sys.argv[2], *map(int, sys.argv[3:])
l = b['latency_ms']
print(f"{what}: {b['fps']:.1f} frames/s, p50 {l['p50']:.1f} ms, p99 {l['p99']:.1f} ms; "
      f"RSS {rss0} -> {rss1} MB, {rss2} MB after the viewers left", flush=True)
PY
    done
  done
done
