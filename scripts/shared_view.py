#!/usr/bin/env python3
"""Which frames of a recording see what a map's recording saw, and from how far: the selection of
wide-baseline queries for pntr's benchmarks (scripts/bench_real.sh, scripts/bench_wide.sh).

    shared_view.py MAP_DIR QUERY_DIR --out FRAMES.json [--select DIR --min-shared S --min-distance-m D]

MAP_DIR and QUERY_DIR are TUM RGB-D folders (rgb.txt, depth.txt, groundtruth.txt of the colour
camera with optical axes, depth registered to colour at 5000 units a metre; calibration.txt or
--intrinsics). For each query frame with ground truth: `shared`, the largest share of its depth
pixels (every 8th pixel of every 8th row) that one map frame also sees (projected into that frame,
in front of it, inside its image, and within 3 cm + 1% of the range of its depth there: the same
surface, not one behind it); `distance_m` and `angle_deg`, from the nearest map camera in position
and in orientation (each over every map frame, so over every camera a map built from MAP_DIR can
hold). `--select DIR` writes a TUM folder of the queries with shared >= --min-shared and
distance_m >= --min-distance-m (links to the images, not copies).
"""
import argparse
import json
import os

import numpy as np
from PIL import Image


def read_list(path):
    out = []
    for line in open(path):
        if line.startswith("#") or not line.strip():
            continue
        out.append(line.split())
    return out


def poses(folder):
    out = {}
    for t, *v in read_list(os.path.join(folder, "groundtruth.txt")):
        tx, ty, tz, x, y, z, w = map(float, v[:7])
        m = np.eye(4)
        m[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        m[:3, 3] = tx, ty, tz
        out[float(t)] = (t, m)
    return out


def frames(folder):
    """(stamp text, depth path, world_from_camera) for each depth image with a pose at its stamp."""
    gt = poses(folder)
    if not gt:
        return []
    stamps = np.array(sorted(gt))
    out = []
    for t, path, *_ in read_list(os.path.join(folder, "depth.txt")):
        i = int(np.argmin(np.abs(stamps - float(t))))
        if abs(stamps[i] - float(t)) <= 0.02:
            out.append((t, os.path.join(folder, path), gt[stamps[i]][1]))
    return out


def intrinsics(folder, given):
    if given:
        return list(map(float, given.split(",")[:4]))
    path = os.path.join(folder, "calibration.txt")
    if not os.path.exists(path):
        raise SystemExit(f"{folder}: no calibration.txt; give --intrinsics fx,fy,cx,cy")
    return list(map(float, open(path).read().split()[:4]))


def depth_m(path):
    return np.asarray(Image.open(path)).astype(np.float64) / 5000.0


def world_points(depth, k, world_from_camera, step=8):
    fx, fy, cx, cy = k
    v, u = np.mgrid[0 : depth.shape[0] : step, 0 : depth.shape[1] : step]
    z = depth[::step, ::step]
    ok = z > 0
    x = (u[ok] - cx) / fx * z[ok]
    y = (v[ok] - cy) / fy * z[ok]
    return world_from_camera @ np.stack([x, y, z[ok], np.ones_like(x)])


def seen_share(points, depth, k, world_from_camera):
    if points.shape[1] == 0:
        return 0.0
    fx, fy, cx, cy = k
    p = np.linalg.inv(world_from_camera) @ points
    z = p[2]
    ok = z > 0.1
    zs = np.where(ok, z, 1.0)
    u = np.round(p[0] / zs * fx + cx).astype(int)
    v = np.round(p[1] / zs * fy + cy).astype(int)
    ok &= (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
    d = np.zeros_like(z)
    d[ok] = depth[v[ok], u[ok]]
    ok &= (d > 0) & (np.abs(d - z) < 0.03 + 0.01 * z)
    return float(ok.mean())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map_dir")
    ap.add_argument("query_dir")
    ap.add_argument("--out", required=True, help="JSON: one object per query frame")
    ap.add_argument("--intrinsics", help="fx,fy,cx,cy of both folders when they hold no calibration.txt")
    ap.add_argument("--map-stride", type=int, default=3, help="every Nth map frame (default 3)")
    ap.add_argument("--select", help="write the selected queries as a TUM folder here")
    ap.add_argument("--min-shared", type=float, default=0.3)
    ap.add_argument("--min-distance-m", type=float, default=1.0)
    a = ap.parse_args()
    k_map = intrinsics(a.map_dir, a.intrinsics)
    k_query = intrinsics(a.query_dir, a.intrinsics)
    maps = [(depth_m(p), m) for _, p, m in frames(a.map_dir)[:: a.map_stride]]
    if not maps:
        raise SystemExit(f"{a.map_dir}: no depth image with a ground-truth pose")
    rows = []
    for t, path, m in frames(a.query_dir):
        pts = world_points(depth_m(path), k_query, m)
        shared = max(seen_share(pts, d, k_map, mm) for d, mm in maps)
        dist = min(float(np.linalg.norm(m[:3, 3] - mm[:3, 3])) for _, mm in maps)
        cos = [(np.trace(m[:3, :3].T @ mm[:3, :3]) - 1) / 2 for _, mm in maps]
        angle = float(np.degrees(np.arccos(np.clip(max(cos), -1, 1))))
        rows.append({"stamp": t, "shared": shared, "distance_m": dist, "angle_deg": angle})
    with open(a.out + ".tmp", "w") as f:
        json.dump(rows, f)
    os.replace(a.out + ".tmp", a.out)
    if a.select:
        keep = {r["stamp"] for r in rows if r["shared"] >= a.min_shared and r["distance_m"] >= a.min_distance_m}
        os.makedirs(a.select, exist_ok=True)
        for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
            src = os.path.join(a.query_dir, name)
            lines = [l for l in open(src) if l.startswith("#") or (l.split() and l.split()[0] in keep)]
            if name != "groundtruth.txt":
                for l in lines:
                    if l.startswith("#"):
                        continue
                    rel = l.split()[1]
                    dst = os.path.join(a.select, rel)
                    os.makedirs(os.path.dirname(dst), exist_ok=True)
                    if not os.path.lexists(dst):
                        os.symlink(os.path.abspath(os.path.join(a.query_dir, rel)), dst)
            with open(os.path.join(a.select, name), "w") as f:
                f.writelines(lines)
        cal = os.path.join(a.query_dir, "calibration.txt")
        if os.path.exists(cal):
            with open(cal) as s, open(os.path.join(a.select, "calibration.txt"), "w") as d:
                d.write(s.read())
        print(f"{len(keep)} of {len(rows)} queries share >= {a.min_shared} of their view and lie >= {a.min_distance_m} m from every map camera")


if __name__ == "__main__":
    main()
