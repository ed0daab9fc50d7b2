"""Time pntr's ONNX feature models through Python onnxruntime, on the shapes `feature_latency` uses.

Counterpart of `cargo run --release -p pntr-features --example feature_latency`: same model files, same
input shapes, same thread count, median of the same number of runs. The Python figures are the bare
`session.run`; the Rust figures include pntr's own work around it (XFeat's sparse step, resizing, the
match filter), so Rust / Python shows the overhead pntr adds.

Environment: a venv with `onnxruntime==1.31.1 numpy`;
`python scripts/bench_features.py [--threads N] [--iters N] [--models DIR]`.
"""
import argparse
import os
import time

import numpy as np
import onnxruntime as ort


def median_ms(iters, fn):
    for _ in range(3):
        fn()
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--models", default="models")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--iters", type=int, default=20)
    a = ap.parse_args()
    so = ort.SessionOptions()
    so.intra_op_num_threads = a.threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    x = ort.InferenceSession(os.path.join(a.models, "xfeat_backbone.onnx"), so, providers=["CPUExecutionProvider"])
    lg = ort.InferenceSession(os.path.join(a.models, "lighterglue.onnx"), so, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    rows = []
    for h, w in ((256, 256), (480, 640)):
        # The trimmed backbone (models/trim.py) takes the grey plane; an exported one, RGB.
        name = x.get_inputs()[0].name
        img = rng.random((1, 1 if name == "gray" else 3, h, w), dtype=np.float32)
        rows.append((f"xfeat {w}x{h}", median_ms(a.iters, lambda: x.run(None, {name: img}))))
    def matcher_rows(name, sess, dim, iters):
        for k in (256, 512, 1024):
            kp = (rng.random((1, k, 2)) * [640, 480]).astype(np.float32)
            d = rng.normal(size=(1, k, dim)).astype(np.float32)
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            size = np.array([[640, 480]], np.float32)
            feed = {"kpts0": kp, "kpts1": kp, "desc0": d, "desc1": d, "size0": size, "size1": size}
            rows.append((f"{name} {k}+{k}", median_ms(iters, lambda: sess.run(None, feed))))

    matcher_rows("lighterglue", lg, 64, a.iters)
    al_path = os.path.join(a.models, "aliked_n16.onnx")
    if os.path.exists(al_path):
        al = ort.InferenceSession(al_path, so, providers=["CPUExecutionProvider"])
        for h, w in ((256, 256), (480, 640)):
            img = rng.random((1, 3, h, w), dtype=np.float32)
            rows.append((f"aliked {w}x{h}", median_ms(min(a.iters, 10), lambda: al.run(None, {"image": img}))))
    lga_path = os.path.join(a.models, "lightglue_aliked.onnx")
    if os.path.exists(lga_path):
        lga = ort.InferenceSession(lga_path, so, providers=["CPUExecutionProvider"])
        matcher_rows("lightglue(aliked)", lga, 128, min(a.iters, 10))
    print(f"python onnxruntime {ort.__version__}; threads {a.threads}; median of {a.iters}")
    print("| stage | ms |\n|---|---|")
    for n, ms in rows:
        print(f"| {n} | {ms:.2f} |")


if __name__ == "__main__":
    main()
