"""Quantize XFeat's backbone to int8 (ONNX Runtime static quantization) for the `xfeat-int8` extractor.

Environment (only needed to regenerate models/xfeat_backbone_int8.onnx; no PyTorch):
    python3 -m venv /tmp/quant-venv
    /tmp/quant-venv/bin/pip install onnxruntime==1.31.1 onnx numpy h5py
    pntr synth --out /tmp/quant-renders --scenes 2 --points-per-scene 12 --queries-per-point 2 --seed 11
    /tmp/quant-venv/bin/python models/quantize.py /tmp/quant-renders

The float model is the trimmed one (`export.py` trims it, `trim.py`): input `gray`, outputs
`descriptor_map`, `keypoint_logits` and `reliability`, so the quantized model has the same layout.
The committed int8 file is this script's output on the trimmed float model (regenerated 2026-12-02;
byte-identical when rerun with the renders below).

Recipe: QDQ format, int8 weights per output channel, uint8 activations, MinMax ranges observed on the
renders of seed 11 (the calibration apartments, no benchmark scene among them): every third database
view and query of each Point, the even ones for the ranges and the odd ones to verify. XFeat's keypoint
and reliability heads stay in float: they decide where keypoints are, which registration depends on,
and cost little. The result is verified against the float model on the held-back renders (descriptor
cosine, heatmap difference) and timed on one thread; the figures go to BENCHMARKS.md ("int8 XFeat").
"""
import glob
import os
import sys
import tempfile
import time

import h5py
import numpy as np
import onnx
import onnxruntime as ort
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

HERE = os.path.dirname(os.path.abspath(__file__))
FLOAT_MODEL = os.path.join(HERE, "xfeat_backbone.onnx")
INT8_MODEL = os.path.join(HERE, "xfeat_backbone_int8.onnx")
FLOAT_PREFIXES = ("/net/keypoint_head", "/net/heatmap_head")


def renders(root):
    """Grey images [1, 1, H, W] in 0..1 (the mean of R, G, B), as pntr feeds the trimmed backbone,
    from the HDF5 files under `root`."""
    files = sorted(glob.glob(os.path.join(root, "**", "*.hdf5"), recursive=True))
    if not files:
        sys.exit(f"{root}: no .hdf5 files (write renders with `pntr synth --out {root} --seed 11`)")
    out = []
    for path in files:
        with h5py.File(path, "r") as f:
            for key in ("rgb_base", "rgb"):
                for rgb in f[key][::3]:
                    planar = rgb.astype(np.float32).transpose(2, 0, 1) / 255.0
                    out.append(planar.mean(axis=0, keepdims=True)[None].copy())
    return out


class Reader(CalibrationDataReader):
    def __init__(self, images):
        self.images = iter(images)

    def get_next(self):
        x = next(self.images, None)
        return None if x is None else {"gray": x}


def heatmap(logits):
    """The full-resolution heatmap from keypoint logits [1, 65, h8, w8], as pntr computes it."""
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    p = (e / e.sum(axis=1, keepdims=True))[0, :64]
    h8, w8 = p.shape[1:]
    return p.reshape(8, 8, h8, w8).transpose(2, 0, 3, 1).reshape(h8 * 8, w8 * 8)


def session(path):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    images = renders(sys.argv[1])
    calibrate, verify = images[0::2], images[1::2]
    with tempfile.TemporaryDirectory(dir=HERE) as tmp:
        pre = os.path.join(tmp, "pre.onnx")
        quant_pre_process(FLOAT_MODEL, pre, skip_symbolic_shape=True)
        keep_float = [n.name for n in onnx.load(pre).graph.node if n.name.startswith(FLOAT_PREFIXES)]
        out = os.path.join(tmp, "int8.onnx")
        quantize_static(pre, out, Reader(calibrate), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_exclude=keep_float)
        float_s, int8_s = session(FLOAT_MODEL), session(out)
        cosines, heat = [], []
        for x in verify:
            ref = float_s.run(None, {"gray": x})
            got = int8_s.run(None, {"gray": x})
            f0 = ref[0].reshape(ref[0].shape[1], -1)
            f1 = got[0].reshape(got[0].shape[1], -1)
            cos = (f0 * f1).sum(0) / (np.linalg.norm(f0, axis=0) * np.linalg.norm(f1, axis=0) + 1e-9)
            cosines.append(np.median(cos))
            heat.append(np.abs(heatmap(ref[1]) - heatmap(got[1])).max())
        cos, hm = float(np.median(cosines)), float(np.median(heat))
        print(f"{len(calibrate)} calibration and {len(verify)} verification renders; "
              f"{len(keep_float)} nodes kept in float")
        print(f"descriptors: median cosine to the float model {cos:.4f}; heatmap max |difference| "
              f"(median over images) {hm:.3f}")
        assert cos > 0.99, "int8 descriptors drifted from the float model's"
        for name, s in (("float", float_s), ("int8", int8_s)):
            for x in verify[:5]:
                s.run(None, {"gray": x})
            t = time.perf_counter()
            for x in verify:
                s.run(None, {"gray": x})
            print(f"{name}: {(time.perf_counter() - t) / len(verify) * 1e3:.2f} ms a frame, one thread")
        os.replace(out, INT8_MODEL)
    print(f"wrote {INT8_MODEL}")


if __name__ == "__main__":
    main()
