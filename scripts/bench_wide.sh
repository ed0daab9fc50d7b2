#!/usr/bin/env bash
# Wide baselines on rendered scenes: a robot maps a scene along one route and comes back along
# another; the frames of the second drive (60 s) that see at least a third of what the first (30 s)
# saw, from at least 1.2 m away from every camera of the first, are localized one by one against
# the map built from the first drive (the real-cameras issue's wide-baseline case; scripts/bench_real.sh has the
# real-frame splits W and W2).
#
#   bash scripts/bench_wide.sh OUT_DIR [PNTR_BIN_DIR] [SEEDS]
#
# SEEDS: space-separated scene seeds (default "5 7 11"). Per seed: `pntr synth --seed S
# --route-seed 1|2 --trajectory-seconds 30|60 --query-camera 640x480 --query-hfov 62 --realism robot`,
# `pntr build-db --sequence` of route 1, scripts/shared_view.py to choose route 2's frames, `pntr
# replay --no-prior` of them at 10 frames/s. Prints per seed: queries, LOCALIZED share, recalls
# (5 cm, 5 deg), (0.25 m, 5 deg), (0.25 m, 2 deg), answers more than 0.5 m or 10 deg off, and the
# (0.25 m, 5 deg) recall by distance to the nearest map camera.
set -euo pipefail
OUT=${1:?usage: bench_wide.sh OUT_DIR [PNTR_BIN_DIR] [SEEDS]}
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN=${2:-$ROOT/target/release}
SEEDS=${3:-5 7 11}
PY=${PNTR_PYTHON:-$ROOT/.deps/venv/bin/python}
mkdir -p "$OUT"
for seed in $SEEDS; do
  for route in 1 2; do
    s="$OUT/seed$seed.route$route"
    [ -f "$s/sequences/synth000/groundtruth.txt" ] || "$BIN/pntr" synth --out "$s" --seed "$seed" \
      --points-per-scene 12 --queries-per-point 1 --query-camera 640x480 --query-hfov 62 \
      --trajectory-seconds $((route == 1 ? 30 : 60)) --route-seed "$route" --realism robot >"$s.log" 2>&1
  done
  map="$OUT/seed$seed.pntrmap"
  [ -f "$map" ] || "$BIN/pntr" build-db --sequence "$OUT/seed$seed.route1/sequences/synth000" \
    --out "$map" --json >"$OUT/seed$seed.build.json" 2>"$OUT/seed$seed.build.err"
  q="$OUT/seed$seed.wide"
  [ -f "$q/groundtruth.txt" ] || "$PY" "$ROOT/scripts/shared_view.py" \
    "$OUT/seed$seed.route1/sequences/synth000" "$OUT/seed$seed.route2/sequences/synth000" \
    --out "$OUT/seed$seed.shared.json" --select "$q" --min-shared 0.33 --min-distance-m 1.2 >&2
  if [ "$(grep -vc '^#' "$q/rgb.txt")" = 0 ]; then
    echo "seed $seed: no frame of the second drive is that far from the first and sees that much of it"
    continue
  fi
  rm -f "$OUT/server.txt"
  "$BIN/pntr-server" --db "$map" --addr 127.0.0.1:0 >"$OUT/server.txt" 2>>"$OUT/server.log" &
  server=$!
  until grep -qs listening "$OUT/server.txt"; do kill -0 $server; sleep 0.2; done
  addr=$(awk '{print $4}' "$OUT/server.txt")
  "$BIN/pntr" replay --addr "$addr" --sequence "$q" --no-prior --rate 10 \
    --trajectory "$OUT/seed$seed.txt" --json "$OUT/seed$seed.json" \
    --frames-log "$OUT/seed$seed.frames.jsonl" >/dev/null 2>&1
  kill $server; wait $server 2>/dev/null || true
  "$PY" - "$seed" "$OUT/seed$seed.frames.jsonl" "$OUT/seed$seed.shared.json" <<'PY'
import json, sys
seed, log, shared = sys.argv[1:4]
near = {r["stamp"]: r for r in json.load(open(shared))}
rows = [json.loads(l) for l in open(log)]
n = len(rows)
def err(r):
    ok = r["status"] == "LOCALIZED" and r.get("error_m") is not None
    return (r["error_m"], r["error_deg"]) if ok else None
def rec(rs, m, d):
    return sum(1 for r in rs if (e := err(r)) and e[0] <= m and e[1] <= d) / max(len(rs), 1)
dist = lambda r: near["%.6f" % r["timestamp"]]["distance_m"]
bins = [(1.2, 1.5), (1.5, 2.0), (2.0, 99.0)]
by = " ".join("%.1f-%s m: %d %.2f" % (lo, "" if hi > 50 else "%.1f" % hi, len(b), rec(b, .25, 5))
              for lo, hi in bins for b in [[r for r in rows if lo <= dist(r) < hi]])
loc = sum(r["status"] == "LOCALIZED" for r in rows) / max(n, 1)
wrong = sum(1 for r in rows if (e := err(r)) and (e[0] > .5 or e[1] > 10))
print("seed %-3s n %3d localized %.3f | (5cm,5deg) %.3f (0.25m,5deg) %.3f (0.25m,2deg) %.3f | >0.5m/10deg %d | (0.25m,5deg) by distance: %s"
      % (seed, n, loc, rec(rows, .05, 5), rec(rows, .25, 5), rec(rows, .25, 2), wrong, by))
PY
done
