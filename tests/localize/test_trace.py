"""Localisation traces: what is recorded per frame, bounded, written atomically, read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.errors import InputError
from sprint_map.localize.trace import FORMAT, VERSION, TraceRecorder, read_trace
from sprint_map.map import SprintMap

pytestmark = pytest.mark.road_map(drives=3, frames=120)


@pytest.fixture
def query(tmp_path, rng, road_map):
    """A drive over the road map's road, saved as ``q.npy``."""
    rows, _ = road_map.road.drive(rng, 100, start=10)
    np.save(tmp_path / "q.npy", rows)
    return tmp_path / "q.npy"


@pytest.mark.parametrize("top_n", [1, 5])
def test_trace_records_each_frame_as_the_localizer_decided(tmp_path, road_map, query, top_n):
    path = road_map.path
    with SprintMap.open(path, readonly=True) as m:
        loc = m.localizer()
        rec = TraceRecorder(m, top_n=top_n)
        rec.attach(loc)
        decisions = loc.localize(np.load(query))
        rec.save(tmp_path / "t.npz")
    t = read_trace(tmp_path / "t.npz")
    n = len(decisions)
    assert t.meta["format"] == FORMAT and t.meta["version"] == VERSION and t.frames == n
    assert t["top_seq"].shape == (n, top_n) and t["hit_seq"].shape == (n, m.config.hmm.k)
    assert [(-1 if d.seq_id is None else d.seq_id) for d in decisions] == t["dec_seq"].tolist()
    np.testing.assert_allclose(t["dec_prob"], [d.prob for d in decisions], rtol=1e-6)
    # the top states are the belief's largest, descending, and probabilities
    probs = t["top_prob"]
    assert (np.diff(probs, axis=1) <= 0).all() and (probs >= 0).all() and (probs <= 1).all()
    assert (probs.sum(axis=1) <= 1 + 1e-5).all()
    # most frames are matched, and a match's sequence holds belief among the top states
    matched = t["dec_seq"] >= 0
    assert matched.mean() > 0.5
    assert np.mean([t["dec_seq"][i] in t["top_seq"][i] for i in np.flatnonzero(matched)]) > 0.9
    # hits resolve to (seq, image) consistently with the vertex ids
    with SprintMap.open(path, readonly=True) as m:
        v = t["hit_vertex"][0]
        assert [tuple(x) for x in m.store.locate(v[v >= 0])] == list(
            zip(t["hit_seq"][0][v >= 0].tolist(), t["hit_image"][0][v >= 0].tolist(), strict=True))
    # active components with their mass, once the filter has started
    comps, mass = t.active(n - 1)
    assert len(comps) >= 1 and 0 < mass.sum() <= 1 + 1e-5
    assert (t["n_active_vertices"][1:] > 0).all()


def test_localize_and_ingest_write_traces_from_the_cli(tmp_path, road_map, query):
    path = road_map.path
    runner = CliRunner()
    out = runner.invoke(main, ["localize", str(path), str(query), "--smooth", "--json", "-q",
                               "--trace", str(tmp_path / "loc.npz")])
    assert out.exit_code == 0, out.output
    decisions = json.loads(out.output)["decisions"]
    t = read_trace(tmp_path / "loc.npz")
    assert t.meta["command"] == "localize" and t.meta["smoothed"] is True
    assert t["final_seq"].tolist() == [-1 if d["seq_id"] is None else d["seq_id"]
                                       for d in decisions]
    out = runner.invoke(main, ["ingest", str(path), str(query), "--name", "q", "--json", "-q",
                               "--trace", str(tmp_path / "ing.npz")])
    assert out.exit_code == 0, out.output
    result = json.loads(out.output)
    t = read_trace(tmp_path / "ing.npz")
    assert t.meta["seq_id"] == result["seq_id"] and t.frames == result["frames"]
    assert t["merged"].tolist() == [d["merged"] for d in result["decisions"]]
    assert t["merged"].sum() == result["edges_added"] // 2 > 0  # both ways
    assert not list(tmp_path.glob("*.partial"))


def test_a_file_that_is_not_a_trace_is_one_input_error(tmp_path):
    (tmp_path / "x.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a sprint-map trace"):
        read_trace(tmp_path / "x.npz")
    np.savez(tmp_path / "y.npz", meta=np.array(json.dumps({"format": FORMAT,
                                                             "version": VERSION + 1})))
    with pytest.raises(InputError, match="newer"):
        read_trace(tmp_path / "y.npz")
