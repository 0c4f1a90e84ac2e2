"""ONNX descriptors (issue 52): the model's output checked before it is normalised, a model's
identity as the digest of every file it loads, and cards and batch axes refused or run in our
words."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from sprint_map.cli.main import main  # noqa: E402
from sprint_map.errors import InputError, InvalidDescriptorError  # noqa: E402
from sprint_map.frontend.descriptors import DescriptorSpec  # noqa: E402
from sprint_map.frontend.onnx_model import onnx_params  # noqa: E402
from sprint_map.map import SprintMap  # noqa: E402
from tests.helpers.onnx_graphs import (  # noqa: E402
    output_model,
    projection_model,
    reference_descriptors,
    with_external_weights,
)


def images(n: int, size=(8, 8), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(n)]


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def drive(folder, frames):
    folder.mkdir()
    for i, image in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:03d}.png"), image)
    return folder


def one_error_line(result, exit_code):
    assert result.exit_code == exit_code, result.output
    assert result.output.startswith("Error: ") and result.output.count("\n") == 1, result.output
    assert "Traceback" not in result.output


# --- the output is checked before it is normalised --------------------------------------------

def test_an_overflowing_output_is_refused_not_normalised_to_zero(tmp_path):
    spec = DescriptorSpec("onnx", onnx_params(output_model(tmp_path / "m.onnx", hazard="scale"),
                                              _card(tmp_path, normalize="l2")))
    with pytest.raises(InvalidDescriptorError, match=r"the model .*m\.onnx gave no descriptor "
                       r"for image 0 of 3 \(element \d+ is .*beyond \+-1e\+15"):
        spec.describe_batch(images(3))


def test_nan_in_one_element_of_one_frame_names_the_model_and_the_frame(tmp_path):
    model = output_model(tmp_path / "m.onnx", hazard="dark")
    made = _cli("init", tmp_path / "map", "--descriptor", "onnx", "--model", model)
    assert made.exit_code == 0, made.output
    frames = [np.full((8, 8, 3), 250, np.uint8) for _ in range(7)]
    frames[5] = np.zeros((8, 8, 3), np.uint8)  # below the mean: log of a negative sum
    result = _cli("ingest", tmp_path / "map", drive(tmp_path / "d", frames), "--name", "a")
    one_error_line(result, InvalidDescriptorError.exit_code)
    assert "frame 5 (005.png)" in result.output and "m.onnx gave no descriptor" in result.output
    assert "element 16 is NaN" in result.output
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        assert m.stats()["sequences"] == 0


def _card(tmp_path, **card):
    path = tmp_path / "card.json"
    path.write_text(json.dumps(card))
    return path


# --- identity: every file the model loads ------------------------------------------------------

def test_external_weights_are_part_of_the_models_identity(tmp_path):
    model = with_external_weights(projection_model(tmp_path / "m.onnx", size=(16, 16), dim=24))
    weights = tmp_path / "m.onnx.data"
    assert weights.is_file()
    made = _cli("init", tmp_path / "map", "--descriptor", "onnx", "--model", model)
    assert made.exit_code == 0, made.output
    frames = images(6, size=(16, 16))
    folder = drive(tmp_path / "d", frames)
    assert _cli("ingest", tmp_path / "map", folder, "--name", "a").exit_code == 0
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        recorded = m.config.descriptor_params["external_data"]
        assert list(recorded) == ["m.onnx.data"] and len(recorded["m.onnx.data"]) == 64
    # other weights, the same graph file: the .onnx digest alone would not notice
    other = with_external_weights(projection_model(tmp_path / "o.onnx", size=(16, 16), dim=24,
                                                   seed=7))
    before = model.read_bytes()
    weights.write_bytes((tmp_path / "o.onnx.data").read_bytes())
    assert model.read_bytes() == before and other.is_file()
    result = _cli("ingest", tmp_path / "map", folder, "--name", "b")
    one_error_line(result, InputError.exit_code)
    assert "different weights in 'm.onnx.data'" in result.output
    weights.unlink()
    result = _cli("ingest", tmp_path / "map", folder, "--name", "b")
    one_error_line(result, InputError.exit_code)
    assert "weights file 'm.onnx.data' is missing" in result.output
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        assert m.stats()["sequences"] == 1


def test_a_model_in_one_file_is_recorded_as_before(tmp_path):
    params = onnx_params(projection_model(tmp_path / "m.onnx"))
    assert "external_data" not in params


def test_a_map_made_before_weights_were_recorded_opens_and_warns(tmp_path):
    model = with_external_weights(projection_model(tmp_path / "m.onnx", size=(16, 16), dim=24))
    params = onnx_params(model)
    del params["external_data"]  # as such a map stores it: the digest of m.onnx only
    from sprint_map.config import MapConfig

    config = MapConfig(dim=24, descriptor="onnx", descriptor_params=params)
    SprintMap.create(tmp_path / "map", config).close()
    folder = drive(tmp_path / "d", images(6, size=(16, 16)))
    result = CliRunner().invoke(main, ["ingest", str(tmp_path / "map"), str(folder)])
    assert result.exit_code == 0, result.output
    assert "weights file(s) m.onnx.data are not verified" in result.output
    located = CliRunner().invoke(main, ["localize", str(tmp_path / "map"), str(folder)])
    assert located.exit_code == 0, located.output
    assert "Warning: " in located.output and "m.onnx.data are not verified" in located.output
    with SprintMap.open(tmp_path / "map", readonly=True) as m:
        want = reference_descriptors(model, [cv2.imread(str(p)) for p in
                                             sorted(folder.glob("*.png"))])
        np.testing.assert_allclose(m.descriptors(0), want, atol=1e-5)


# --- cards and batch axes ------------------------------------------------------------------------

def test_a_card_of_an_absurd_input_size_is_one_error_at_init(tmp_path):
    import onnx

    model = projection_model(tmp_path / "m.onnx")
    graph = onnx.load(str(model))
    dims = graph.graph.input[0].type.tensor_type.shape.dim
    dims[2].dim_param, dims[3].dim_param = "H", "W"
    onnx.save(graph, str(model))
    card = _card(tmp_path, input_size=[2**31, 2**31])
    result = _cli("init", tmp_path / "map", "--descriptor", "onnx", "--model", model,
                  "--model-card", card)
    one_error_line(result, InputError.exit_code)
    assert "input_size [2147483648, 2147483648] is too large" in result.output
    assert not (tmp_path / "map").exists()


def test_a_model_of_a_fixed_batch_of_one_runs_frame_by_frame(tmp_path):
    model = projection_model(tmp_path / "m.onnx", batch=1)
    spec = DescriptorSpec("onnx", onnx_params(model))
    batch = images(5)
    np.testing.assert_allclose(spec.describe_batch(batch), reference_descriptors(model, batch),
                               atol=1e-5)


def test_a_model_of_a_fixed_batch_of_three_is_padded(tmp_path):
    model = projection_model(tmp_path / "m.onnx", batch=3)
    spec = DescriptorSpec("onnx", onnx_params(model))
    batch = images(7)
    np.testing.assert_allclose(spec.describe_batch(batch), reference_descriptors(model, batch),
                               atol=1e-5)


def test_a_model_that_cannot_run_a_batch_is_refused_in_our_words(tmp_path):
    import onnx

    model = projection_model(tmp_path / "m.onnx")
    graph = onnx.load(str(model))
    graph.graph.node[0].op_type = "Reshape"  # the reshape's target: a (1, -1) that 2 images break
    graph.graph.node[0].ClearField("attribute")
    graph.graph.node[0].input.append("one_row")
    graph.graph.initializer.append(onnx.numpy_helper.from_array(np.array([1, -1], np.int64),
                                                                "one_row"))
    onnx.save(graph, str(model))
    result = _cli("init", tmp_path / "map", "--descriptor", "onnx", "--model", model)
    one_error_line(result, InputError.exit_code)
    assert "the model cannot run on a batch of 2 image(s)" in result.output
    assert "ONNXRuntimeError" not in result.output and "Got invalid" not in result.output
