#!/usr/bin/env bash
# The latency pntr-ros adds over a direct Python client of the same server (issue 50), side by side.
#
#   bash scripts/bench_ros.sh MAP TUM_DIR OUT [fx,fy,cx,cy] [SECONDS] [ROUNDS]
#
# One release pntr-server serves MAP. Each round runs, one after the other, for SECONDS (20) each:
#   node:   client/ros/tests/robot.py publishes TUM_DIR's frames over Cyclone DDS at 10 Hz as a ROS 2
#           camera driver and robot base would (raw rgb8 and 16UC1), target/release/pntr-ros localizes
#           them at rate_hz 5 and publishes the pose; latency = the pose's arrival at the robot minus the
#           image's stamp (taken when it was published);
#   direct: the same script hands the same frames at 5 Hz to the Python client (`pntr_client`,
#           client/python) on one LocalizeStream; latency = the answer's arrival minus the frame's capture.
# Both run inside a private user + network namespace (DDS on a veth pair, gRPC on lo), as the test does.
# Needs `cargo build --release -p pntr-service -p pntr-ros` and scripts/setup.sh's venv; a venv with
# the Python client is made in OUT/venv (pip, before entering the namespace). Prints a table and writes
# OUT/summary.json.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ $# -ge 3 ] || { sed -n 2,16p "$0"; exit 2; }
MAP="$(realpath "$1")" TUM="$(realpath "$2")" OUT="$3" K="${4:-}" SECS="${5:-20}" ROUNDS="${6:-3}"
mkdir -p "$OUT"
OUT="$(realpath "$OUT")"
PY="$OUT/venv/bin/python"
if [ -z "${PNTR_BENCH_ROS_INSIDE:-}" ]; then
  if ! "$PY" -c "import pntr_client, cyclonedds, numpy, PIL" 2>/dev/null; then
    python3 -m venv "$OUT/venv"
    "$PY" -m pip install -q --disable-pip-version-check numpy pillow "cyclonedds==11.0.1" "$ROOT/client/python"
  fi
  exec unshare --user --map-root-user --net env PNTR_BENCH_ROS_INSIDE=1 bash "$0" "$@"
fi

ip link set lo up
ip link add dds0 type veth peer name dds1
ip addr add 10.255.42.1/24 dev dds0
ip link set dds0 up; ip link set dds1 up; ip link set dds0 multicast on
ip route add 224.0.0.0/4 dev dds0
export CYCLONEDDS_URI='<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="dds0" multicast="true"/></Interfaces><AllowMulticast>true</AllowMulticast></General></Domain></CycloneDDS>'
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$ROOT/.deps/onnxruntime/libonnxruntime.so.1.31.1}"
export OPENVINO_DYLIB_PATH="${OPENVINO_DYLIB_PATH:-$ROOT/.deps/openvino/libopenvino_c.so.2641}"
B="$ROOT/target/release"
ADDR=127.0.0.1:50151
"$B/pntr-server" --db "$MAP" --addr $ADDR --metrics-addr 127.0.0.1:0 --models "$ROOT/models" > "$OUT/server.txt" 2> "$OUT/server.log" &
SERVER=$!
trap 'kill $SERVER 2>/dev/null || true' EXIT
until grep -qs listening "$OUT/server.txt"; do kill -0 $SERVER; sleep 0.2; done
KARG=()
[ -n "$K" ] && KARG=(--intrinsics "$K")
ROBOT=("$PY" "$ROOT/client/ros/tests/robot.py" --tum "$TUM" "${KARG[@]}" --ros-from-map 1 0 0 0 --seconds "$SECS")
for r in $(seq 1 "$ROUNDS"); do
  RMW_IMPLEMENTATION=rmw_cyclonedds_cpp "$B/pntr-ros" --addr $ADDR --ros-args -p rate_hz:=5.0 2> "$OUT/node$r.log" &
  NODE=$!
  "${ROBOT[@]}" --out "$OUT/node$r.json" > /dev/null
  kill -INT $NODE; wait $NODE
  "${ROBOT[@]}" --direct $ADDR --rate-hz 5 --out "$OUT/direct$r.json" > /dev/null
done
"$PY" - "$OUT" "$ROUNDS" "$SECS" <<'PYEOF'
import json, sys
import numpy as np
out, rounds, secs = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rows = []
for r in range(1, rounds + 1):
    node = json.load(open(f"{out}/node{r}.json"))
    direct = json.load(open(f"{out}/direct{r}.json"))["direct"]
    written = {f["stamp_ns"]: f["written_ns"] for f in node["frames"]}
    nl = [(p["recv_ns"] - p["stamp_ns"]) * 1e-6 for p in node["poses"]]
    nw = [(p["recv_ns"] - written[p["stamp_ns"]]) * 1e-6 for p in node["poses"]]
    dl = [a["latency_ms"] for a in direct]
    dloc = [a["latency_ms"] for a in direct if a["localized"]]
    dw = [a["from_loaded_ms"] for a in direct if a["localized"]]
    p = lambda v, q: float(np.percentile(v, q))
    rows.append({"round": r, "node_poses": len(nl), "node_p50_ms": p(nl, 50), "node_p90_ms": p(nl, 90),
                 "node_from_written_p50_ms": p(nw, 50), "node_from_written_p90_ms": p(nw, 90),
                 "direct_answers": len(dl), "direct_localized": len(dloc), "direct_p50_ms": p(dloc, 50),
                 "direct_p90_ms": p(dloc, 90), "direct_from_loaded_p50_ms": p(dw, 50), "direct_from_loaded_p90_ms": p(dw, 90)})
print("latency of LOCALIZED answers, ms (p50 / p90): from the frame's capture (its stamp), and from the moment")
print("the images were handed over (node: written to DDS; direct: loaded, given to the client)")
print(f"{'round':>5} {'node poses':>10} {'node capture':>13} {'node handed':>12} {'direct LOCALIZED':>17} {'direct capture':>15} {'direct handed':>14} {'added p50':>9}")
for x in rows:
    print(f"{x['round']:>5} {x['node_poses']:>10} {x['node_p50_ms']:>6.1f}/{x['node_p90_ms']:<6.1f} {x['node_from_written_p50_ms']:>5.1f}/{x['node_from_written_p90_ms']:<6.1f}"
          f" {x['direct_localized']:>8}/{x['direct_answers']:<8} {x['direct_p50_ms']:>7.1f}/{x['direct_p90_ms']:<7.1f} {x['direct_from_loaded_p50_ms']:>6.1f}/{x['direct_from_loaded_p90_ms']:<7.1f}"
          f" {x['node_from_written_p50_ms'] - x['direct_from_loaded_p50_ms']:>9.1f}")
json.dump({"seconds": secs, "rounds": rows}, open(f"{out}/summary.json", "w"), indent=1)
PYEOF
