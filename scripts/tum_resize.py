#!/usr/bin/env python3
"""Write a TUM RGB-D folder as another camera size would have taken it, for timing pntr at the frame
sizes robots send (BENCHMARKS.md, "Real recordings": speed by frame size).

    python scripts/tum_resize.py SRC DST --size WxH --intrinsics FX,FY,CX,CY

The frames of SRC (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt; depth registered to colour) are
cropped about their centre to the aspect ratio of WxH and resampled to WxH: colour with PIL's
antialiased bilinear filter, depth by the nearest pixel (depths are never blended across an edge).
The poses are the same camera's, so groundtruth.txt is copied. Prints the new camera's FX,FY,CX,CY
(pixel centres at +0.5, as pntr and OpenCV take them), for --intrinsics. Upscaling (a 1280x720 frame
from a 640x480 one) adds no detail: use it for timing, not for accuracy.
"""
import argparse
import os
import shutil
import sys

from PIL import Image


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--size", required=True, help="WxH, e.g. 256x256 or 1280x720")
    ap.add_argument("--intrinsics", required=True, help="FX,FY,CX,CY of SRC's colour camera")
    a = ap.parse_args()
    try:
        w, h = (int(v) for v in a.size.lower().split("x"))
        fx, fy, cx, cy = (float(v) for v in a.intrinsics.split(","))
    except ValueError:
        sys.exit(f"--size must be WxH and --intrinsics FX,FY,CX,CY (got {a.size!r}, {a.intrinsics!r})")
    os.makedirs(os.path.join(a.dst, "rgb"), exist_ok=True)
    os.makedirs(os.path.join(a.dst, "depth"), exist_ok=True)
    crop = None
    for listing, kind in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        rows = [l.split() for l in open(os.path.join(a.src, listing)) if l.strip() and not l.startswith("#")]
        for stamp, rel in rows:
            im = Image.open(os.path.join(a.src, rel))
            if crop is None:
                sw, sh = im.size
                cw, ch = (sw, sw * h / w) if sw * h / w <= sh else (sh * w / h, sh)
                crop = ((sw - cw) / 2, (sh - ch) / 2, (sw + cw) / 2, (sh + ch) / 2)
            if kind == "rgb":
                out = im.convert("RGB").resize((w, h), Image.BILINEAR, box=crop, reducing_gap=None)
            else:
                out = im.resize((w, h), Image.NEAREST, box=crop)
            out.save(os.path.join(a.dst, rel))
        shutil.copy(os.path.join(a.src, listing), os.path.join(a.dst, listing))
    shutil.copy(os.path.join(a.src, "groundtruth.txt"), os.path.join(a.dst, "groundtruth.txt"))
    s = w / (crop[2] - crop[0])
    k = (fx * s, fy * s, (cx - crop[0] + 0.5) * s - 0.5, (cy - crop[1] + 0.5) * s - 0.5)
    print(",".join("%.4f" % v for v in k))


if __name__ == "__main__":
    main()
