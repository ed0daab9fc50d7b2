"""Cross-checks between pntr's HDF5 files and h5py, the way the HPointLoc code reads the dataset.

  write PATH   write a small Point file exactly as h5py writes the real dataset (default file format,
               uint8 RGB, float32 depth with a trailing channel, float32 gps/quat, uint32 semantic,
               one field gzip+shuffle compressed); values follow formulas the Rust test recomputes.
  check PATH   open a pntr-written file with h5py, access it as the HPointLoc code does
               (f['gps_base'][i], depth squeezed and multiplied by 10), print JSON with every field's
               shape and dtype and checksums the Rust test compares with its own reading.
"""
import json
import sys

import h5py
import numpy as np

N_DB, N_Q, H, W = 6, 3, 5, 7


def expected_rgb(n, base):
    i, y, x, c = np.meshgrid(np.arange(n), np.arange(H), np.arange(W), np.arange(3), indexing="ij")
    return ((i * 31 + y * 7 + x * 3 + c + base) % 256).astype(np.uint8)


def expected_depth(n, base):
    i, y, x = np.meshgrid(np.arange(n), np.arange(H), np.arange(W), indexing="ij")
    d = (0.05 * (i + 1) + 0.01 * y + 0.001 * x + base).astype(np.float32)
    d[:, 0, 0] = 0.0  # one invalid pixel per frame
    return d[..., None]


def expected_pose(n, base):
    k = np.arange(n, dtype=np.float64)
    gps = np.stack([k + base, 1.25 + 0 * k, -0.5 * k], axis=1).astype(np.float32)
    yaw = 0.3 * k + base
    # camera-to-world rotation about +y by yaw: q = (cos(yaw/2), 0, sin(yaw/2), 0)
    quat = np.stack([np.cos(yaw / 2), 0 * k, np.sin(yaw / 2), 0 * k], axis=1).astype(np.float32)
    return gps, quat


def write(path):
    with h5py.File(path, "w") as f:
        f.create_dataset("rgb_base", data=expected_rgb(N_DB, 0))
        f.create_dataset("depth_base", data=expected_depth(N_DB, 0.0), compression="gzip", shuffle=True,
                         chunks=(1, H, W, 1))
        sem = (np.arange(N_DB * H * W) % 11).astype(np.uint32).reshape(N_DB, H, W)
        f.create_dataset("semantic_base", data=sem)
        gps, quat = expected_pose(N_DB, 0.0)
        f.create_dataset("gps_base", data=gps)
        f.create_dataset("quat_base", data=quat)
        f.create_dataset("rgb", data=expected_rgb(N_Q, 100))
        f.create_dataset("depth", data=expected_depth(N_Q, 0.2))
        gps, quat = expected_pose(N_Q, 1.0)
        f.create_dataset("gps", data=gps)
        f.create_dataset("quat", data=quat)


def check(path):
    out = {"fields": {}, "sums": {}}
    with h5py.File(path, "r") as f:
        for name in f:
            out["fields"][name] = {"shape": list(f[name].shape), "dtype": str(f[name].dtype)}
        # The HPointLoc code's access pattern: per-image rows, squeeze the depth channel, x10 metres.
        for role in ("_base", ""):
            rgb = f["rgb" + role][:]
            depth_m = np.squeeze(f["depth" + role][:], axis=-1).astype(np.float64) * 10.0
            out["sums"]["rgb" + role] = int(rgb.astype(np.int64).sum())
            out["sums"]["depth_m" + role] = float(depth_m.sum())
            out["sums"]["gps" + role] = [float(v) for v in np.asarray(f["gps" + role][:], np.float64).sum(axis=0)]
            out["sums"]["quat0" + role] = [float(v) for v in f["quat" + role][0]]
            if "semantic" + role in f:
                out["sums"]["semantic" + role] = int(f["semantic" + role][:].astype(np.int64).sum())
    print(json.dumps(out))


if __name__ == "__main__":
    {"write": write, "check": check}[sys.argv[1]](sys.argv[2])
