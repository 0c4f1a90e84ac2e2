"""The one commit path of a localised drive (``sprint_map.merge.commit``), as ingest, merge and the
service use it: merges become edges, everything is validated before a row is written, the
exclusive section holds the transaction and the commit hook, retries are reported."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import pytest

from sprint_map.config import MapConfig, MergeRule
from sprint_map.errors import DuplicateNameError, InputError, UnknownSequenceError
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec
from sprint_map.testing.faults import CallRecorder
from sprint_map.util.atomic import set_file_hook

DIM = 5


def decision(frame: int, seq: int | None, image: int | None, prob: float = 0.9) -> FrameDecision:
    return FrameDecision(frame=frame, seq_id=seq, image_id=image, prob=prob, novel_prob=0.0,
                         vertex_id=-1)


@pytest.fixture
def smap(tmp_path, rng):
    """Two drives in separate components (ids 0 and 1); every decision may merge."""
    config = MapConfig(dim=DIM, merge=MergeRule(min_run=0, dist_quantile=0.0, min_advance=0.0, both_ways=False))
    with SprintMap.create(tmp_path / "m", config) as m:
        m.add_sequence(rng.standard_normal((6, DIM)), name="a")
        m.add_sequence(rng.standard_normal((6, DIM)), name="b")
        yield m


def test_merge_commits_the_selected_decisions_as_edges(smap, rng):
    rows = rng.standard_normal((3, DIM))
    decisions = [decision(0, 0, 2), decision(1, 1, 4), decision(2, None, None)]
    added = smap.merge(rows, decisions, name="c")
    assert added.edges_added == 2 and not added.already_committed
    assert {(e.src_seq, e.src_image, e.dst_seq, e.dst_image) for e in smap.edges(added_by="c")} \
        == {(2, 0, 0, 2), (2, 1, 1, 4)}
    assert smap.stats()["components"] == 1


@pytest.mark.parametrize("bad", [
    {"positions": np.zeros((2, 2))},  # positions of the wrong length
    {"decisions": [decision(0, 0, 99)]},  # an edge past the end of sequence 0
])
def test_everything_is_validated_before_a_row_is_written(smap, rng, bad):
    before = smap.stats()
    calls = CallRecorder()
    previous = set_file_hook(calls)
    try:
        with pytest.raises(InputError if "positions" in bad else UnknownSequenceError):
            smap.merge(rng.standard_normal((3, DIM)), bad.get("decisions", [decision(0, 0, 2)]),
                       name="c", positions=bad.get("positions"))
    finally:
        set_file_hook(previous)
    assert smap.stats() == before
    assert not [op for op, _ in calls.calls if op == "write"]


def test_a_name_is_checked_when_the_drive_begins(smap, rng):
    with pytest.raises(InputError):
        smap.service.begin_drive("")
    with pytest.raises(DuplicateNameError):  # "a" was committed without these rows
        smap.merge(rng.standard_normal((3, DIM)), [], name="a")


def test_exclusive_section_holds_the_commit_and_the_hook(smap, rng):
    events: list[str] = []

    @contextmanager
    def exclusive():
        events.append("enter")
        yield
        events.append("exit")

    def on_commit(changed: set[int]) -> None:
        events.append(f"changed {sorted(changed)} stats {smap.stats()['sequences']}")

    def seam(op: str, path: object, info: object) -> None:
        if op == "fsync":
            events.append("fsync")

    with smap.service.begin_drive(None, "cam", reserved={"seq-2"}) as drive:
        assert drive.name == "seq-2-2"  # a default name avoids the reserved ones
        drive.append(rng.standard_normal((4, DIM)))
        previous = set_file_hook(seam)
        try:
            done = drive.commit([decision(0, 0, 1), decision(3, 1, 0)], exclusive=exclusive,
                                on_commit=on_commit)
        finally:
            set_file_hook(previous)
    # the rows fsynced before the gate (the slow part: frames go on meanwhile); under it the
    # transaction and the hook: the components before (0 and 1) and the new one (0: the edges
    # joined all three)
    assert events == ["fsync", "enter", "changed [0, 1] stats 3", "exit"]
    assert done.changed == {0, 1} and done.added.component == 0
    assert done.merged.tolist() == [True, True]
    assert done.added.sequence.source == "cam"


def test_a_retry_of_a_committed_drive_is_reported_not_added(smap, rng):
    rows = rng.standard_normal((3, DIM)).astype(np.float32)
    decisions = [decision(0, 0, 2)]
    first = smap.merge(rows, decisions, name="c")
    again = smap.merge(rows, decisions, name="c")
    assert again.already_committed and again.edges_added == 0
    assert again.sequence == first.sequence
    assert smap.stats()["sequences"] == 3


def test_leaving_without_a_commit_leaves_nothing(smap, rng):
    before = smap.stats()
    with smap.service.begin_drive("c") as drive:
        drive.append(rng.standard_normal((4, DIM)))
    assert smap.stats() == before
    added = smap.add_sequence(rng.standard_normal((2, DIM)), name="c",
                              edges=[EdgeSpec((None, 0), (0, 0))])
    assert added.sequence.first_vertex == 12  # the aborted rows left no trace
