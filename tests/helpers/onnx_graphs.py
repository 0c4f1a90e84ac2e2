"""Small ONNX graphs built with the onnx package's helper API (no download)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def projection_model(path: Path, *, size: tuple[int, int] = (8, 8), channels: int = 3,
                     dim: int = 16, seed: int = 0, batch: int | str = "N",
                     output: str = "vector") -> Path:
    """``(N, C, H, W) -> Flatten -> MatMul(W) -> (N, dim)``; ``output="map"`` keeps the input
    image as the output (not one vector per image); ``output="column"`` gives (N, dim, 1, 1)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    h, w = size
    rng = np.random.default_rng(seed)
    weight = rng.standard_normal((channels * h * w, dim)).astype(np.float32)
    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [batch, channels, h, w])
    nodes = [helper.make_node("Flatten", ["image"], ["flat"], axis=1),
             helper.make_node("MatMul", ["flat", "W"], ["desc"])]
    out_shape: list[int | str] = [batch, dim]
    if output == "map":
        nodes = [helper.make_node("Identity", ["image"], ["desc"])]
        out_shape = [batch, channels, h, w]
    elif output == "column":
        nodes.append(helper.make_node("Reshape", ["desc", "shape"], ["col"]))
        out_shape = [batch, dim, 1, 1]
    final = "col" if output == "column" else "desc"
    y = helper.make_tensor_value_info(final, TensorProto.FLOAT, out_shape)
    inits = [numpy_helper.from_array(weight, "W")] if output != "map" else []
    if output == "column":
        inits.append(numpy_helper.from_array(np.array([-1, dim, 1, 1], np.int64), "shape"))
    graph = helper.make_graph(nodes, "projection", [x], [y], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def reference_descriptors(path: Path, images: list[np.ndarray], *, channels: str = "rgb",
                          mean=(0.485, 0.456, 0.406), std=(0.229, 0.224, 0.225),
                          l2: bool = True) -> np.ndarray:
    """What the projection model gives for BGR ``images`` already at its input size, computed
    with numpy from the stored weight (a reference independent of the map's pre-processing)."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    weight = numpy_helper.to_array(model.graph.initializer[0])
    rows = []
    for image in images:
        pixels = image[:, :, ::-1] if channels == "rgb" else image
        data = (pixels.astype(np.float32) / 255.0 - np.float32(mean)) / np.float32(std)
        rows.append(data.transpose(2, 0, 1).reshape(-1) @ weight)
    out = np.stack(rows)
    if l2:
        out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.astype(np.float32)


def output_model(path: Path, *, hazard: str, size: tuple[int, int] = (8, 8), dim: int = 16,
                 seed: int = 0) -> Path:
    """The projection model with a broken output: ``hazard="scale"`` multiplies it by 1e30
    (finite in float32, its norm is not); ``hazard="dark"`` appends ``log(sum of the
    normalised pixels)``, NaN for a dark image only (its pixels lie below the mean)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    h, w = size
    weight = np.random.default_rng(seed).standard_normal((3 * h * w, dim)).astype(np.float32)
    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, h, w])
    nodes = [helper.make_node("Flatten", ["image"], ["flat"], axis=1),
             helper.make_node("MatMul", ["flat", "W"], ["desc"])]
    inits = [numpy_helper.from_array(weight, "W")]
    if hazard == "scale":
        nodes.append(helper.make_node("Mul", ["desc", "big"], ["out"]))
        inits.append(numpy_helper.from_array(np.array(1e30, np.float32), "big"))
        out_dim = dim
    else:
        nodes += [helper.make_node("ReduceSum", ["flat", "axes"], ["total"], keepdims=1),
                  helper.make_node("Log", ["total"], ["log"]),
                  helper.make_node("Concat", ["desc", "log"], ["out"], axis=1)]
        inits.append(numpy_helper.from_array(np.array([1], np.int64), "axes"))
        out_dim = dim + 1
    y = helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", out_dim])
    graph = helper.make_graph(nodes, "hazard", [x], [y], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def with_external_weights(path: Path) -> Path:
    """Re-save the model at ``path`` with its weights in ``<name>.data`` beside it."""
    import onnx

    model = onnx.load(str(path))
    onnx.save(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True,
              location=path.name + ".data", size_threshold=0)
    return path
