#!/usr/bin/env bash
# Real recordings in pntr's own benchmark: 7-Scenes frames (a Kinect: 640x480 colour, depth from a
# separate depth camera, poses from the dataset's reconstruction) built into maps and localized the
# way the docs say (docs/mapping.md, "A real RGB-D sensor").
#
#   bash scripts/bench_real.sh SEVEN_SCENES_DIR OUT_DIR [PNTR_BIN_DIR]
#
# SEVEN_SCENES_DIR holds frame-NNNNNN.color.jpg|png, .depth.png, .pose.txt (and camera-intrinsics.txt)
# with frames 0-499 at least, e.g. the data/ folder of the public repository andyzeng/tsdf-fusion-python
# (7-Scenes redkitchen; Microsoft's licence: non-commercial use only, never commit the frames). Nothing
# is fetched here. Frames 500 and later are never read: they are the held-out measure.
#
# Splits: A = map of frames 0-249, queries 250-499; B = the reverse; W = a map of frames 0-149 and the
# 50 queries among 250-499 farthest from every map camera (they share 1-9% of their view with it:
# the right answer is a refusal); W2 = a map of frames 350-499 and the queries among 0-249 that share
# at least a quarter of their view with one of its frames from at least 1 m away from every one of
# its cameras (scripts/shared_view.py; the widest baseline with a shared view that frames 0-499
# hold). Each map is built from a TUM RGB-D folder (depth registered to colour by
# scripts/sevenscenes_to_tum.py with the Kinect's translation offset), the A map also straight from the 7-Scenes layout (`--depth-to-colour`), which
# must agree. Queries go through `pntr replay` at 20 frames/s, each frame alone (--no-prior) and as
# one stream (tracking). Prints one line per run: localized share, recalls at (5 cm, 5 deg),
# (10 cm, 5 deg), (0.25 m, 2 deg), (0.25 m, 5 deg: the wide-baseline bar), median errors, answers
# more than 0.5 m or 10 deg off, latency; and a second line for the frames that share at least 30%
# of their view with some frame of the map's recording (scripts/shared_view.py): on these splits
# the camera leaves what the map saw, and that line separates the pipeline's accuracy from coverage.
set -euo pipefail
SRC=${1:?usage: bench_real.sh SEVEN_SCENES_DIR OUT_DIR [PNTR_BIN_DIR]}
OUT=${2:?usage: bench_real.sh SEVEN_SCENES_DIR OUT_DIR [PNTR_BIN_DIR]}
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN=${3:-$ROOT/target/release}
PY=${PNTR_PYTHON:-$ROOT/.deps/venv/bin/python}
K=525,525,320,240
OFFSET=-0.0256,0.0001,0.0020
for f in 0 499; do
  [ -f "$SRC/$(printf frame-%06d.pose.txt $f)" ] || { echo "$SRC: no frame $f (need frames 0-499 in the 7-Scenes layout)" >&2; exit 2; }
done
mkdir -p "$OUT"
tum() { # first last name
  [ -f "$OUT/$3/groundtruth.txt" ] || "$PY" "$ROOT/scripts/sevenscenes_to_tum.py" "$SRC" "$OUT/$3" --first "$1" --last "$2" >/dev/null
}
tum 0 249 tum_0_249
tum 250 499 tum_250_499
tum 0 149 tum_0_149
# The 7-Scenes layout itself for split A (links, so nothing is copied).
for r in 0_249:0:249 250_499:250:499; do
  IFS=: read -r name first last <<<"$r"
  d="$OUT/7scenes_$name"; mkdir -p "$d"; cp -f "$SRC/camera-intrinsics.txt" "$d/" 2>/dev/null || true
  for i in $(seq "$first" "$last"); do
    for s in color.jpg color.png depth.png pose.txt; do
      f="$SRC/$(printf frame-%06d $i).$s"; [ -f "$f" ] && ln -sf "$(realpath "$f")" "$d/"
    done
  done
done
# W: the 50 queries among 250-499 farthest from every camera of frames 0-149.
if [ ! -f "$OUT/tum_wide/groundtruth.txt" ]; then
  frames=$("$PY" - "$SRC" <<'PY'
import sys, numpy as np
src = sys.argv[1]
pos = lambda i: np.loadtxt("%s/frame-%06d.pose.txt" % (src, i))[:3, 3]
fwd = lambda i: np.loadtxt("%s/frame-%06d.pose.txt" % (src, i))[:3, 2]
m = [(pos(i), fwd(i)) for i in range(150)]
def gap(j):
    p, f = pos(j), fwd(j)
    return min(np.linalg.norm(p - mp) + 0.02 * np.degrees(np.arccos(np.clip(f @ mf, -1, 1))) for mp, mf in m)
far = sorted(range(250, 500), key=gap)[-50:]
print(",".join(str(i) for i in sorted(far)))
PY
)
  "$PY" "$ROOT/scripts/sevenscenes_to_tum.py" "$SRC" "$OUT/tum_wide" --frames "$frames" >/dev/null
fi

# W2: the queries of 0-249 that see a quarter of what frames 350-499 saw, from 1 m or more.
tum 350 499 tum_350_499
[ -f "$OUT/tum_wide2/groundtruth.txt" ] || "$PY" "$ROOT/scripts/shared_view.py" "$OUT/tum_350_499" "$OUT/tum_0_249" \
  --intrinsics $K --out "$OUT/wide2.shared.json" --select "$OUT/tum_wide2" --min-shared 0.25 --min-distance-m 1.0 >&2
[ -f "$OUT/wide.shared.json" ] || "$PY" "$ROOT/scripts/shared_view.py" "$OUT/tum_0_149" "$OUT/tum_wide" \
  --intrinsics $K --out "$OUT/wide.shared.json"

serve() { # map -> sets ADDR and SERVER
  rm -f "$OUT/server.txt"
  "$BIN/pntr-server" --db "$1" --addr 127.0.0.1:0 >"$OUT/server.txt" 2>>"$OUT/server.log" &
  SERVER=$!
  until grep -qs listening "$OUT/server.txt"; do kill -0 $SERVER; sleep 0.2; done
  ADDR=$(awk '{print $4}' "$OUT/server.txt")
}
summary() { # tag json shared.json
  "$PY" - "$1" "$2" "$3" <<'PY'
import json, sys
tag, path, shared_path = sys.argv[1], sys.argv[2], sys.argv[3]
r = json.load(open(path))
rows = [json.loads(l) for l in open(path.replace(".json", ".frames.jsonl"))]
def line(rows):
    n = len(rows)
    err = [(x["error_m"], x["error_deg"]) for x in rows if x.get("error_m") is not None]
    rec = lambda m, d: sum(1 for e in err if e[0] <= m and e[1] <= d) / max(n, 1)
    med = lambda v: sorted(v)[len(v) // 2] if v else float("nan")
    return ("n %3d localized %.3f | (5cm,5deg) %.3f (10cm,5deg) %.3f (0.25m,2deg) %.3f (0.25m,5deg) %.3f | median %.1f cm %.2f deg | >0.5m/10deg %d"
            % (n, sum(x["status"] == "LOCALIZED" for x in rows) / max(n, 1), rec(.05, 5), rec(.10, 5), rec(.25, 2),
               rec(.25, 5), 100 * med([e[0] for e in err]), med([e[1] for e in err]),
               sum(1 for e in err if e[0] > .5 or e[1] > 10)))
print("%-28s %s | p50 %.0f ms" % (tag, line(rows), r["latency_ms"]["p50"]))
# The frames that share at least 30% of their view with the map's recording: what coverage
# leaves to the pipeline (frames that share less are mostly right to refuse).
shared = {round(float(x["stamp"]), 4): x["shared"] for x in json.load(open(shared_path))}
covered = [x for x in rows if shared.get(round(x["timestamp"], 4), 0) >= 0.3]
print("%-28s %s" % ("  sharing >= 30% of the view", line(covered)))
PY
}
run() { # tag map_source build_flags query_source replay_flags [split whose shared views to use]
  local tag=$1 map="$OUT/$1.pntrmap" shared="$OUT/${6:-$1}.shared.json"
  [ -f "$map" ] || "$BIN/pntr" build-db --sequence "$2" $3 --out "$map" --json >"$OUT/$tag.build.json" 2>"$OUT/$tag.build.err"
  # How much of each query's view the map's recording saw (ground-truth depth carried across).
  [ -f "$shared" ] || "$PY" "$ROOT/scripts/shared_view.py" "$2" "$4" --intrinsics $K --out "$shared" >/dev/null
  serve "$map"
  for mode in single stream; do
    local flags=$5; [ $mode = single ] && flags="$flags --no-prior"
    "$BIN/pntr" replay --addr "$ADDR" --sequence "$4" $flags --rate 20 \
      --trajectory "$OUT/$tag.$mode.txt" --json "$OUT/$tag.$mode.json" --frames-log "$OUT/$tag.$mode.frames.jsonl" >/dev/null 2>&1
    summary "$tag $mode" "$OUT/$tag.$mode.json" "$shared"
  done
  kill $SERVER; wait $SERVER 2>/dev/null || true
}
run A "$OUT/tum_0_249" "--intrinsics $K" "$OUT/tum_250_499" "--intrinsics $K"
run A_7scenes "$OUT/7scenes_0_249" "--intrinsics $K --depth-to-colour=$OFFSET" "$OUT/7scenes_250_499" "--intrinsics $K --depth-to-colour=$OFFSET" A
run B "$OUT/tum_250_499" "--intrinsics $K" "$OUT/tum_0_249" "--intrinsics $K"
run W "$OUT/tum_0_149" "--intrinsics $K" "$OUT/tum_wide" "--intrinsics $K" wide
run W2 "$OUT/tum_350_499" "--intrinsics $K" "$OUT/tum_wide2" "--intrinsics $K" wide2
