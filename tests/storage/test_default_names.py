"""Default sequence names never collide (issue 14, item 2): ids are not names.

A drive named ``seq-3`` by its user may be committed as sequence 2; the default name of the
unnamed drive that later becomes sequence 3 must then skip ``seq-3`` rather than fail every
commit (and every retry) with "a sequence named 'seq-3' already exists".
"""

from __future__ import annotations

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.storage.sequence_writer import SequenceWriter, default_name
from sprint_map.storage.store import MapStore


def _rows(rng: np.random.Generator, n: int = 3, dim: int = 4) -> np.ndarray:
    return rng.standard_normal((n, dim)).astype(np.float32)


def test_a_default_name_skips_names_in_use(tmp_path, rng):
    with MapStore.create(tmp_path / "m.map", MapConfig(dim=4)) as store:
        assert store.add_sequence(_rows(rng)).sequence.name == "seq-0"
        # The user takes the default name of sequence 3 (and its first fallback).
        assert store.add_sequence(_rows(rng), name="seq-3").sequence.seq_id == 1
        assert store.add_sequence(_rows(rng), name="seq-3-2").sequence.seq_id == 2
        third = store.add_sequence(_rows(rng))  # was: DuplicateNameError, on every retry
        assert (third.sequence.seq_id, third.sequence.name) == (3, "seq-3-3")
        assert store.add_sequence(_rows(rng)).sequence.name == "seq-4"
        with store.begin_sequence() as writer:  # the streaming path names the same way
            writer.append(_rows(rng))
            assert writer.commit().sequence.name == "seq-5"
        assert [s.name for s in store.sequences()] == [
            "seq-0", "seq-3", "seq-3-2", "seq-3-3", "seq-4", "seq-5"]
    with MapStore.open(tmp_path / "m.map", readonly=True) as store:
        assert store.sequence_by_name("seq-3-3").seq_id == 3


def test_a_default_name_also_skips_reserved_names(tmp_path, rng):
    """Names a caller holds for drives not committed yet (the service's open sessions)."""
    with MapStore.create(tmp_path / "m.map", MapConfig(dim=4)) as store:
        with SequenceWriter(store, None, reserved={"seq-0", "seq-0-2"}) as writer:
            writer.append(_rows(rng))
            assert writer.commit().sequence.name == "seq-0-3"
        # A given name is the caller's choice: reserved names only steer defaults.
        assert store.add_sequence(_rows(rng), name="seq-0").sequence.name == "seq-0"


def test_default_name_scheme():
    taken = {"seq-7", "seq-7-2"}
    assert default_name(7, taken.__contains__) == "seq-7-3"
    assert default_name(8, taken.__contains__) == "seq-8"
