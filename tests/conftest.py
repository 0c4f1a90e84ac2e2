"""Shared fixtures: reproducible random generators and a factory of small maps.

The map factory records what it wrote (descriptors as stored, positions, edges) so a test can
close, reopen and compare bit for bit with :func:`assert_map_matches` (the ``expect_map``
fixture).
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
import pytest
from hypothesis import settings

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore
from tests.helpers.road_map import RoadMap, build_road_map

SEED = 20200531


# CI replays the same hypothesis examples every run (a red CI is reproducible by rerunning it);
# local runs keep exploring new ones, which is how the W = 1 gutter bug was found.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


def rng_for(*keys: int | str) -> np.random.Generator:
    """A generator seeded from ``SEED`` and ``keys`` (strings are hashed stably)."""
    words = [SEED] + [zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys]
    return np.random.default_rng(words)


#: Test modules moved from the top of ``tests/`` into their package's folder (issue 53): their
#: ``rng`` is seeded from the node id they had, so each test still draws the data it always drew.
MOVED_FROM_TOP = frozenset({
    "cli/test_bad_input.py", "cli/test_cli.py", "cli/test_cli_images.py",
    "cli/test_drive_folders.py", "cli/test_progress.py", "localize/test_localizer.py",
    "localize/test_trace.py", "merge/test_commit.py", "merge/test_drives.py",
    "merge/test_merge_rule.py", "merge/test_verification.py", "storage/test_concurrency.py",
    "storage/test_crash.py", "storage/test_map_thumbnail_check.py",
    "util/test_dataclass_dict.py", "util/test_exact_search.py"})


def seed_key(nodeid: str) -> str:
    """The key the ``rng`` of test ``nodeid`` is seeded from: the node id, or for a test in
    :data:`MOVED_FROM_TOP` the one it had at the top of ``tests/``."""
    path, sep, rest = nodeid.partition("::")
    inner = path.removeprefix("tests/")
    if inner in MOVED_FROM_TOP:
        return f"tests/{inner.rpartition('/')[2]}{sep}{rest}"
    return nodeid


@pytest.fixture
def rng(request: pytest.FixtureRequest) -> np.random.Generator:
    """A generator seeded per test: reproducible, yet different tests draw different data."""
    return rng_for(seed_key(request.node.nodeid))


def random_descriptors(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    """``n`` distinct float32 descriptors (continuous draws: no two rows coincide)."""
    return rng.standard_normal((n, dim)).astype(np.float32)


@dataclass
class BuiltSequence:
    """What the factory committed for one sequence, in stored form."""

    seq_id: int
    name: str
    first_vertex: int
    descriptors: np.ndarray  # float32, as stored
    positions: np.ndarray | None  # (n, 4), NaN where not given, as stored
    edges: list[tuple[int, int, float, int | None]]  # (src vertex, dst vertex, weight, frame)
    source: str = ""

    @property
    def length(self) -> int:
        return len(self.descriptors)


@dataclass
class BuiltMap:
    """A map written by :class:`MapFactory` (closed) and its expected contents."""

    path: Path
    config: MapConfig
    sequences: list[BuiltSequence] = field(default_factory=list)

    @property
    def vertices(self) -> int:
        return sum(s.length for s in self.sequences)

    def all_descriptors(self) -> np.ndarray:
        return np.concatenate([s.descriptors for s in self.sequences])

    def edge_set(self) -> dict[tuple[int, int], tuple[float, int, int | None]]:
        """``(src, dst) -> (weight, query seq, frame)``; a repeated edge keeps the newest."""
        out: dict[tuple[int, int], tuple[float, int, int | None]] = {}
        for seq in self.sequences:
            for src, dst, weight, frame in seq.edges:
                out[(src, dst)] = (weight, seq.seq_id, frame)
        return out

    def seq_of_vertex(self, vertex: int) -> int:
        for seq in self.sequences:
            if seq.first_vertex <= vertex < seq.first_vertex + seq.length:
                return seq.seq_id
        raise KeyError(vertex)

    def expected_components(self) -> set[frozenset[int]]:
        graph = nx.Graph()
        graph.add_nodes_from(s.seq_id for s in self.sequences)
        for src, dst in self.edge_set():
            graph.add_edge(self.seq_of_vertex(src), self.seq_of_vertex(dst))
        return {frozenset(c) for c in nx.connected_components(graph)}

    def add(
        self,
        store: MapStore,
        descriptors: np.ndarray,
        *,
        positions: np.ndarray | None = None,
        edges: Sequence[EdgeSpec] = (),
        name: str | None = None,
        source: str = "",
    ) -> BuiltSequence:
        """Add a sequence through ``store`` and record what it should have stored."""
        result = store.add_sequence(
            descriptors, name=name, positions=positions, edges=edges, source=source
        )
        rec = result.sequence
        stored_pos = None
        if positions is not None:
            stored_pos = np.full((rec.length, 4), np.nan)
            stored_pos[:, : positions.shape[1]] = positions
        first_of = {s.seq_id: s.first_vertex for s in self.sequences}
        first_of[rec.seq_id] = rec.first_vertex

        def vertex(end: tuple[int | None, int]) -> int:
            seq, image = end
            return first_of[rec.seq_id if seq is None else seq] + image

        built = BuiltSequence(
            seq_id=rec.seq_id,
            name=rec.name,
            first_vertex=rec.first_vertex,
            descriptors=np.asarray(descriptors, dtype=np.float32).copy(),
            positions=stored_pos,
            edges=[(vertex(e.src), vertex(e.dst), e.weight, e.frame) for e in edges],
            source=source,
        )
        self.sequences.append(built)
        return built


class MapFactory:
    """Build small maps under a test's ``tmp_path`` with random content from its ``rng``."""

    def __init__(self, root: Path, rng: np.random.Generator) -> None:
        self.root = root
        self.rng = rng
        self._count = 0

    def empty(self, config: MapConfig) -> BuiltMap:
        """A fresh path and an empty record, for tests that create the map themselves."""
        self._count += 1
        return BuiltMap(self.root / f"map{self._count}", config)

    def random_edges(self, built: BuiltMap, length: int, n_edges: int) -> list[EdgeSpec]:
        """Edges between the new sequence and random frames of random earlier sequences."""
        edges = []
        for _ in range(n_edges if built.sequences else 0):
            other = built.sequences[int(self.rng.integers(len(built.sequences)))]
            new_end = (None, int(self.rng.integers(length)))
            old_end = (other.seq_id, int(self.rng.integers(other.length)))
            # Both directions occur: localisation edges point query -> map, merges may add both.
            src, dst = (new_end, old_end) if self.rng.random() < 0.7 else (old_end, new_end)
            edges.append(EdgeSpec(src, dst, weight=float(self.rng.random()),
                                  frame=int(self.rng.integers(length))))
        return edges

    def __call__(
        self,
        lengths: Sequence[int] = (5, 12, 30),
        *,
        dim: int = 8,
        shard_rows: int = 16,
        positions: bool | str = "alternate",
        edges: int = 1,
        **config: Any,
    ) -> BuiltMap:
        """Create a map, add one sequence per entry of ``lengths``, close it.

        Parameters
        ----------
        positions : bool or "alternate"
            Give positions to every sequence, none, or every other one (2 to 4 columns).
        edges : int
            Random edges from each sequence (after the first) to earlier ones.
        """
        built = self.empty(MapConfig(dim=dim, **config, store=StoreOptions(shard_rows=shard_rows)))
        with MapStore.create(built.path, built.config) as store:
            for i, length in enumerate(lengths):
                self.add_random(store, built, length, positions=positions, edges=edges, index=i)
        return built

    def add_random(self, store: MapStore, built: BuiltMap, length: int, *,
                   positions: bool | str = "alternate", edges: int = 1, index: int = 0
                   ) -> BuiltSequence:
        """Add one random sequence of ``length`` frames to an open ``store``."""
        pos = None
        if positions is True or (positions == "alternate" and index % 2 == 0):
            cols = 2 + index % 3
            pos = self.rng.uniform(-1e3, 1e3, (length, cols))
        return built.add(
            store,
            random_descriptors(self.rng, length, built.config.dim),
            positions=pos,
            edges=self.random_edges(built, length, edges),
            source=f"factory #{index}",
        )


@pytest.fixture
def make_map(tmp_path: Path, rng: np.random.Generator) -> MapFactory:
    """Factory of small, closed maps with known content (see :class:`MapFactory`)."""
    return MapFactory(tmp_path, rng)


def assert_map_matches(store: MapStore, built: BuiltMap) -> None:
    """Assert ``store`` holds exactly what ``built`` recorded, bit for bit."""
    edges = built.edge_set()
    assert store.stats() == {
        "sequences": len(built.sequences),
        "vertices": built.vertices,
        "edges": len(edges),
        "components": len(built.expected_components()),
    }
    records = store.sequences()
    assert [r.seq_id for r in records] == [s.seq_id for s in built.sequences]
    for rec, seq in zip(records, built.sequences, strict=True):
        assert (rec.name, rec.length, rec.first_vertex, rec.source) == (
            seq.name, seq.length, seq.first_vertex, seq.source)
        assert store.sequence_by_name(seq.name) == rec
        stored = store.descriptors(seq.seq_id)
        assert stored.dtype == np.float32
        assert stored.shape == seq.descriptors.shape
        assert stored.tobytes() == seq.descriptors.tobytes()
        pos = store.positions(seq.seq_id)
        if seq.positions is None:
            assert pos is None
        else:
            assert pos is not None
            np.testing.assert_array_equal(pos, seq.positions)  # NaN == NaN here
    got_edges = {
        (e.src, e.dst): (e.weight, e.query_seq, e.frame) for e in store.edges()
    }
    assert got_edges == edges
    comps = {frozenset(c.sequences) for c in store.components()}
    assert comps == built.expected_components()
    for comp in store.components():
        assert comp.vertices == sum(built.sequences[s].length for s in comp.sequences)
        for seq_id in comp.sequences:
            assert store.component_of(seq_id) == comp.component


@pytest.fixture
def expect_map() -> Callable[[MapStore, BuiltMap], None]:
    """The :func:`assert_map_matches` helper, as a fixture for test modules."""
    return assert_map_matches


@pytest.fixture
def road_map(tmp_path: Path, rng: np.random.Generator, request: pytest.FixtureRequest
             ) -> RoadMap:
    """A closed map of drives over one road, with positions, plus a drive elsewhere
    (:func:`tests.helpers.road_map.build_road_map`). Its size: ``drives=3, frames=100``, or
    the arguments of the closest ``@pytest.mark.road_map(drives=..., frames=...,
    with_thumbnails=...)``."""
    marker = request.node.get_closest_marker("road_map")
    kwargs = {"drives": 3, "frames": 100, **(marker.kwargs if marker else {})}
    road, ids = build_road_map(tmp_path / "m", rng, **kwargs)
    return RoadMap(tmp_path / "m", road, ids)
