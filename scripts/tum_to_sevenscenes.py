#!/usr/bin/env python3
"""Write a TUM RGB-D folder (depth registered to colour) in the 7-Scenes layout, as a Kinect records it:
depth in a separate depth camera with its own intrinsics, a few centimetres from the colour camera.

The inverse of what pntr does with `--depth-intrinsics` and `--depth-to-colour`, written with numpy and
PIL only (another tool than pntr's own reader), for tests:

    OUT/frame-NNNNNN.color.png       the colour image as it is
    OUT/frame-NNNNNN.depth.png       16-bit millimetres in the depth camera, 65535 where it saw nothing
    OUT/frame-NNNNNN.pose.txt        4x4 world_from_camera of the depth camera
    OUT/camera-intrinsics.txt        3x3 K of the depth camera

Each colour pixel with depth is back-projected with the colour camera, moved by depth_from_colour and
projected into the depth camera (nearest surface kept, footprints filled).

    python3 scripts/tum_to_sevenscenes.py SRC OUT --intrinsics fx,fy,cx,cy --depth-intrinsics fx,fy,cx,cy \
        --depth-to-colour tx,ty,tz
"""
import argparse
import os

import numpy as np
from PIL import Image


def quat_to_matrix(qx, qy, qz, qw):
    n = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    qx, qy, qz, qw = qx / n, qy / n, qz / n, qw / n
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])


def listing(path):
    rows = []
    with open(path) as f:
        for line in f:
            if line.strip() and not line.startswith("#"):
                rows.append(line.split())
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("--intrinsics", required=True, help="colour camera fx,fy,cx,cy")
    ap.add_argument("--depth-intrinsics", required=True, help="depth camera fx,fy,cx,cy")
    ap.add_argument("--depth-to-colour", required=True, help="tx,ty,tz: colour point = depth point + t")
    ap.add_argument("--depth-size", default=None, help="WxH of the depth images (default: the colour size)")
    a = ap.parse_args()
    kc = [float(x) for x in a.intrinsics.split(",")]
    kd = [float(x) for x in a.depth_intrinsics.split(",")]
    t = np.array([float(x) for x in a.depth_to_colour.split(",")])
    os.makedirs(a.out, exist_ok=True)
    rgb = {r[0]: r[1] for r in listing(os.path.join(a.src, "rgb.txt"))}
    depth = {r[0]: r[1] for r in listing(os.path.join(a.src, "depth.txt"))}
    gt = {r[0]: [float(x) for x in r[1:]] for r in listing(os.path.join(a.src, "groundtruth.txt"))}
    stamps = sorted(rgb, key=float)
    for i, s in enumerate(stamps):
        colour = Image.open(os.path.join(a.src, rgb[s])).convert("RGB")
        w, h = colour.size
        dw, dh = (int(x) for x in a.depth_size.split("x")) if a.depth_size else (w, h)
        z = np.array(Image.open(os.path.join(a.src, depth[s]))).astype(np.float64) / 5000.0
        v, u = np.nonzero(z > 0)
        zz = z[v, u]
        p = np.stack([(u - kc[2]) / kc[0] * zz, (v - kc[3]) / kc[1] * zz, zz]) - t[:, None]
        ud = np.round(kd[0] * p[0] / p[2] + kd[2]).astype(np.int64)
        vd = np.round(kd[1] * p[1] / p[2] + kd[3]).astype(np.int64)
        out = np.full((dh, dw), np.inf)
        # The depth camera's pixels are finer than the colour camera's by kd/kc: fill each footprint.
        half = int(np.ceil((max(kd[0] / kc[0], kd[1] / kc[1]) - 1) / 2))
        for dv in range(-half, half + 1):
            for du in range(-half, half + 1):
                uu, vv = ud + du, vd + dv
                ok = (uu >= 0) & (uu < dw) & (vv >= 0) & (vv < dh) & (p[2] > 0)
                np.minimum.at(out, (vv[ok], uu[ok]), p[2][ok])
        mm = np.where(np.isfinite(out), np.round(out * 1000.0), 65535).astype(np.uint16)
        stem = os.path.join(a.out, "frame-%06d" % i)
        colour.save(stem + ".color.png")
        Image.fromarray(mm).save(stem + ".depth.png")
        g = gt.get(s)
        m = np.full((4, 4), np.inf)
        if g is not None:
            wc = np.eye(4)
            wc[:3, :3] = quat_to_matrix(*g[3:7])
            wc[:3, 3] = g[0:3]
            cd = np.eye(4)
            cd[:3, 3] = t
            m = wc @ cd
        np.savetxt(stem + ".pose.txt", m, fmt="%.9e")
    np.savetxt(os.path.join(a.out, "camera-intrinsics.txt"),
               np.array([[kd[0], 0, kd[2]], [0, kd[1], kd[3]], [0, 0, 1]]), fmt="%.6e")
    print("%d frames -> %s" % (len(stamps), a.out))


if __name__ == "__main__":
    main()
