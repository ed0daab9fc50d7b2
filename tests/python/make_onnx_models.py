"""Write two tiny ONNX models that follow pntr's plug-in contracts (models/README.md), for the tests.

  tiny_extractor.onnx  image [1,3,H,W] -> keypoints [1,4,2] (fixed pixels), scores [1,4],
                       descriptors [1,4,3] = the image's mean colour plus a distinct offset per keypoint
  tiny_matcher.onnx    kpts0/kpts1/desc0/desc1/size0/size1 -> scores [1,M+1,N+1]:
                       10 * (desc0 . desc1^T - 1), with a dustbin row and column of -100
  tiny_global.onnx     image [1,3,H,W] -> descriptor [1,3]: the mean colour (global-descriptor contract)
  tiny_global_bad.onnx image -> descriptor [1,3,1,1]: breaks that contract (must be refused at load)
Usage: make_onnx_models.py OUT_DIR
"""
import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], producer_name="pntr-tests")
    model.ir_version = 9
    onnx.checker.check_model(model)
    onnx.save(model, path)


def extractor(path):
    kp = numpy_helper.from_array(np.array([[[10, 10], [20, 30], [40, 15], [50, 50]]], np.float32), "kp")
    sc = numpy_helper.from_array(np.array([[0.6, 0.9, 0.8, 0.7]], np.float32), "sc")
    off = numpy_helper.from_array(np.array([[[0, 2, 0], [0, 0, 2], [0, -2, 0], [0, 0, -2]]], np.float32), "off")
    shape = numpy_helper.from_array(np.array([1, 1, 3], np.int64), "shape")
    reps = numpy_helper.from_array(np.array([1, 4, 1], np.int64), "reps")
    nodes = [
        helper.make_node("Identity", ["kp"], ["keypoints"]),
        helper.make_node("Identity", ["sc"], ["scores"]),
        helper.make_node("GlobalAveragePool", ["image"], ["mean"]),
        helper.make_node("Reshape", ["mean", "shape"], ["mean3"]),
        helper.make_node("Tile", ["mean3", "reps"], ["tiled"]),
        helper.make_node("Add", ["tiled", "off"], ["descriptors"]),
    ]
    g = helper.make_graph(
        nodes, "tiny_extractor",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])],
        [helper.make_tensor_value_info("keypoints", TensorProto.FLOAT, [1, 4, 2]),
         helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, 4]),
         helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, [1, 4, 3])],
        [kp, sc, off, shape, reps])
    save(g, path)


def matcher(path):
    ten = numpy_helper.from_array(np.array(10, np.float32), "ten")
    one = numpy_helper.from_array(np.array(1, np.float32), "one")
    pads = numpy_helper.from_array(np.array([0, 0, 0, 0, 1, 1], np.int64), "pads")
    fill = numpy_helper.from_array(np.array(-100, np.float32), "fill")
    nodes = [
        helper.make_node("Transpose", ["desc1"], ["d1t"], perm=[0, 2, 1]),
        helper.make_node("MatMul", ["desc0", "d1t"], ["sim"]),
        helper.make_node("Sub", ["sim", "one"], ["sim1"]),
        helper.make_node("Mul", ["sim1", "ten"], ["logits"]),
        helper.make_node("Pad", ["logits", "pads", "fill"], ["scores"], mode="constant"),
    ]
    f = TensorProto.FLOAT
    g = helper.make_graph(
        nodes, "tiny_matcher",
        [helper.make_tensor_value_info("kpts0", f, [1, "m", 2]), helper.make_tensor_value_info("kpts1", f, [1, "n", 2]),
         helper.make_tensor_value_info("desc0", f, [1, "m", 3]), helper.make_tensor_value_info("desc1", f, [1, "n", 3]),
         helper.make_tensor_value_info("size0", f, [1, 2]), helper.make_tensor_value_info("size1", f, [1, 2])],
        [helper.make_tensor_value_info("scores", f, [1, "m1", "n1"])],
        [ten, one, pads, fill])
    save(g, path)


def global_model(path, flatten):
    nodes = [helper.make_node("GlobalAveragePool", ["image"], ["mean"])]
    if flatten:
        nodes.append(helper.make_node("Flatten", ["mean"], ["descriptor"], axis=1))
        shape = [1, 3]
    else:
        nodes.append(helper.make_node("Identity", ["mean"], ["descriptor"]))
        shape = [1, 3, 1, 1]
    g = helper.make_graph(
        nodes, "tiny_global",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, shape)])
    save(g, path)


if __name__ == "__main__":
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    extractor(os.path.join(out, "tiny_extractor.onnx"))
    matcher(os.path.join(out, "tiny_matcher.onnx"))
    global_model(os.path.join(out, "tiny_global.onnx"), True)
    global_model(os.path.join(out, "tiny_global_bad.onnx"), False)
