"""ONNX descriptors on small graphs built here: card and defaults, batching, the stored
digest, and the models and cards that are refused."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from sprint_map.cli.main import main  # noqa: E402
from sprint_map.errors import InputError  # noqa: E402
from sprint_map.frontend.descriptors import DescriptorSpec  # noqa: E402
from sprint_map.frontend.onnx_model import onnx_params  # noqa: E402
from sprint_map.map import SprintMap  # noqa: E402
from tests.helpers.onnx_graphs import projection_model, reference_descriptors  # noqa: E402


def images(n: int, size=(8, 8), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(n)]


def test_defaults_rgb_imagenet_l2(tmp_path):
    model = projection_model(tmp_path / "m.onnx")
    params = onnx_params(model)
    assert (params["input_size"], params["channels"], params["normalize"], params["dim"]) == (
        [8, 8], "rgb", "l2", 16)
    spec = DescriptorSpec("onnx", params)
    batch = images(40)  # more than one run of 32
    got = spec.describe_batch(batch)
    np.testing.assert_allclose(got, reference_descriptors(model, batch), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(spec.describe(batch[3]), got[3], atol=1e-6)  # batched == single


def test_card_beside_the_model_and_on_the_command_line(tmp_path):
    model = projection_model(tmp_path / "m.onnx")
    card = {"input_size": [8, 8], "channels": "bgr", "mean": [0.5, 0.5, 0.5],
            "std": [0.25, 0.5, 1.0], "normalize": "none"}
    (tmp_path / "m.card.json").write_text(json.dumps(card))
    spec = DescriptorSpec("onnx", onnx_params(model))  # found beside it
    batch = images(5)
    want = reference_descriptors(model, batch, channels="bgr", mean=card["mean"],
                                 std=card["std"], l2=False)
    np.testing.assert_allclose(spec.describe_batch(batch), want, rtol=1e-5, atol=1e-4)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**card, "channels": "rgb"}))
    rgb = DescriptorSpec("onnx", onnx_params(model, other))
    assert not np.allclose(rgb.describe_batch(batch), want, atol=1e-3)


def test_images_of_another_size_are_resized(tmp_path):
    model = projection_model(tmp_path / "m.onnx", size=(8, 8))
    spec = DescriptorSpec("onnx", onnx_params(model))
    big = [cv2.resize(im, (32, 32), interpolation=cv2.INTER_NEAREST) for im in images(3)]
    np.testing.assert_allclose(spec.describe_batch(big),
                               reference_descriptors(model, images(3)), atol=1e-5)


def test_dynamic_input_needs_a_card(tmp_path):
    import onnx

    model = projection_model(tmp_path / "m.onnx")
    graph = onnx.load(str(model))
    dims = graph.graph.input[0].type.tensor_type.shape.dim
    dims[2].dim_param, dims[3].dim_param = "H", "W"
    onnx.save(graph, str(model))
    with pytest.raises(InputError, match="input size is not fixed"):
        onnx_params(model)
    card = tmp_path / "card.json"
    card.write_text(json.dumps({"input_size": [8, 8]}))
    assert onnx_params(model, card)["dim"] == 16


def test_trailing_singleton_axes_are_one_vector(tmp_path):
    model = projection_model(tmp_path / "m.onnx", output="column")
    assert onnx_params(model)["dim"] == 16


@pytest.mark.parametrize(("make", "card", "message"), [
    ({"output": "map"}, None, r"output has shape \[2, 3, 8, 8\] for 2 images; expected one "
                              r"vector per image"),
    ({}, {"input_size": [16, 16]}, r"input_size \[16, 16\] but the model takes 8x8 images"),
    ({}, {"channels": "gray"}, r"channels 'gray' give 1 channel\(s\), the model takes 3"),
    ({}, {"mean": [0.5, 0.5]}, "mean must be 3 finite numbers"),
    ({}, {"std": [0, 1, 1]}, "std must be > 0"),
    ({}, {"normalize": "l1"}, "normalize must be l2 or none"),
    ({}, {"colour": "rgb"}, "unknown model-card key"),
])
def test_refused_models_and_cards(tmp_path, make, card, message):
    model = projection_model(tmp_path / "m.onnx", **make)
    path = None
    if card is not None:
        path = tmp_path / "card.json"
        path.write_text(json.dumps(card))
    with pytest.raises(InputError, match=message):
        onnx_params(model, path)


def test_not_a_model(tmp_path):
    (tmp_path / "m.onnx").write_bytes(b"not a model")
    with pytest.raises(InputError, match="cannot load ONNX model"):
        onnx_params(tmp_path / "m.onnx")


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_cli_map_keeps_the_digest_and_refuses_another_model(tmp_path):
    model = projection_model(tmp_path / "m.onnx", size=(16, 16), dim=24)
    folder = tmp_path / "drive"
    folder.mkdir()
    for i, image in enumerate(images(6, size=(16, 16))):
        cv2.imwrite(str(folder / f"{i:03d}.png"), image)
    made = _cli("init", tmp_path / "map", "--descriptor", "onnx", "--model", model)
    assert made.exit_code == 0, made.output
    assert "(onnx, dim 24)" in made.output
    assert _cli("ingest", tmp_path / "map", folder, "--name", "a").exit_code == 0
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        params = m.config.descriptor_params
        assert len(params["digest"]) == 64 and m.config.dim == 24
        want = reference_descriptors(model, [cv2.imread(str(p)) for p in
                                             sorted(folder.glob("*.png"))])
        np.testing.assert_allclose(m.descriptors(0), want, atol=1e-5)
    projection_model(model, size=(16, 16), dim=24, seed=7)  # another model, same path
    result = _cli("ingest", tmp_path / "map", folder, "--name", "b")
    assert result.exit_code == InputError.exit_code
    assert "a different model" in result.output and result.output.count("\n") == 1
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        assert m.stats()["sequences"] == 1


@pytest.mark.parametrize(("args", "message"), [
    (["--descriptor", "onnx"], "--descriptor onnx needs --model FILE"),
    (["--descriptor", "hog", "--model", "m.onnx"], "--model and --model-card are for"),
])
def test_cli_option_errors(tmp_path, args, message):
    result = _cli("init", tmp_path / "map", *args)
    assert result.exit_code == InputError.exit_code and message in result.output
    assert not (tmp_path / "map").exists()


@pytest.mark.parametrize(("make", "card", "message"), [
    ({"output": "map"}, None, "expected one vector per image"),
    ({}, {"input_size": [4, 4]}, "but the model takes 8x8 images"),
])
def test_cli_refused_model_or_card_creates_no_map(tmp_path, make, card, message):
    model = projection_model(tmp_path / "m.onnx", **make)
    args = ["init", tmp_path / "map", "--descriptor", "onnx", "--model", model]
    if card is not None:
        (tmp_path / "c.json").write_text(json.dumps(card))
        args += ["--model-card", tmp_path / "c.json"]
    result = _cli(*args)
    assert result.exit_code == InputError.exit_code
    assert message in result.output and result.output.count("\n") == 1
    assert not (tmp_path / "map").exists()
