"""Trim XFeat's backbone graph to the network proper: pntr does the cheap ends in Rust.

    python3 models/trim.py models/xfeat_backbone.onnx [more.onnx ...]   (needs only the onnx package)

The exported graph (models/export.py) begins and ends with steps that ONNX Runtime runs slowly on one
CPU thread because of their layouts, about a fifth of the backbone's time at 256 x 256 (profile in
BENCHMARKS.md, "XFeat's graph ends in Rust"): the mean over the colour channels of the input, the
softmax over the 65 keypoint logits with the pixel shuffle that makes the full-resolution heatmap,
and the L2 normalisation of the descriptor map. This rewrites a model in place so that

- its input is `gray` [1, 1, H, W], the mean of the R, G and B planes in 0..1, where the graph's
  `ReduceMean` of `image` was (pntr's XFeat computes it while it resamples the image);
- its outputs are `descriptor_map` [1, 64, H/8, W/8] (the descriptors before their L2
  normalisation), `keypoint_logits` [1, 65, H/8, W/8] (before the softmax) and `reliability`
  [1, 1, H/8, W/8] as before;

and drops every node only the removed ends used. `export.py` trims the float model it exports, and
`quantize.py` quantizes the trimmed float model, so its int8 model comes out trimmed; this script is
for files exported before (it rewrites an int8 model of the exported layout the same way). A model
already trimmed is left as it is. pntr loads either layout (`pntr_features::xfeat`).
"""
import os
import sys
import tempfile

import onnx
import onnx.numpy_helper
from onnx import TensorProto, helper


def producer_of(graph):
    return {out: n for n in graph.node for out in n.output}


def trim(path):
    model = onnx.load(path)
    g = model.graph
    if any(i.name == "gray" for i in g.input):
        print(f"{path}: already trimmed")
        return
    means = [n for n in g.node if n.op_type == "ReduceMean" and "image" in n.input]
    norms = [n for n in g.node if n.op_type == "ReduceL2"]
    softmaxes = [n for n in g.node if n.op_type == "Softmax"]
    if len(means) != 1 or len(norms) != 1 or len(softmaxes) != 1:
        sys.exit(f"{path}: not XFeat's exported backbone (one ReduceMean of `image`, one ReduceL2 "
                 f"and one Softmax expected; found {len(means)}, {len(norms)}, {len(softmaxes)})")
    consts = {t.name: onnx.numpy_helper.to_array(t) for t in g.initializer}
    for n in g.node:
        if n.op_type == "Constant":
            consts[n.output[0]] = onnx.numpy_helper.to_array(n.attribute[0].t)

    def axes(node):
        given = [a.ints for a in node.attribute if a.name == "axes"]
        if given:
            return list(given[0])
        return [int(v) for v in consts.get(node.input[1], [])] if len(node.input) > 1 else []

    def attr(node, name, default):
        return next((onnx.helper.get_attribute_value(a) for a in node.attribute if a.name == name), default)

    # The three ends must be the ones the Rust side replaces: over the channel axis, dims kept.
    for node, what in ((means[0], "ReduceMean"), (norms[0], "ReduceL2")):
        if axes(node) != [1] or attr(node, "keepdims", 1) != 1:
            sys.exit(f"{path}: {what} over axes {axes(node)}, keepdims {attr(node, 'keepdims', 1)}; "
                     "expected the channel axis [1], dims kept")
    if attr(softmaxes[0], "axis", -1) != 1:
        sys.exit(f"{path}: Softmax over axis {attr(softmaxes[0], 'axis', -1)}; expected 1")
    made = producer_of(g)

    def upstream(tensor):
        seen, stack = set(), [tensor]
        while stack:
            t = stack.pop()
            if t in seen:
                continue
            seen.add(t)
            n = made.get(t)
            if n is not None:
                stack.extend(i for i in n.input if i)
        return seen

    if softmaxes[0].output[0] not in upstream("heatmap"):
        sys.exit(f"{path}: the Softmax does not feed `heatmap`")
    feats = made.get("feats")
    if feats is None or feats.op_type != "Div" or feats.input[0] != norms[0].input[0]:
        sys.exit(f"{path}: `feats` is not the descriptor map divided by its ReduceL2 norm")
    gray_tensor = means[0].output[0]
    descriptors = norms[0].input[0]
    logits = softmaxes[0].input[0]
    reliability = [o for o in g.output if o.name == "reliability"]
    if not reliability:
        sys.exit(f"{path}: no `reliability` output")

    # The new input takes the place of the channel mean.
    for n in g.node:
        for k, name in enumerate(n.input):
            if name == gray_tensor:
                n.input[k] = "gray"
    # The new outputs are renamed at their producers.
    rename = {descriptors: "descriptor_map", logits: "keypoint_logits"}
    for n in g.node:
        for k, name in enumerate(n.output):
            if name in rename:
                n.output[k] = rename[name]
        for k, name in enumerate(n.input):
            if name in rename:
                n.input[k] = rename[name]

    # Keep only what the outputs need.
    wanted = ["descriptor_map", "keypoint_logits", "reliability"]
    made_by = producer_of(g)
    needed, stack = set(), list(wanted)
    while stack:
        t = stack.pop()
        n = made_by.get(t)
        if n is None or id(n) in needed:
            continue
        needed.add(id(n))
        stack.extend(i for i in n.input if i)
    kept = [n for n in g.node if id(n) in needed]
    used = {i for n in kept for i in n.input}
    del g.node[:]
    g.node.extend(kept)
    inits = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(inits)

    dims = ["height", "width"]
    image = [i for i in g.input if i.name == "image"][0]
    shape = image.type.tensor_type.shape.dim
    if len(shape) == 4 and shape[2].dim_param and shape[3].dim_param:
        dims = [shape[2].dim_param, shape[3].dim_param]
    del g.input[:]
    g.input.append(helper.make_tensor_value_info("gray", TensorProto.FLOAT, [1, 1] + dims))
    rel = reliability[0]
    del g.output[:]
    g.output.extend([
        helper.make_tensor_value_info("descriptor_map", TensorProto.FLOAT, [1, 64, "h8", "w8"]),
        helper.make_tensor_value_info("keypoint_logits", TensorProto.FLOAT, [1, 65, "h8", "w8"]),
        rel,
    ])
    # Shapes inferred for tensors that no longer exist would only mislead.
    keep_info = {i for n in kept for i in list(n.input) + list(n.output)}
    infos = [v for v in g.value_info if v.name in keep_info]
    del g.value_info[:]
    g.value_info.extend(infos)
    onnx.checker.check_model(model)
    # A temporary file beside the model, renamed over it once written whole.
    fd, tmp = tempfile.mkstemp(prefix=os.path.basename(path) + ".", suffix=".tmp",
                               dir=os.path.dirname(os.path.abspath(path)))
    os.close(fd)
    try:
        onnx.save(model, tmp)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    print(f"{path}: trimmed to {len(kept)} nodes; input gray, outputs {', '.join(wanted)}")


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for p in sys.argv[1:]:
        trim(p)


if __name__ == "__main__":
    main()
