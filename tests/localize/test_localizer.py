"""Localise-then-merge through the facade: temporal inference against k-NN, merges, streaming."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import DescriptorShapeError, DuplicateNameError
from sprint_map.localize.localizer import FrameDecision, Localizer
from sprint_map.map import SprintMap
from sprint_map.merge.commit import merge_edges
from sprint_map.merge.rule import MergeRule, select_merges
from tests.helpers.worlds import road_places, traverse, unit

DIM = 48


@pytest.fixture
def world(rng):
    """Appearance of 400 places along one long road; neighbours look alike (aliasing)."""
    return road_places(rng, 400, DIM, corr=0.95)


def test_temporal_inference_beats_knn_and_merges(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        places_of = {}
        for i in range(3):
            desc, places = traverse(rng, world, 0, 300, noise=1.5)
            result = m.ingest(desc, name=f"drive-{i}")
            places_of[result.added.sequence.seq_id] = places
        query, truth = traverse(rng, world, 20, 250, noise=1.5)
        decisions, timing = m.localize(query)
        _, ids = m.search(query, 1)
        located = m.store.locate(ids[:, 0])
        knn = np.mean([abs(places_of[s][i] - t) <= 2 for (s, i), t in zip(located, truth, strict=True)])
        sprint = np.mean([d.is_match and abs(places_of[d.seq_id][d.image_id] - t) <= 2
                          for d, t in zip(decisions, truth, strict=True)])
        # k-NN@1 is about 0.35 on this data, SPRINT about 0.7 (seed-dependent).
        assert sprint > knn + 0.2, (sprint, knn)
        assert sprint > 0.55
        # Merges joined the drives into one component through confident decisions.
        assert len(m.components()) == 1
        assert m.stats()["edges"] > 0
        assert timing.frames == len(query)
        assert 0 < max(timing.active_vertices) <= m.stats()["vertices"]


def test_novel_place_is_mostly_no_match(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        desc, _ = traverse(rng, world, 0, 200, noise=0.3)
        m.add_sequence(desc)
        novel = unit(rng.standard_normal((120, DIM)))  # a street nobody drove
        decisions, _ = m.localize(novel)
    # Random frames still hit neighbouring (alike) places now and then: most, not all.
    assert np.mean([not d.is_match for d in decisions[10:]]) > 0.7


def test_first_sequence_of_an_empty_map_is_added_directly(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        desc, _ = traverse(rng, world, 0, 50, noise=0.3)
        result = m.ingest(desc)
        assert result.decisions == [] and result.added.edges_added == 0
        decisions, _ = m.localize(desc[:10])  # the map now answers for its own drive
        assert all(d.seq_id == 0 for d in decisions[2:])


def test_no_merge_appends_without_edges(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        a, _ = traverse(rng, world, 0, 80, noise=0.3)
        m.ingest(a)
        result = m.ingest(a, name="again", merge=False)
        assert result.decisions == [] and result.added.edges_added == 0
        assert len(m.components()) == 2


def test_streaming_step_equals_batch_localize(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        a, _ = traverse(rng, world, 0, 150, noise=0.3)
        m.add_sequence(a)
        q, _ = traverse(rng, world, 5, 100, noise=0.3)
        batch, _ = m.localize(q)
        loc = m.localizer()
        streamed = [loc.step(row) for row in q]
    assert [(d.frame, d.seq_id, d.image_id) for d in streamed] == [
        (d.frame, d.seq_id, d.image_id) for d in batch]
    np.testing.assert_allclose([d.prob for d in streamed], [d.prob for d in batch], rtol=1e-9)


def test_ingest_streams_batches_and_rolls_back_on_bad_batch(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        a, _ = traverse(rng, world, 0, 100, noise=0.3)
        m.ingest(iter([a[:40], a[40:]]), name="streamed")
        assert m.sequence(0).length == 100
        np.testing.assert_array_equal(m.descriptors(0), a)
        bad = np.zeros((5, DIM + 1), np.float32)
        with pytest.raises(DescriptorShapeError):
            m.ingest(iter([a[:30], bad]), name="broken")
        with pytest.raises(DuplicateNameError):  # (the same content again is a retry)
            m.ingest(a[:50], name="streamed")
        assert m.stats() == {"sequences": 1, "vertices": 100, "edges": 0, "components": 1}
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        assert m.check().ok


def test_localize_overrides_and_read_only(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        a, _ = traverse(rng, world, 0, 60, noise=0.3)
        m.add_sequence(a)
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        decisions, _ = m.localize(a[:20], k=3, window=(0.5, 0.5))
        assert len(decisions) == 20
        assert m.localizer(k=3).config.k == 3


@pytest.mark.parametrize(("both", "expected"), [(True, 4), (False, 2)])
def test_merge_edges_from_confident_decisions(both, expected):
    decisions = [
        FrameDecision(0, 3, 7, 0.9, 100),
        FrameDecision(1, None, None, 0.95),  # no match: never an edge
        FrameDecision(2, 3, 9, 0.4, 102),  # below the threshold
        FrameDecision(3, 4, 1, 0.5, 200),
    ]
    merged = select_merges(decisions, MergeRule.permissive(threshold=0.5))
    assert merged.tolist() == [True, False, False, True]
    edges = merge_edges(decisions, merged, both_ways=both)
    assert len(edges) == expected
    assert edges[0].src == (None, 0) and edges[0].dst == (3, 7) and edges[0].frame == 0
    if both:
        assert edges[1].src == (3, 7) and edges[1].dst == (None, 0)


def test_merge_rule_needs_neighbours_that_agree():
    along = [FrameDecision(i, 2, 10 + i, 0.9) for i in range(7)]
    along[3] = FrameDecision(3, 5, 80, 0.99)  # a jump to another drive
    along[5] = FrameDecision(5, None, None, 0.1)
    rule = MergeRule.permissive(threshold=0.5, window=2, min_agree=2)
    # (the last frame has one agreeing neighbour left: 4; 5 is no match)
    assert select_merges(along, rule).tolist() == [True, True, True, False, True, False, False]
    # Not novel: a decision the filter thinks unmapped is not merged however confident.
    novel = [FrameDecision(i, 2, 10 + i, 0.9, novel_prob=0.6 if i == 1 else 0.0)
             for i in range(3)]
    assert select_merges(novel, MergeRule.permissive(max_novel=0.5)).tolist() == [True, False, True]
    # A neighbour that runs backwards along the drive does not agree.
    back = [FrameDecision(i, 2, 50 - 3 * i, 0.9) for i in range(5)]
    assert not select_merges(back, MergeRule.permissive(window=2, min_agree=1)).any()


def test_ingest_merges_smoothed_decisions(tmp_path, rng, world):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        a, _ = traverse(rng, world, 0, 80, noise=0.3)
        b, _ = traverse(rng, world, 0, 80, noise=0.3)
        m.add_sequence(a, name="a")
        smoothed, _ = m.localize(b, smooth=True)
        res = m.ingest(b, name="b")
        assert [d.best for d in res.decisions] == [d.best for d in smoothed]
        assert res.merged.tolist() == m.service.select_merges(smoothed).tolist()
        assert res.added.edges_added == 2 * int(res.merged.sum()) > 0
        out = res.to_dict()
        assert all("novel_prob" in d and "merged" in d for d in out["decisions"])


def test_a_deeper_search_answers_every_frame_but_merges_only_the_k_model(tmp_path, rng, world):
    """With ``smooth_k`` > ``k``: the frames the merge rule accepts from the ``k`` nearest
    hits keep their acceptance, every other frame answers with the decision from all
    ``smooth_k`` hits and is never merged."""
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        for i in range(3):  # merged with each other: parallel drives are not rivals
            m.ingest(traverse(rng, world, 0, 200, noise=1.0)[0], name=f"d{i}")
        q, _ = traverse(rng, world, 20, 150, noise=1.0)
        assert m.config.hmm.smooth_k > m.config.hmm.k  # the default searches deeper
        deep, _ = m.localize(q, smooth=True)
        shallow, _ = m.localize(q, smooth=True, smooth_k=0)
        wide, _ = m.localize(q, smooth=True, k=m.config.hmm.smooth_k, smooth_k=0)
        accepted = m.service.select_merges(shallow)
        assert 0 < accepted.sum() < len(q)
        assert [d.confirmed for d in deep] == accepted.tolist()
        assert not m.service.select_merges(deep)[~accepted].any()
        assert [d.novel_prob for d in deep] == [d.novel_prob for d in shallow]
        radius = m.config.hmm.place_radius
        for d, s, w, ok in zip(deep, shallow, wide, accepted, strict=True):
            if ok:  # the k-model's accepted place, or the deep one where it is the same
                assert d.seq_id == s.seq_id and abs(d.image_id - s.image_id) <= radius
            else:  # the place the smooth_k hits give
                assert (d.seq_id, d.image_id, d.best) == (w.seq_id, w.image_id, w.best)
        assert any(d.best != s.best for d, s in zip(deep, shallow, strict=True))


def test_a_drive_recorded_k_deep_is_searched_deeper_when_smoothed(tmp_path, rng, world):
    """The service answers from ``k`` hits per frame (``record_k``) and smooths at commit
    with the drive's descriptors: the same decisions as a drive recorded ``smooth_k`` deep."""
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        for i in range(2):
            m.ingest(traverse(rng, world, 0, 150, noise=1.0)[0], name=f"d{i}")
        q = np.vstack([traverse(rng, world, 10, 100, noise=1.0)[0],
                       unit(rng.standard_normal((30, DIM)))])  # then a street nobody drove
        deep = Localizer(m, record=True)
        shallow = Localizer(m, record=True, record_k=m.config.hmm.k)
        for row in q:
            deep.step(row)
            shallow.step(row)
        assert {len(ids) for ids, _ in shallow.hits} == {m.config.hmm.k}
        want = m.smoothed(deep)
        assert m.smoothed(shallow, q) == want
        assert any(not d.confirmed for d in want)
        with pytest.raises(ValueError, match="descriptors for 130"):
            m.smoothed(shallow, q[:50])


def test_novelty_is_calibrated_on_short_consistent_runs_too(tmp_path, rng):
    """A stretch the merge rule does not accept (a run shorter than ``merge_min_run``), under
    its own light, far from the runs it accepts: the calibration learns its distances from the
    stretch itself (a consistent run of at least CALIBRATE_MIN_RUN frames), so its frames are
    not called unmapped for lying farther than the accepted runs."""
    places = unit(rng.standard_normal((400, DIM)))
    mapped = unit(places + 0.05 * unit(rng.standard_normal(places.shape)))

    def seen(idx, noise):
        return unit(places[idx] + noise * unit(rng.standard_normal((len(idx), DIM))))

    stretch = slice(230, 245)  # 15 frames of places 330..344, seen under a dimmer light
    query = np.vstack([seen(np.arange(100), 0.15), unit(rng.standard_normal((130, DIM))),
                       seen(np.arange(330, 345), 0.4)])
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        m.add_sequence(mapped, name="mapped")
        smoothed, _ = m.localize(query, smooth=True)
        merged = m.service.select_merges(smoothed)
        assert merged[:100].mean() > 0.9 and not merged[100:].any()  # the stretch: too short
        far = [d.distance for d in smoothed[stretch]]
        assert max(d.distance for d in smoothed[:100]) < min(far)
        assert all(d.image_id is not None and abs(d.image_id - (100 + f)) <= 2
                   for f, d in enumerate(smoothed[stretch], start=230))
        # calibrated on the stretch's own distances: its frames are mapped places
        assert np.median([d.novel_prob for d in smoothed[stretch]]) < 0.2


def test_smoothed_novelty_is_calibrated_on_the_drive(tmp_path, rng):
    """A drive that follows a mapped road closely, with a detour on its way past a lookalike
    of a stretch it saw earlier, which it matches only loosely: the unmapped-place probability,
    calibrated on the drive's own matches, vetoes the detour's merge."""
    places = unit(rng.standard_normal((300, DIM)))
    mapped = unit(places + 0.05 * unit(rng.standard_normal(places.shape)))
    close = unit(places + 0.15 * unit(rng.standard_normal((300, DIM))))
    lookalike = unit(places[40:60] + 0.5 * unit(rng.standard_normal((20, DIM))))
    query = np.vstack([close[:150], lookalike, close[150:]])
    detour = slice(150, 170)
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        m.add_sequence(mapped, name="mapped")
        smoothed, _ = m.localize(query, smooth=True)
        far = [d.distance for d in smoothed[detour]]
        assert max(d.distance for d in smoothed[:150]) < min(far)
        merged = m.service.select_merges(smoothed)
        assert merged[:150].mean() > 0.9 and not merged[detour].any()
        assert min(d.novel_prob for d in smoothed[153:167]) > 0.5
        # What the calibration takes away (with the distance gate off: it catches this too).
        plain, _ = m.localize(query, smooth=True, novelty_quantile=0.0)
        ungated = dataclasses.replace(m.config.merge, dist_quantile=0.0)
        assert select_merges(plain, ungated)[detour].sum() >= 15
        assert not select_merges(smoothed, ungated)[detour].any()
        assert [d.best for d in plain] == [d.best for d in smoothed]  # the places stay
