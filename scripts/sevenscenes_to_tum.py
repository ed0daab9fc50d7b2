#!/usr/bin/env python3
"""Convert a sequence in the 7-Scenes layout to the TUM RGB-D layout, depth registered to colour.

The 7-Scenes layout (also 12-Scenes' and tsdf-fusion's demo data):
    SRC/frame-000000.color.png|jpg   colour, 640x480
    SRC/frame-000000.depth.png       16-bit depth of the *depth* camera, millimetres, 65535 = invalid
    SRC/frame-000000.pose.txt        4x4 world_from_camera (row-major) of the depth camera

The TUM layout written (what `pntr build-db --sequence` and `pntr replay --sequence` read):
    OUT/rgb/<t>.png, OUT/depth/<t>.png (16-bit, 5000 per metre, registered to the colour image),
    OUT/rgb.txt, OUT/depth.txt, OUT/groundtruth.txt (world_from_camera of the colour camera, TUM order)

Depth is registered by forward projection with a z-buffer: every depth pixel is back-projected with
the depth camera's intrinsics, moved by colour_from_depth (a translation by default: the offset the
Kinect calibration used by DSAC* and ACE gives, rotation neglected) and projected into the colour
camera. Frames are stamped at 30 Hz from their index. The data is not fetched here: give the folder.

    python3 scripts/sevenscenes_to_tum.py SRC OUT --first 0 --last 249
"""
import argparse
import os
import sys

import numpy as np
from PIL import Image


def quaternion(r):
    """(qx, qy, qz, qw) of a rotation matrix."""
    t = np.trace(r)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return tuple(q)


def register(depth_mm, kd, kc, colour_from_depth, size):
    w, h = size
    v, u = np.nonzero((depth_mm > 0) & (depth_mm < 65535))
    z = depth_mm[v, u].astype(np.float64) / 1000.0
    x = (u - kd[2]) / kd[0] * z
    y = (v - kd[3]) / kd[1] * z
    p = colour_from_depth[:3, :3] @ np.stack([x, y, z]) + colour_from_depth[:3, 3:4]
    ok = p[2] > 0.05
    p = p[:, ok]
    uc = np.round(kc[0] * p[0] / p[2] + kc[2]).astype(np.int64)
    vc = np.round(kc[1] * p[1] / p[2] + kc[3]).astype(np.int64)
    inside = (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
    uc, vc, zc = uc[inside], vc[inside], p[2][inside]
    out = np.full(h * w, np.inf)
    np.minimum.at(out, vc * w + uc, zc)
    out[~np.isfinite(out)] = 0.0
    return np.clip(np.round(out * 5000.0), 0, 65535).astype(np.uint16).reshape(h, w)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--last", type=int, default=None, help="last frame index, inclusive")
    ap.add_argument("--frames", default=None, help="comma-separated frame indices (instead of a range)")
    ap.add_argument("--colour-intrinsics", default="525,525,320,240")
    ap.add_argument("--depth-intrinsics", default="585,585,320,240")
    ap.add_argument("--colour-from-depth", default="-0.0256,0.0001,0.0020",
                    help="tx,ty,tz metres (translation only) or 12 numbers (3x4 row-major)")
    a = ap.parse_args()
    kc = [float(x) for x in a.colour_intrinsics.split(",")]
    kd = [float(x) for x in a.depth_intrinsics.split(",")]
    e = [float(x) for x in a.colour_from_depth.split(",")]
    c_from_d = np.eye(4)
    if len(e) == 3:
        c_from_d[:3, 3] = e
    elif len(e) == 12:
        c_from_d[:3, :] = np.array(e).reshape(3, 4)
    else:
        sys.exit("--colour-from-depth: 3 or 12 numbers")
    d_from_c = np.linalg.inv(c_from_d)
    if a.frames:
        idx = [int(x) for x in a.frames.split(",")]
    else:
        last = a.last
        if last is None:
            last = a.first
            while os.path.exists(os.path.join(a.src, "frame-%06d.pose.txt" % (last + 1))):
                last += 1
        idx = list(range(a.first, last + 1))
    os.makedirs(os.path.join(a.out, "rgb"), exist_ok=True)
    os.makedirs(os.path.join(a.out, "depth"), exist_ok=True)
    rgb_txt, depth_txt, gt = ["# colour images\n"], ["# depth images\n"], ["# timestamp tx ty tz qx qy qz qw\n"]
    for i in idx:
        stem = os.path.join(a.src, "frame-%06d" % i)
        colour = stem + ".color.png" if os.path.exists(stem + ".color.png") else stem + ".color.jpg"
        rgb = Image.open(colour).convert("RGB")
        depth = np.array(Image.open(stem + ".depth.png")).astype(np.int64)
        pose = np.loadtxt(stem + ".pose.txt").reshape(4, 4)
        t = "%.6f" % (i / 30.0)
        rgb.save(os.path.join(a.out, "rgb", t + ".png"))
        reg = register(depth, kd, kc, c_from_d, rgb.size)
        Image.fromarray(reg).save(os.path.join(a.out, "depth", t + ".png"))
        rgb_txt.append("%s rgb/%s.png\n" % (t, t))
        depth_txt.append("%s depth/%s.png\n" % (t, t))
        w_from_c = pose @ d_from_c
        q = quaternion(w_from_c[:3, :3])
        gt.append("%s %.6f %.6f %.6f %.8f %.8f %.8f %.8f\n" % ((t,) + tuple(w_from_c[:3, 3]) + q))
    for name, lines in (("rgb.txt", rgb_txt), ("depth.txt", depth_txt), ("groundtruth.txt", gt)):
        with open(os.path.join(a.out, name), "w") as f:
            f.writelines(lines)
    print("%d frames -> %s" % (len(idx), a.out))


if __name__ == "__main__":
    main()
