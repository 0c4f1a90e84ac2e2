"""Export public VPR global-descriptor models to ONNX, each with its model card.

Run on a machine with the internet and PyTorch (``pip install torch torchvision onnx``); the
tests never run it. Each model is fetched through ``torch.hub`` from its authors' repository,
traced at a fixed input size with a dynamic batch axis, checked against PyTorch on a random
batch, and written as ``OUT/<name>.onnx`` with ``OUT/<name>.card.json`` beside it (what
``sprint-map init MAP --descriptor onnx --model OUT/<name>.onnx`` reads)::

    python tools/export_onnx_models.py --out models/ cosplace-r50-2048 eigenplaces-r50-2048
    python tools/export_onnx_models.py --list

The input sizes are the ones the authors evaluate at (a square crop for the DINOv2 models,
whose patch size is 14). All take RGB with ImageNet mean/std and give an L2-normalised vector;
the cards say so (``normalize: l2`` again is harmless). Licences are the models' own: see each
repository before using its weights.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

IMAGENET = {"mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225]}


@dataclass(frozen=True)
class Entry:
    """One public model: its ``torch.hub`` repository, entry point and arguments."""

    repo: str
    entry: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    input_size: tuple[int, int] = (480, 640)
    notes: str = ""


MODELS = {
    "cosplace-r50-2048": Entry("gmberton/cosplace", "get_trained_model",
                               {"backbone": "ResNet50", "fc_output_dim": 2048},
                               notes="CosPlace (Berton et al., CVPR 2022)"),
    "cosplace-r18-512": Entry("gmberton/cosplace", "get_trained_model",
                              {"backbone": "ResNet18", "fc_output_dim": 512},
                              notes="CosPlace, the small one"),
    "eigenplaces-r50-2048": Entry("gmberton/eigenplaces", "get_trained_model",
                                  {"backbone": "ResNet50", "fc_output_dim": 2048},
                                  notes="EigenPlaces (Berton et al., ICCV 2023)"),
    "salad-dinov2": Entry("serizba/salad", "dinov2_salad", {}, (322, 322),
                          "SALAD (Izquierdo & Civera, CVPR 2024), 8448 dims"),
    "boq-r50": Entry("amaralibey/bag-of-queries", "get_trained_boq",
                     {"backbone_name": "resnet50", "output_dim": 16384}, (384, 384),
                     "Bag-of-Queries (Ali-bey et al., CVPR 2024), ResNet-50"),
    "boq-dinov2": Entry("amaralibey/bag-of-queries", "get_trained_boq",
                        {"backbone_name": "dinov2", "output_dim": 12288}, (322, 322),
                        "Bag-of-Queries, DINOv2 backbone"),
    "mixvpr-r50-4096": Entry("jarvisyjw/MixVPR", "get_trained_model", {}, (320, 320),
                             "MixVPR (Ali-bey et al., WACV 2023) through a community hub "
                             "entry; check the repository first"),
    "netvlad-vgg16": Entry("gmberton/VPR-methods-evaluation", "netvlad", {}, (480, 640),
                           "NetVLAD (Arandjelovic et al., CVPR 2016) as the VPR evaluation "
                           "code ports it; check the repository first"),
}


def export(name: str, entry: Entry, out: Path, opset: int = 17) -> Path:
    """Export one model and its card; returns the ``.onnx`` path."""
    import numpy as np
    import torch

    model = torch.hub.load(entry.repo, entry.entry, trust_repo=True, **entry.kwargs).eval()
    height, width = entry.input_size
    dummy = torch.randn(2, 3, height, width)
    path = out / f"{name}.onnx"
    torch.onnx.export(model, dummy, str(path), input_names=["image"],
                      output_names=["descriptor"], opset_version=opset,
                      dynamic_axes={"image": {0: "N"}, "descriptor": {0: "N"}})
    with torch.no_grad():
        want = model(dummy)
        want = (want[0] if isinstance(want, (tuple, list)) else want).reshape(2, -1).numpy()
    import onnxruntime

    got = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        None, {"image": dummy.numpy()})[0].reshape(2, -1)
    if not np.allclose(got, want, atol=1e-3, rtol=1e-3):
        raise SystemExit(f"{name}: ONNX output differs from PyTorch (max "
                         f"{float(np.abs(got - want).max()):.2e})")
    card = {"input_size": [height, width], "channels": "rgb", **IMAGENET, "normalize": "l2",
            "name": name, "source": f"torch.hub {entry.repo}:{entry.entry} {entry.kwargs}",
            "notes": entry.notes}
    (out / f"{name}.card.json").write_text(json.dumps(card, indent=2) + "\n")
    print(f"wrote {path} ({want.shape[1]} dims, {height}x{width}) and its card")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="Models to export (default: all).")
    parser.add_argument("--out", type=Path, default=Path("models"))
    parser.add_argument("--list", action="store_true", help="List the models and exit.")
    args = parser.parse_args()
    if args.list:
        for name, entry in MODELS.items():
            print(f"{name:22} {entry.repo}:{entry.entry}  {entry.notes}")
        return
    unknown = [n for n in args.names if n not in MODELS]
    if unknown:
        raise SystemExit(f"unknown model(s) {', '.join(unknown)}; see --list")
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.names or list(MODELS):
        export(name, MODELS[name], args.out)


if __name__ == "__main__":
    main()
