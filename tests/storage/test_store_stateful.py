"""Stateful property test of the store against a simple in-memory model (hypothesis).

Hypothesis drives random programs of: adding sequences (in one call or streamed in batches, with
positions, with edges to earlier sequences, sometimes under a used name or with bad descriptors),
aborting a streamed sequence, searching, reopening the map (as a writer, or read-only for a full
``check``) and reading descriptors and components back. The model is a list of sequences (name,
descriptors as stored, positions) and a dict of edges; components are recomputed from the edges
with networkx. After every step the counters agree with the model, and the readings compare bit
for bit.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import networkx as nx
import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import (
    DescriptorShapeError,
    DuplicateNameError,
    EmptySequenceError,
    InvalidDescriptorError,
)
from sprint_map.storage.check import check_map
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore
from sprint_map.util.exact_search import pair_distances

DIM = 3
CONFIG = MapConfig(dim=DIM, store=StoreOptions(shard_rows=5, index_persist_every=4, index_persist_growth=0.5))
NAMES = st.sampled_from(["a", "b", "c", "d", "e", "f", "g", "h"])
values = st.floats(-1e3, 1e3, allow_nan=False, width=32)


@st.composite
def descriptors(draw: st.DrawFn, max_rows: int = 9) -> np.ndarray:
    n = draw(st.integers(1, max_rows))
    flat = draw(st.lists(values, min_size=n * DIM, max_size=n * DIM))
    return np.array(flat, dtype=np.float32).reshape(n, DIM)


class StoreMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.root = Path(tempfile.mkdtemp(prefix="stateful-"))
        self.path = self.root / "m"
        self.store = MapStore.create(self.path, CONFIG)
        # The model.
        self.names: list[str] = []
        self.rows: list[np.ndarray] = []
        self.positions: list[np.ndarray | None] = []
        self.edges: dict[tuple[int, int], tuple[float, int, int | None]] = {}
        #: (seq_id, image_id) -> (count, last drive, last distance) of places seen again
        self.sightings: dict[tuple[int, int], tuple[int, str, float]] = {}

    def teardown(self) -> None:
        self.store.close()
        shutil.rmtree(self.root, ignore_errors=True)

    # --- model helpers ----------------------------------------------------------------------
    def first_vertex(self, seq: int) -> int:
        return sum(len(r) for r in self.rows[:seq])

    def components(self) -> set[frozenset[int]]:
        graph = nx.Graph()
        graph.add_nodes_from(range(len(self.rows)))
        firsts = [self.first_vertex(s) for s in range(len(self.rows))]
        seq_of = lambda v: max(s for s, f in enumerate(firsts) if f <= v)  # noqa: E731
        graph.add_edges_from((seq_of(a), seq_of(b)) for a, b in self.edges)
        return {frozenset(c) for c in nx.connected_components(graph)}

    def draw_edges(self, data: st.DataObject, length: int) -> list[EdgeSpec]:
        edges = []
        for _ in range(data.draw(st.integers(0, 3)) if self.rows else 0):
            other = data.draw(st.integers(0, len(self.rows) - 1))
            old = (other, data.draw(st.integers(0, len(self.rows[other]) - 1)))
            new = (None, data.draw(st.integers(0, length - 1)))
            src, dst = (new, old) if data.draw(st.booleans()) else (old, new)
            weight = data.draw(st.floats(0, 1))
            edges.append(EdgeSpec(src, dst, weight, new[1]))
        return edges

    def record(self, name: str, rows: np.ndarray, pos: np.ndarray | None,
               edges: list[EdgeSpec]) -> None:
        seq = len(self.rows)
        first = self.first_vertex(seq)
        for e in edges:
            ends = [first + i if s is None else self.first_vertex(s) + i for s, i in (e.src, e.dst)]
            self.edges[(ends[0], ends[1])] = (e.weight, seq, e.frame)  # a repeat keeps the newest
        self.names.append(name)
        self.rows.append(rows.astype(np.float32))
        full = None
        if pos is not None:
            full = np.full((len(rows), 4), np.nan)
            full[:, : pos.shape[1]] = pos
        self.positions.append(full)

    # --- rules ------------------------------------------------------------------------------
    @rule(rows=descriptors(), name=st.none() | NAMES, with_pos=st.booleans(), data=st.data())
    def add(self, rows, name, with_pos, data):
        pos = rows[:, :2].astype(np.float64) if with_pos else None
        edges = self.draw_edges(data, len(rows))
        if name in self.names:
            same = self.rows[self.names.index(name)]
            if same.shape == rows.shape and same.tobytes() == rows.astype(np.float32).tobytes():
                # The same drive again (a retry): reported, nothing added.
                again = self.store.add_sequence(rows, name=name, positions=pos, edges=edges)
                assert again.already_committed and again.sequence.name == name
                return
            try:
                self.store.add_sequence(rows, name=name, positions=pos, edges=edges)
                raise AssertionError("a used name was accepted")
            except DuplicateNameError:
                return
        result = self.store.add_sequence(rows, name=name, positions=pos, edges=edges)
        assert result.sequence.seq_id == len(self.rows)
        self.record(result.sequence.name, rows, pos, edges)

    @rule(rows=descriptors(max_rows=14), cuts=st.lists(st.integers(1, 13), max_size=3),
          commit=st.booleans(), data=st.data())
    def add_streamed(self, rows, cuts, commit, data):
        bounds = sorted({c for c in cuts if c < len(rows)})
        edges = self.draw_edges(data, len(rows))
        with self.store.begin_sequence() as writer:
            for batch in np.split(rows, bounds):
                writer.append(batch)
            if not commit:
                return  # leaving the block aborts: the rows are dropped
            result = writer.commit(edges=edges)
        self.record(result.sequence.name, rows, None, edges)

    @rule(kind=st.sampled_from(["nan", "inf", "dim", "empty"]), rows=descriptors())
    def add_bad(self, kind, rows):
        bad = rows.copy()
        error: type[Exception] = InvalidDescriptorError
        if kind in ("nan", "inf"):
            bad[-1, 0] = np.nan if kind == "nan" else np.inf
        elif kind == "dim":
            bad, error = np.zeros((len(rows), DIM + 1), np.float32), DescriptorShapeError
        else:
            bad, error = bad[:0], EmptySequenceError
        try:
            self.store.add_sequence(bad)
            raise AssertionError("bad descriptors were accepted")
        except error:
            pass

    @rule()
    def reopen(self):
        self.store.close()
        self.store = MapStore.open(self.path)

    @rule()
    def check_read_only(self):
        self.store.close()
        with MapStore.open(self.path, readonly=True) as reader:
            report = check_map(reader)
            assert report.ok, report.violations
            self.compare_everything(reader)
        self.store = MapStore.open(self.path)

    @precondition(lambda self: self.rows)
    @rule(data=st.data())
    def read_descriptors(self, data):
        seq = data.draw(st.integers(0, len(self.rows) - 1))
        assert self.store.descriptors(seq).tobytes() == self.rows[seq].tobytes()
        pos = self.store.positions(seq)
        if self.positions[seq] is None:
            assert pos is None
        else:
            np.testing.assert_array_equal(pos, self.positions[seq])

    @precondition(lambda self: self.rows)
    @rule(data=st.data())
    def search_finds_itself(self, data):
        seq = data.draw(st.integers(0, len(self.rows) - 1))
        image = data.draw(st.integers(0, len(self.rows[seq]) - 1))
        query = self.rows[seq][image : image + 1]
        distances, ids = self.store.search(query, k=1)
        assert distances[0, 0] == 0.0  # itself, or an identical row
        found = int(ids[0, 0])
        all_rows = np.concatenate(self.rows)
        # A row at distance 0 ties with itself, and ties go to the lower vertex id: a row
        # holding -0.0 where the query holds 0.0, or one differing by a denormal whose square
        # rounds to 0 in float32 (the certified search's distance, ``pair_distances``).
        assert pair_distances(query[0], all_rows[found : found + 1])[0] == 0.0
        assert found <= sum(len(r) for r in self.rows[:seq]) + image

    @precondition(lambda self: self.rows)
    @rule(data=st.data())
    def see_again(self, data):
        """A drive that stored nothing: its sightings committed alone (admission)."""
        n = data.draw(st.integers(0, 6))
        seen = []
        for _ in range(n):
            seq = data.draw(st.integers(0, len(self.rows) - 1))
            image = data.draw(st.integers(0, len(self.rows[seq]) - 1))
            seen.append((seq, image, data.draw(st.floats(0, 10, width=32))))
        seen.append((len(self.rows) + 5, 0, 1.0))  # a sequence not in the map: dropped
        drive = data.draw(NAMES)
        assert self.store.record_sightings(drive, seen) == n
        for seq, image, dist in seen[:-1]:
            count = self.sightings.get((seq, image), (0, "", 0.0))[0]
            self.sightings[(seq, image)] = (count + 1, drive, dist)

    @rule()
    def components_match(self):
        got = {frozenset(c.sequences) for c in self.store.components()}
        assert got == self.components()
        for comp in self.store.components():
            assert comp.vertices == sum(len(self.rows[s]) for s in comp.sequences)
            assert all(self.store.component_of(s) == comp.component for s in comp.sequences)

    # --- invariants ---------------------------------------------------------------------------
    @invariant()
    def counters_match(self):
        assert self.store.stats() == {
            "sequences": len(self.rows),
            "vertices": sum(len(r) for r in self.rows),
            "edges": len(self.edges),
            "components": len(self.components()),
        }

    def compare_everything(self, store: MapStore) -> None:
        records = store.sequences()
        assert [r.name for r in records] == self.names
        for rec, rows in zip(records, self.rows, strict=True):
            assert store.descriptors(rec.seq_id).tobytes() == rows.tobytes()
        got = {(e.src, e.dst): (e.weight, e.query_seq, e.frame) for e in store.edges()}
        assert got == self.edges
        assert {frozenset(c.sequences) for c in store.components()} == self.components()
        for (seq, image), (count, drive, dist) in self.sightings.items():
            seen = store.sighting(seq, image)
            assert seen is not None and (seen.count, seen.last_drive) == (count, drive)
            assert seen.last_distance == dist


TestStoreStateful = StoreMachine.TestCase
TestStoreStateful.settings = settings(
    max_examples=30, stateful_step_count=25, deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
