"""ONNX descriptor throughput: frames/s of a ResNet-18-sized graph, batched vs one at a time.

The graph is ResNet-18's (He et al. 2016) built with ``onnx.helper``: a 7x7/2 stem conv, max
pool, four stages of two basic blocks (64, 128, 256, 512 channels; 3x3 convs, projection
shortcuts where the shape changes), global average pooling and a 512 -> 512 linear layer as
the descriptor: 11.7 M weights (random, seeded: speed does not depend on their values), 1.8
GFLOPs at 224 x 224. Batch norm is left out, as an exported model folds it into its convs.

Frames (random 640 x 480 BGR images) are described through
:class:`sprint_map.frontend.descriptors.DescriptorSpec` ``describe_batch`` -- pre-processing
(resize, colour order, mean/std) included -- in batches of ``--batch`` (the baseline: one
frame per call, as a naive per-frame loop would run it). onnxruntime uses every core in both.

    python tools/bench_onnx.py --frames 128 --json onnx.json
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def resnet18(path: Path, size: int = 224, dim: int = 512, seed: int = 0) -> Path:
    """Write ResNet-18 (random weights) as ONNX; returns ``path``."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    nodes: list[Any] = []
    inits: list[Any] = []
    count = [0]

    def name(prefix: str) -> str:
        count[0] += 1
        return f"{prefix}{count[0]}"

    def conv(x: str, cin: int, cout: int, k: int, stride: int, relu: bool) -> str:
        w, b, y = name("w"), name("b"), name("conv")
        inits.append(numpy_helper.from_array(
            (rng.standard_normal((cout, cin, k, k)) * np.sqrt(2 / (cin * k * k))).astype(
                np.float32), w))
        inits.append(numpy_helper.from_array(np.zeros(cout, np.float32), b))
        nodes.append(helper.make_node("Conv", [x, w, b], [y], kernel_shape=[k, k],
                                      strides=[stride, stride], pads=[k // 2] * 4))
        if not relu:
            return y
        r = name("relu")
        nodes.append(helper.make_node("Relu", [y], [r]))
        return r

    def block(x: str, cin: int, cout: int, stride: int) -> str:
        y = conv(conv(x, cin, cout, 3, stride, True), cout, cout, 3, 1, False)
        short = x if stride == 1 and cin == cout else conv(x, cin, cout, 1, stride, False)
        s, r = name("add"), name("relu")
        nodes.append(helper.make_node("Add", [y, short], [s]))
        nodes.append(helper.make_node("Relu", [s], [r]))
        return r

    x = conv("image", 3, 64, 7, 2, True)
    pooled = name("pool")
    nodes.append(helper.make_node("MaxPool", [x], [pooled], kernel_shape=[3, 3], strides=[2, 2],
                                  pads=[1, 1, 1, 1]))
    x, cin = pooled, 64
    for cout, stride in ((64, 1), (128, 2), (256, 2), (512, 2)):
        x = block(block(x, cin, cout, stride), cout, cout, 1)
        cin = cout
    nodes.append(helper.make_node("GlobalAveragePool", [x], ["gap"]))
    nodes.append(helper.make_node("Flatten", ["gap"], ["flat"], axis=1))
    inits.append(numpy_helper.from_array(
        (rng.standard_normal((512, dim)) / np.sqrt(512)).astype(np.float32), "fc"))
    nodes.append(helper.make_node("MatMul", ["flat", "fc"], ["descriptor"]))
    graph = helper.make_graph(
        nodes, "resnet18", [helper.make_tensor_value_info("image", TensorProto.FLOAT,
                                                          ["N", 3, size, size])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, ["N", dim])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def weights(path: Path) -> int:
    import onnx
    from onnx import numpy_helper

    return sum(int(numpy_helper.to_array(t).size) for t in onnx.load(str(path)).graph.initializer)


def run(frames: int, batch: int, seed: int) -> dict[str, Any]:
    from sprint_map.frontend.descriptors import DescriptorSpec
    from sprint_map.frontend.onnx_model import onnx_params

    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, (480, 640, 3), dtype=np.uint8) for _ in range(frames)]
    with tempfile.TemporaryDirectory() as tmp:
        model = resnet18(Path(tmp) / "resnet18.onnx")
        spec = DescriptorSpec("onnx", onnx_params(model))
        spec.describe_batch(images[:2])  # session loaded, warmed up
        rows: dict[str, Any] = {"weights": weights(model), "cores": os.cpu_count(),
                                "frames": frames, "batch": batch}
        started = time.perf_counter()
        for image in images:
            spec.describe_batch([image])
        single = time.perf_counter() - started
        started = time.perf_counter()
        for start in range(0, frames, batch):
            spec.describe_batch(images[start:start + batch])
        batched = time.perf_counter() - started
    rows["one_at_a_time_fps"] = round(frames / single, 1)
    rows["batched_fps"] = round(frames / batched, 1)
    rows["speedup"] = round(single / batched, 2)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=128)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="Also write the results here.")
    args = parser.parse_args()
    out = run(args.frames, args.batch, args.seed)
    print(f"ResNet-18-sized graph ({out['weights'] / 1e6:.1f} M weights, 224 x 224), "
          f"{out['frames']} frames of 640 x 480, {out['cores']} cores")
    print("| mode | frames/s |\n|---|---|")
    print(f"| one at a time | {out['one_at_a_time_fps']} |")
    print(f"| batched ({out['batch']}) | {out['batched_fps']} |")
    print(f"batched / one at a time: {out['speedup']}x")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
