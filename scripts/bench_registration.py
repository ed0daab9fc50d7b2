"""Compare `pntr register --method teaser` with Open3D's correspondence-based RANSAC on identical inputs.

Both solvers get the same correspondences (written to CSV; pntr reads them through its CLI, Open3D
through numpy) and run on one core (OMP_NUM_THREADS=1 for Open3D; pntr's solver is single-threaded).
Times are each solver's own: pntr's `seconds` field (the solve, without process start or CSV parsing)
and a perf_counter around Open3D's call. Prints a markdown table for BENCHMARKS.md.

Environment: `python3 -m venv .deps/bench-venv && .deps/bench-venv/bin/pip install open3d-cpu numpy`,
then `.deps/bench-venv/bin/python scripts/bench_registration.py [--pntr target/release/pntr]`.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

NOISE_SIGMA = 0.01
NOISE_BOUND = 0.05


def random_rotation(rng):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, np.pi)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def problem(seed, n, ratio):
    """Same distribution as pntr_registration::problems::generate (not the same draws)."""
    rng = np.random.default_rng(seed)
    r = random_rotation(rng)
    t = np.array([rng.uniform(-5, 5), rng.uniform(-2, 2), rng.uniform(-5, 5)])

    def pts(m):
        return np.stack([rng.uniform(-4, 4, m), rng.uniform(-1.5, 1.5, m), rng.uniform(0.5, 8, m)], axis=1)

    src = pts(n)
    dst = src @ r.T + t + rng.normal(0, NOISE_SIGMA, size=(n, 3))
    n_out = int(round(n * ratio))
    dst[:n_out] = pts(n_out) @ r.T + t
    return src, dst, r, t


def errors(r_est, t_est, r, t):
    c = np.clip((np.trace(r_est.T @ r) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(c)), np.linalg.norm(t_est - t)


def run_pntr(binary, src, dst):
    with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as f:
        f.write("sx,sy,sz,dx,dy,dz\n")
        for s, d in zip(src, dst):
            f.write(",".join(repr(float(v)) for v in (*s, *d)) + "\n")
        path = f.name
    try:
        out = subprocess.run([binary, "register", "--pairs", path, "--noise-bound", str(NOISE_BOUND)],
                             check=True, capture_output=True, text=True).stdout
    finally:
        os.unlink(path)
    v = json.loads(out)
    return np.array(v["rotation"]), np.array(v["translation"]), v["seconds"], v["valid"]


def run_open3d(src, dst):
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst))
    idx = np.arange(len(src))
    corres = o3d.utility.Vector2iVector(np.stack([idx, idx], axis=1).astype(np.int32))
    start = time.perf_counter()
    res = o3d.pipelines.registration.registration_ransac_based_on_correspondence(
        ps, pd, corres, NOISE_BOUND,
        o3d.pipelines.registration.TransformationEstimationPointToPoint(False), 3, [],
        o3d.pipelines.registration.RANSACConvergenceCriteria(100000, 0.999))
    seconds = time.perf_counter() - start
    tr = np.asarray(res.transformation)
    return tr[:3, :3], tr[:3, 3], seconds


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pntr", default="target/release/pntr")
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    print(f"open3d {o3d.__version__}, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}", file=sys.stderr)
    print("| N | outliers | pntr ms | Open3D ms | Open3D/pntr time | pntr rot/trans err (deg/cm) "
          "| Open3D rot/trans err (deg/cm) | pntr fails | Open3D fails |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in (100, 500, 1000, 2000):
        for ratio in (0.0, 0.5, 0.9, 0.95):
            rows = []
            for seed in range(args.seeds):
                src, dst, r, t = problem(1000 * n + int(100 * ratio) + seed, n, ratio)
                pr, pt, ps, pv = run_pntr(args.pntr, src, dst)
                orr, ot, os_ = run_open3d(src, dst)
                pe, oe = errors(pr, pt, r, t), errors(orr, ot, r, t)
                rows.append((ps, os_, pe, oe, (not pv) or pe[0] > 1 or pe[1] > 0.03, oe[0] > 1 or oe[1] > 0.03))
            pm = np.median([x[0] for x in rows]) * 1e3
            om = np.median([x[1] for x in rows]) * 1e3
            pe = np.median([x[2] for x in rows], axis=0)
            oe = np.median([x[3] for x in rows], axis=0)
            print(f"| {n} | {int(ratio * 100)}% | {pm:.2f} | {om:.1f} | {om / pm:.1f} | "
                  f"{pe[0]:.3f}/{pe[1] * 100:.2f} | {oe[0]:.3f}/{oe[1] * 100:.2f} | "
                  f"{sum(x[4] for x in rows)}/{len(rows)} | {sum(x[5] for x in rows)}/{len(rows)} |", flush=True)


if __name__ == "__main__":
    main()
