"""One rule for what an answer is: causal, lagged and smoothed answers, in the API, JSON, text
and the trace, call a frame "no match" when the map does not know its place (the best place
holds less than ``min_confidence``, or the unmapped place at least as much as it)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.hmm.decision import is_unknown
from sprint_map.localize.localizer import FrameDecision
from sprint_map.localize.trace import read_trace
from sprint_map.map import SprintMap
from tests.helpers.worlds import drive, random_places, road_places

DIM = 32
NOVEL = slice(60, 210)  # the query's frames beyond the map


@pytest.fixture
def world(tmp_path, rng):
    """A map of one road and a query that leaves it for 150 unmapped places, then rejoins."""
    places = road_places(rng, 200, DIM, 0.9)
    path = tmp_path / "m.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.ingest(drive(places, rng, 0.2), name="road")
    query = np.concatenate([drive(places[:60], rng), random_places(rng, 150, DIM),
                            drive(places[100:160], rng)])
    np.save(tmp_path / "q.npy", query)
    return path, query


def _breaks_the_rule(d: FrameDecision, min_confidence: float) -> bool:
    return d.is_match and not d.verified and is_unknown(d.prob, d.novel_prob, min_confidence)


@pytest.mark.parametrize("mode", ["causal", "lag", "smoothed"])
def test_every_answer_follows_the_rule(world, mode):
    path, query = world
    with SprintMap.open(path, readonly=True) as m:
        floor = m.config.hmm.min_confidence
        decisions, _ = m.localize(query, smooth=mode == "smoothed", lag=8 if mode == "lag" else 0)
    assert len(decisions) == len(query)
    assert [d for d in decisions if _breaks_the_rule(d, floor)] == []
    assert sum(d.is_match for d in decisions[:50]) >= 40, mode  # the mapped road is known
    if mode == "smoothed":  # the drive's calibrated unmapped place claims the novel stretch
        novel = decisions[NOVEL]
        assert sum(not d.is_match for d in novel) >= 0.9 * len(novel)
    for d in decisions:  # "no match" names nothing, whatever it was near
        if not d.is_match:
            assert (d.seq_id, d.image_id, d.vertex_id) == (None, None, None)


def test_smoothed_json_text_and_trace_give_the_same_answers(world, tmp_path):
    path, _ = world
    run = CliRunner().invoke(main, ["localize", str(path), str(tmp_path / "q.npy"), "--smooth",
                                    "--json", "-q", "--trace", str(tmp_path / "t.npz")])
    assert run.exit_code == 0, run.output
    answers = json.loads(run.output)["decisions"]
    text = CliRunner().invoke(main, ["localize", str(path), str(tmp_path / "q.npy"),
                                     "--smooth", "-q"])
    assert text.exit_code == 0, text.output
    lines = text.output.splitlines()[: len(answers)]
    trace = read_trace(tmp_path / "t.npz")
    floor = MapConfig(dim=DIM).hmm.min_confidence
    for a, line, seq in zip(answers, lines, trace["final_seq"].tolist(), strict=True):
        known = a["seq_id"] is not None
        assert known == ("no match" not in line) == (seq >= 0), (a, line, seq)
        if known:
            assert not is_unknown(a["prob"], a["novel_prob"], floor) or a["verified"], a
    assert sum(a["seq_id"] is None for a in answers[NOVEL]) >= 0.9 * (NOVEL.stop - NOVEL.start)
