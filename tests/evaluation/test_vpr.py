"""eval --layout vpr: names, order, recall@N against a brute-force reference."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from sprint_map.cli.main import main
from sprint_map.errors import InputError
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.vpr import VprDataset, parse_vpr_name
from tests.helpers.vpr import make_vpr_dataset, vpr_name


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def brute_force_recall(data: VprDataset, radius: float) -> dict[str, float]:
    """k-NN recall@N with numpy: HoG of every image, exact L2 ranking, UTM radius."""
    hog = DescriptorSpec("hog")
    db = hog.describe_batch([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in data.database])
    q = hog.describe_batch([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in data.queries])
    dist = ((q[:, None, :] - db[None, :, :]) ** 2).sum(-1)
    ranked = np.argsort(dist, axis=1, kind="stable")
    pos = cKDTree(data.database_utm).query_ball_point(data.queries_utm, radius)
    has = [i for i, p in enumerate(pos) if p]
    return {f"recall@{n}": round(sum(bool(set(ranked[i, :n]) & set(pos[i])) for i in has)
                                 / len(has), 4) for n in (1, 5, 10, 20)}


@pytest.mark.parametrize("radius", [8.0, 25.0])
def test_knn_recall_equals_brute_force(tmp_path, radius):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=40, spacing_m=6.0, noise=35.0,
                            query_every=1)
    result = _cli("eval", root, "--layout", "vpr", "--radius", radius, "--out", tmp_path / "o",
                  "-q")
    assert result.exit_code == 0, result.output
    out = json.loads((tmp_path / "o" / "results.json").read_text())
    want = brute_force_recall(VprDataset.open(root), radius)
    assert out["methods"]["knn"] == want
    assert 0 < want["recall@1"] < 1  # a data set on which ranking matters
    assert set(out["methods"]["sprint"]) == {"recall@1", "recall@5", "recall@10", "recall@20"}
    assert out["order"] == {"database": "timestamp", "queries": "file name"}
    assert out["radius_m"] == radius and out["utm_zone"] == "32N"


def test_timestamp_order_and_file_name_order(tmp_path):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=6)
    data = VprDataset.open(root)
    stamps = [parse_vpr_name(p).timestamp for p in data.database]
    assert stamps == sorted(stamps)  # names sort the other way (eastings decrease)
    assert sorted(p.name for p in data.database) != [p.name for p in data.database]
    assert data.queries == sorted(data.queries, key=lambda p: p.name)


def test_sprint_on_the_sequence(tmp_path):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=40, spacing_m=6.0, noise=35.0,
                            query_every=1)
    assert _cli("eval", root, "--layout", "vpr", "--out", tmp_path / "o", "-q").exit_code == 0
    out = json.loads((tmp_path / "o" / "results.json").read_text())
    sprint, knn = out["methods"]["sprint"], out["methods"]["knn"]
    assert sprint["recall@1"] > knn["recall@1"]  # the sequence helps on this route
    assert all(sprint[f"recall@{n}"] <= sprint[f"recall@{m}"] for n, m in ((1, 5), (5, 10)))


def test_ingest_takes_positions_from_the_names(tmp_path):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=5)
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    assert _cli("ingest", tmp_path / "m", root / "database").exit_code == 0
    assert _cli("export", tmp_path / "m", "--csv", tmp_path / "csv").exit_code == 0
    rows = (tmp_path / "csv" / "vertices.csv").read_text().splitlines()[1:]
    xy = np.array([[float(v) for v in r.split(",")[2:4]] for r in rows])
    data = VprDataset.open(root)
    np.testing.assert_allclose(xy, data.database_utm, atol=0.01)  # the names' UTM, same zone


@pytest.mark.parametrize(("name", "message"), [
    ("img001.jpg", None),  # not a VPR name at all: a plain folder, no error at ingest
    ("@597000.00@6643000.00@75@V@59.9@10.7@p@0@0@0@0@0@@@.jpg", "UTM zone"),
    ("@east@north@32@V@59.9@10.7@p@0@0@0@0@0@@@.jpg", "no UTM easting"),
    ("@597000.00@6643000.00@32.jpg", "not a VPR-layout name"),
])
def test_non_utm_names_are_one_line_errors(tmp_path, name, message):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=4)
    image = cv2.imread(str(next((root / "queries").iterdir())))
    cv2.imwrite(str(root / "queries" / name), image)
    result = _cli("eval", root, "--layout", "vpr", "--out", tmp_path / "o", "-q")
    if message is None:
        assert result.exit_code == InputError.exit_code  # mixed with @-names: not parseable
        assert "not a VPR-layout name" in result.output
        return
    assert result.exit_code == InputError.exit_code and message in result.output
    assert result.output.count("\n") == 1 and name[:8] in result.output


def test_not_a_vpr_folder(tmp_path):
    (tmp_path / "x").mkdir()
    result = _cli("eval", tmp_path / "x", "--layout", "vpr", "--out", tmp_path / "o")
    assert result.exit_code == InputError.exit_code
    assert "no database/ and queries/" in result.output


def test_benchmark_download_layout(tmp_path):
    root = make_vpr_dataset(tmp_path / "pitts" / "images" / "test", n_places=4)
    assert VprDataset.open(tmp_path / "pitts").database[0].parent == root / "database"
    assert os.path.basename(vpr_name(1.0, 2.0)).count("@") == 15


def test_vpr_with_an_onnx_model(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from tests.helpers.onnx_graphs import projection_model

    model = projection_model(tmp_path / "m.onnx", size=(16, 16), dim=32)
    root = make_vpr_dataset(tmp_path / "vpr", n_places=12, query_every=1)
    result = _cli("eval", root, "--layout", "vpr", "--model", model, "--out", tmp_path / "o",
                  "-q")
    assert result.exit_code == 0, result.output
    out = json.loads((tmp_path / "o" / "results.json").read_text())
    assert (out["descriptor"], out["dim"]) == ("onnx", 32)
    assert 0 < out["methods"]["knn"]["recall@20"] <= 1


def test_prefixed_names_are_ordered_and_placed_alike_by_the_map_and_the_data_set(tmp_path):
    """``img059@...`` names (a prefix before the first ``@``): the map's vertices and the data
    set take the same frame order (timestamps), so recall is that of the plain names; the
    order results.json reports is the one SPRINT streamed the queries in."""
    plain = make_vpr_dataset(tmp_path / "plain", n_places=40, spacing_m=6.0, noise=35.0,
                             query_every=1)
    prefixed = make_vpr_dataset(tmp_path / "prefixed", n_places=40, spacing_m=6.0, noise=35.0,
                                query_every=1, prefix=True)
    out = {}
    for name, root in (("plain", plain), ("prefixed", prefixed)):
        result = _cli("eval", root, "--layout", "vpr", "--out", tmp_path / f"o-{name}", "-q")
        assert result.exit_code == 0, result.output
        out[name] = json.loads((tmp_path / f"o-{name}" / "results.json").read_text())
    assert out["prefixed"]["methods"] == out["plain"]["methods"]
    assert out["prefixed"]["methods"]["knn"]["recall@1"] > 0.5
    assert out["prefixed"]["order"] == {"database": "timestamp", "queries": "file name"}
    # the map builder's own view of the folder: the same order and the names' positions
    from sprint_map.frontend.sources import open_source

    data = VprDataset.open(prefixed)
    source = open_source(prefixed / "database", DescriptorSpec("hog"))
    assert source.files == data.database and source.order == "timestamp"
    assert source.positions is not None and len(source.positions.xy) == len(data.database)


def test_map_config_works_with_the_vpr_layout(tmp_path):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=12)
    result = _cli("eval", root, "--layout", "vpr", "--out", tmp_path / "o", "-q",
                  "--map-config", "index_type=flat", "--map-config", "merge_min_run=5")
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "o" / "results.json").read_text())["database"] == 12


@pytest.mark.parametrize("layout", ["vpr", "traversals"])
@pytest.mark.parametrize("radius", ["-1", "nan", "inf", "-inf"])
def test_a_radius_that_is_no_distance_is_one_error(tmp_path, layout, radius):
    root = make_vpr_dataset(tmp_path / "vpr", n_places=6)
    result = _cli("eval", root, "--layout", layout, "--radius", radius, "--out",
                  tmp_path / "o", "-q")
    assert result.exit_code == InputError.exit_code, result.output
    assert result.output.startswith("Error: --radius must be a finite number of metres")
    assert result.output.count("\n") == 1
    assert not (tmp_path / "o").exists()
