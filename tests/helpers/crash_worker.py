"""The crash harness: writer processes to kill (child side) and the checks after each kill.

Run as a script it is the child side (never imported by pytest as a test module)::

    crash_worker.py write MAP --seed S [--count N] [--length L]
        Open MAP for writing, print ``ready``, and add sequences ``n, n+1, ...`` (``n`` =
        sequences already there) whose content is a pure function of (seed, index): see
        :func:`planned_sequence`. After each add returns, print ``ack <i>`` (flushed). Run it
        with ``SPRINT_MAP_CRASH_AT=<point>`` to have it SIGKILL itself at that crash point.
    crash_worker.py hold MAP
        Open MAP for writing, print ``locked``, then wait for stdin to close.
    crash_worker.py try-open MAP
        Try to open MAP for writing; print JSON ``{"error", "message", "seconds"}``.
    crash_worker.py zygote
        A fork server: imports everything once, then for each JSON line on stdin
        ``{"op": "spawn", "ack": FILE, ...}`` forks a child that runs ``write`` (the default;
        ``"groups": true`` commits some sequences in groups, :func:`group_of`)
        or, with ``"mode": "repair"``, ``check --repair`` (``"remove"`` with ``"seqs"``:
        ``remove``; ``"unmerge"`` with ``"seq"``: ``unmerge``; ``"compact"``: ``compact``),
        with ``SPRINT_MAP_CRASH_AT`` set to ``"crash_at"`` if given; the child appends
        ``ready``, ``ack <i>``, ``done`` lines to FILE (``os.write``: in the kernel once it
        returns) and the zygote replies ``{"pid": ...}``;
        ``{"op": "wait", "pid": P}`` reaps it and replies ``{"signal": ..., "code": ...}``.
        Forking a warmed-up process makes a kill-and-restart cycle cost milliseconds instead of
        a Python start-up (~0.7 s with numpy/faiss/cv2).

Imported (by ``tests/storage/test_crash.py`` and ``tools/crash_soak.py``) it is the parent side:
:class:`Zygote` (the client), :func:`verify` (after a kill: the map holds exactly a prefix of the
stream, bit for bit, with the components of its edges) and :func:`kill_loop` (random kills).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import traceback
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import SprintMapError
from sprint_map.storage.check import check_map
from sprint_map.storage.keys import THUMB_KEY, read_u64
from sprint_map.storage.records import CheckReport, EdgeSpec
from sprint_map.storage.repair import repair_map
from sprint_map.storage.store import MapStore
from sprint_map.storage.thumbnails import THUMBNAILS_DB
from sprint_map.testing.crash import CRASH_ENV

WORKER = Path(__file__).resolve()
MAX_LENGTH = 90
#: Rows per append when a sequence is streamed (every third sequence), as ``ingest`` does.
STREAM_BATCH = 16


# --- the stream of sequences -----------------------------------------------------------------


def _rng(seed: int, index: int, what: str) -> np.random.Generator:
    return np.random.default_rng([seed, index, zlib.crc32(what.encode())])


def planned_length(seed: int, index: int, fixed: int | None = None) -> int:
    """Frames of sequence ``index``: ``fixed`` or a deterministic draw in 1..MAX_LENGTH."""
    return fixed if fixed else int(_rng(seed, index, "length").integers(1, MAX_LENGTH + 1))


@dataclass(frozen=True)
class Planned:
    """The deterministic content of the ``index``-th sequence a worker adds."""

    name: str
    descriptors: np.ndarray
    positions: np.ndarray | None
    edges: tuple[EdgeSpec, ...]
    #: one JPEG-signed byte string per frame (odd sequences), or None
    thumbnails: tuple[bytes, ...] | None = None


def planned_sequence(seed: int, index: int, dim: int, fixed_length: int | None = None) -> Planned:
    """Sequence ``index`` of the worker stream ``seed`` (same on every call, in every process).

    Every other sequence has positions, the others thumbnails (bytes with the JPEG signature:
    storage never decodes them); each has 0-2 edges to earlier sequences of the stream
    (so the i-th sequence of the stream must be seq id i, which holds when only the worker
    writes the map).
    """
    length = planned_length(seed, index, fixed_length)
    rng = _rng(seed, index, "content")
    descriptors = rng.standard_normal((length, dim)).astype(np.float32)
    positions = rng.uniform(-500, 500, (length, 3)) if index % 2 == 0 else None
    edges = []
    for _ in range(int(rng.integers(0, 3)) if index else 0):
        other = int(rng.integers(index))
        old_end = (other, int(rng.integers(planned_length(seed, other, fixed_length))))
        new_end = (None, int(rng.integers(length)))
        src, dst = (new_end, old_end) if rng.random() < 0.5 else (old_end, new_end)
        edges.append(EdgeSpec(src, dst, weight=float(rng.random()), frame=new_end[1]))
    thumbs = _rng(seed, index, "thumbnails")
    thumbnails = tuple(b"\xff\xd8" + thumbs.bytes(int(thumbs.integers(4, 64))) + b"\xff\xd9"
                       for _ in range(length)) if index % 2 else None
    return Planned(f"w-{index}", descriptors, positions, tuple(edges), thumbnails)


@lru_cache(maxsize=8192)
def planned(seed: int, index: int, dim: int, length: int | None) -> Planned:
    """:func:`planned_sequence`, memoised for the parent that re-verifies after every kill."""
    return planned_sequence(seed, index, dim, length)


def add_planned(store: MapStore, seed: int, index: int, length: int | None = None) -> None:
    """Add sequence ``index`` of stream ``seed`` to ``store`` (it must be the next seq id).

    Every third sequence is streamed in batches through ``begin_sequence`` (the ``ingest``
    path: rows written uncommitted batch by batch, one commit); the others in one call (the
    ``add_sequence``/``merge`` path). Both commit the same content.
    """
    plan = planned_sequence(seed, index, store.config.dim, length)
    if index % 3 == 1:
        with store.begin_sequence(plan.name) as writer:
            for start in range(0, len(plan.descriptors), STREAM_BATCH):
                writer.append(plan.descriptors[start : start + STREAM_BATCH])
            result = writer.commit(plan.positions, plan.edges, plan.thumbnails)
    else:
        result = store.add_sequence(plan.descriptors, name=plan.name, positions=plan.positions,
                                    edges=plan.edges, thumbnails=plan.thumbnails)
    assert result.sequence.seq_id == index


#: Writers that commit groups (``"groups": true``) add sequences ``6j+3 .. 6j+5`` as one group
#: (``MapStore.begin_group``: one fsync, one transaction), the others one at a time.
GROUP_PERIOD, GROUP_START = 6, 3


def group_of(index: int) -> range:
    """The sequences a group-committing writer commits together with sequence ``index``."""
    start = index - index % GROUP_PERIOD + GROUP_START
    return range(start, start + GROUP_PERIOD - GROUP_START) if index >= start else \
        range(index, index + 1)


def add_planned_group(store: MapStore, seed: int, indices: range,
                      length: int | None = None) -> None:
    """Add sequences ``indices`` of stream ``seed`` in one group commit (every third streamed
    in batches, as :func:`add_planned` does; their edges may reach earlier sequences of the
    group). The same content as adding them one by one."""
    with store.begin_group() as group:
        for index in indices:
            plan = planned_sequence(seed, index, store.config.dim, length)
            rows = plan.descriptors
            if index % 3 == 1:
                rows = (plan.descriptors[i : i + STREAM_BATCH]
                        for i in range(0, len(plan.descriptors), STREAM_BATCH))
            group.add(rows, plan.name, "", plan.positions, plan.edges, plan.thumbnails)
        results = group.commit()
    assert [r.sequence.seq_id for r in results] == list(indices)


# --- child side --------------------------------------------------------------------------------


def write(path: str, seed: int, count: int | None, length: int | None,
          emit: Callable[[str], None], groups: bool = False) -> None:
    """Add planned sequences to the map at ``path``, acknowledging each with ``emit`` (with
    ``groups``, a group's sequences once the group is committed)."""
    with MapStore.open(path) as store:
        emit("ready")
        start = store.stats()["sequences"]
        index = start
        while count is None or index < start + count:
            block = group_of(index) if groups else range(index, index + 1)
            assert block.start == index, f"the map ends inside group {block}"
            if len(block) > 1:
                add_planned_group(store, seed, block, length)
            else:
                add_planned(store, seed, index, length)
            for i in block:
                emit(f"ack {i}")
            index = block.stop
    emit("done")


def repair(path: str, emit: Callable[[str], None]) -> None:
    """Run ``check --repair`` on ``path``; emit ``repaired <json report>``."""
    emit("ready")
    emit("repaired " + json.dumps(repair_map(path).to_dict()))


def remove(path: str, seqs: list[int], emit: Callable[[str], None]) -> None:
    """Remove ``seqs`` from ``path``; emit ``removed`` once the commit returned."""
    with MapStore.open(path) as store:
        emit("ready")
        store.remove_sequences(seqs)
        emit("removed")
    emit("done")


def unmerge(path: str, seq: int, emit: Callable[[str], None]) -> None:
    """Unmerge ``seq`` in ``path``; emit ``unmerged <edges removed>`` once the commit returned."""
    with MapStore.open(path) as store:
        emit("ready")
        emit(f"unmerged {store.unmerge(seq).edges_removed}")
    emit("done")


def compact(path: str, emit: Callable[[str], None]) -> None:
    """Compact ``path``; emit ``compacted <generation>`` once it returned."""
    with MapStore.open(path) as store:
        emit("ready")
        emit(f"compacted {store.compact().generation}")
    emit("done")


def logical_state(store: MapStore) -> dict[str, Any]:
    """What a map means, independent of its vertex numbering: every sequence (name, length,
    source, descriptor, position and thumbnail bytes), every edge between ``(seq, image)`` endpoints with
    its provenance, the components and the counters. Asserts that the components are those
    recomputed from the edges (networkx). Equal before and after a compaction."""
    seqs = {}
    for rec in store.sequences():
        pos = store.positions(rec.seq_id)
        seqs[rec.seq_id] = (rec.name, rec.length, rec.source,
                            np.asarray(store.descriptors(rec.seq_id)).tobytes(),
                            None if pos is None else pos.tobytes(),
                            tuple(store.thumbnail(rec.seq_id, i) for i in range(rec.length)))
    records = store.edges()
    ends = store.locate([v for e in records for v in (e.src, e.dst)])
    edges = {(ends[2 * i], ends[2 * i + 1], e.weight, e.query_seq, e.frame, e.time)
             for i, e in enumerate(records)}
    graph = nx.Graph()
    graph.add_nodes_from(seqs)
    graph.add_edges_from((a[0], b[0]) for a, b, *_ in edges)
    components = {frozenset(c.sequences) for c in store.components()}
    assert components == {frozenset(c) for c in nx.connected_components(graph)}
    return {"sequences": seqs, "edges": edges, "components": components,
            "stats": {k: v for k, v in store.stats().items() if k != "vertices"},
            "live_vertices": sum(r.length for r in store.sequences())}


def _stdout_emit(line: str) -> None:
    print(line, flush=True)


def _child(request: dict[str, Any]) -> None:
    """The body of a zygote child: never returns."""
    status = 0
    try:
        os.environ.pop(CRASH_ENV, None)
        if request.get("crash_at"):
            os.environ[CRASH_ENV] = request["crash_at"]
        fd = os.open(request["ack"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

        def emit(line: str, fd: int = fd) -> None:
            os.write(fd, f"{line}\n".encode())

        mode = request.get("mode", "write")
        if mode == "repair":
            repair(request["map"], emit)
        elif mode == "remove":
            remove(request["map"], request["seqs"], emit)
        elif mode == "compact":
            compact(request["map"], emit)
        elif mode == "unmerge":
            unmerge(request["map"], request["seq"], emit)
        else:
            write(request["map"], request["seed"], request.get("count"), request.get("length"),
                  emit, request.get("groups", False))
    except BaseException:
        traceback.print_exc()
        status = 1
    os._exit(status)


def _zygote() -> None:
    for raw in sys.stdin:
        request = json.loads(raw)
        if request["op"] == "spawn":
            sys.stdout.flush()
            pid = os.fork()
            if pid == 0:
                _child(request)
            reply: dict[str, object] = {"pid": pid}
        elif request["op"] == "wait":
            _, status = os.waitpid(request["pid"], 0)
            reply = {
                "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
                "code": os.WEXITSTATUS(status) if os.WIFEXITED(status) else None,
            }
        else:
            raise ValueError(f"unknown op {request['op']!r}")
        print(json.dumps(reply), flush=True)


# --- parent side -------------------------------------------------------------------------------


class Zygote:
    """Client of ``crash_worker.py zygote``: forks ready-to-run writers in milliseconds."""

    def __init__(self, log: Path) -> None:
        self.log = log
        self._stderr = log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, str(WORKER), "zygote"], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self._stderr, text=True,
        )

    def _ask(self, request: dict[str, Any]) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        assert line, f"zygote died: {self.log.read_text()}"
        reply: dict[str, Any] = json.loads(line)
        return reply

    def spawn(self, **request: Any) -> int:
        """Fork a child (see the module docstring for the request); return its pid."""
        return int(self._ask({"op": "spawn", **request})["pid"])

    def wait(self, pid: int) -> dict[str, Any]:
        return self._ask({"op": "wait", "pid": pid})

    def run(self, **request: Any) -> dict[str, Any]:
        """Spawn a child and wait for it to end (by itself or by its crash point)."""
        return self.wait(self.spawn(**request))

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self._stderr.close()


def wait_for_line(path: Path, word: str, timeout: float = 120.0) -> list[str]:
    """Poll an ack file until it holds ``word`` (generous timeout: only a hang trips it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        lines = read_lines(path)
        if word in lines:
            return lines
        time.sleep(0.002)
    raise AssertionError(f"no {word!r} in {path} after {timeout} s")


def read_acks(path: Path) -> set[int]:
    text = path.read_text() if path.exists() else ""
    return {int(line.split()[1]) for line in text.split("\n") if line.startswith("ack ")}


def expected_edges(seed: int, index: int, dim: int, length: int | None,
                   first: list[int]) -> dict[tuple[int, int], tuple[float, int | None]]:
    out = {}
    for spec in planned(seed, index, dim, length).edges:
        ends = [first[index if s is None else s] + image for s, image in (spec.src, spec.dst)]
        out[(ends[0], ends[1])] = (spec.weight, spec.frame)  # a repeat keeps the later one
    return out


def expected_components(seed: int, n: int, dim: int, length: int | None
                        ) -> set[frozenset[int]]:
    """Connected components (networkx) of the first ``n`` sequences joined by their edges."""
    graph = nx.Graph()
    graph.add_nodes_from(range(n))
    for i in range(n):
        for spec in planned(seed, i, dim, length).edges:
            graph.add_edge(*(i if s is None else s for s, _ in (spec.src, spec.dst)))
    return {frozenset(c) for c in nx.connected_components(graph)}


def verify(path: Path, seed: int, acked: set[int], length: int | None = None, *,
           groups: bool = False) -> CheckReport:
    """Open read-only and assert the map holds exactly a prefix of the worker stream (with
    ``groups``, one that ends with a whole group: :func:`group_of`).

    Every acknowledged sequence is there; every sequence there is whole and bit for bit the
    planned one (descriptors, positions, thumbnails, edges with their provenance); the
    components are those of the planned edges. Descriptors and positions are compared in bulk
    (all shards against the concatenated stream) so that re-verifying the whole map after every
    kill stays cheap.
    Returns the check report; the caller decides which violations a fresh crash may leave.
    """
    with MapStore.open(path, readonly=True) as store:
        dim = store.config.dim
        records = store.sequences()
        n = len(records)
        assert acked <= set(range(n)), f"acknowledged {sorted(acked - set(range(n)))} missing"
        if groups and n:
            assert group_of(n - 1).stop == n, f"{n} sequences: a group committed in part"
        plans = [planned(seed, i, dim, length) for i in range(n)]
        first = np.cumsum([0] + [len(p.descriptors) for p in plans]).tolist()
        for i, (rec, plan) in enumerate(zip(records, plans, strict=True)):
            assert (rec.seq_id, rec.name, rec.first_vertex, rec.length) == (
                i, plan.name, first[i], len(plan.descriptors))
        total = first[-1]
        assert store.stats()["vertices"] == total
        if n:
            want = np.concatenate([p.descriptors for p in plans])
            assert store.shards.rows(0, total, total).tobytes() == want.tobytes()
        with store.env.read() as txn:
            stored = list(txn.cursor(db=store.env.db("vertex_data")))
        got_ids = np.array([read_u64(k) for k, _ in stored], dtype=np.int64)
        got_pos = np.frombuffer(b"".join(v for _, v in stored), dtype=">f8").reshape(-1, 4)
        with_pos = [i for i, p in enumerate(plans) if p.positions is not None]
        want_ids = np.array([v for i in with_pos for v in range(first[i], first[i + 1])],
                            dtype=np.int64)
        want_pos = np.full((len(want_ids), 4), np.nan)
        if with_pos:
            want_pos[:, :3] = np.concatenate([plans[i].positions for i in with_pos])
        np.testing.assert_array_equal(got_ids, want_ids)
        np.testing.assert_array_equal(got_pos, want_pos)
        edges: dict[int, dict[tuple[int, int], tuple[float, int | None]]] = {}
        for e in store.edges():
            assert e.query_seq is not None
            edges.setdefault(e.query_seq, {})[(e.src, e.dst)] = (e.weight, e.frame)
        for i in range(n):
            assert edges.get(i, {}) == expected_edges(seed, i, dim, length, first)
        # Thumbnails in one scan (a read per frame costs more than the rest of the check):
        # exactly the planned ones, every frame of a drive that keeps them, nothing else.
        with store.env.read() as txn:
            got_thumbs = ({THUMB_KEY.unpack(bytes(k)): bytes(v) for k, v in
                           txn.cursor(db=store.env.db(THUMBNAILS_DB))}
                          if store.env.has_db(THUMBNAILS_DB) else {})
        want_thumbs = {(i, j): t for i, p in enumerate(plans) if p.thumbnails is not None
                       for j, t in enumerate(p.thumbnails)}
        assert got_thumbs.keys() == want_thumbs.keys()
        assert all(got_thumbs[key] == thumb for key, thumb in want_thumbs.items())
        assert set(edges) <= set(range(n))
        components = store.components()
        assert {frozenset(c.sequences) for c in components} == expected_components(
            seed, n, dim, length)
        for comp in components:
            assert comp.vertices == sum(len(plans[s].descriptors) for s in comp.sequences)
        return check_map(store)


def assert_ok_but_partials(report: CheckReport) -> None:
    """``check`` passes on a map no writer has reopened yet: a partial index file a kill left
    is a note (the next writable open deletes it), never a violation."""
    assert report.ok, report.violations


#: Rows above which :func:`assert_search_finds_everything` searches a sample (exact search of
#: every row is quadratic: 23 s at 82,000 rows).
SEARCH_ALL_ROWS = 20_000
#: The sample: the first row of every drive, every ``SEARCH_STRIDE``-th row and the last
#: ``SEARCH_TAIL`` rows (the drives a kill was closest to).
SEARCH_STRIDE = 8
SEARCH_TAIL = 2_000


def assert_search_finds_everything(path: Path) -> None:
    """A search for a map row finds that row: every row of a small map; of a larger one, the
    first row of every drive, every :data:`SEARCH_STRIDE`-th row and the last
    :data:`SEARCH_TAIL` (a lost drive, or a lost block of rows, is still caught)."""
    with MapStore.open(path, readonly=True) as store:
        total = store.stats()["vertices"]
        want = np.arange(total)
        if total > SEARCH_ALL_ROWS:
            firsts = [rec.first_vertex for rec in store.sequences()]
            want = np.union1d(np.union1d(want[::SEARCH_STRIDE], want[-SEARCH_TAIL:]), firsts)
        rows = store.shards.rows(0, total, total)[want]
        _, ids = store.search(rows, k=1)
    np.testing.assert_array_equal(ids[:, 0], want)


def create_map(path: Path, dim: int, **store: Any) -> None:
    """Create an empty map of ``dim`` with these storage options (``StoreOptions`` fields)."""
    MapStore.create(path, MapConfig(dim=dim, store=StoreOptions(**store))).close()


#: What recovery or repair may find after a kill: files past the commit, and an index cache not
#: persisted yet; never a derived record or an index to rebuild.
CRASH_LEFTOVERS = ("removed leftover temp file", "truncated shard-", "removed uncommitted shard",
                   "wrote the missing index")

#: Random-kill maps: small shards and frequent index persists put shard creation and index
#: publication among the moments a kill can hit.
KILL_MAP = {"dim": 16, "shard_rows": 128, "index_persist_every": 150}


@dataclass
class KillStats:
    """What :func:`kill_loop` did. ``violations`` must stay empty; the rest is what the kills
    hit (timing, so reported, never asserted)."""

    kills: int = 0
    maps: int = 0
    sequences_verified: int = 0  # acknowledged sequences compared bit for bit, over all kills
    sequences_committed: int = 0  # distinct sequences in the maps at the end
    vertices_committed: int = 0
    killed_before_ready: int = 0  # during fork, open and recovery
    killed_inside_group: int = 0  # rows of a group written, its transaction not committed
    partial_index_left: int = 0
    uncommitted_rows_left: int = 0
    recovered_by_open: int = 0
    repaired_by_check_repair: int = 0
    seconds: float = 0.0
    violations: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def kill_loop(root: Path, zygote: Zygote, kills: int, seed: int, *, kills_per_map: int = 25,
              max_wait: float = 0.04, keep_going: bool = False,
              progress: Callable[[KillStats], None] | None = None) -> KillStats:
    """SIGKILL writers at random instants, ``kills`` times; verify the map after every kill.

    A writer (forked by ``zygote``) opens the map and adds the stream of ``seed`` (alone, or three
    sequences in one group commit: :func:`group_of`); it is killed
    after a random delay (15 % of the kills land before it is ready: during open and recovery;
    the others up to ``max_wait`` s after). After each kill: the map opened read-only holds
    every acknowledged sequence bit for bit, nothing else but whole sequences of the stream, the
    components of its edges, and passes ``check`` but for a partial index file; then a writable
    open (the recovery any writer does; odd kills) or ``check --repair`` (even kills: it must
    find nothing but files past the commit) leaves it passing ``check`` strictly. Every
    ``kills_per_map`` kills a last writer runs to completion (the stream continues: the map
    repaired itself), is verified and searched, and a fresh map starts, so that the cost of a
    kill stays flat. A violation (an ``AssertionError``) is raised, or with ``keep_going``
    recorded in the stats and the map abandoned.
    """
    stats = KillStats()
    started = time.monotonic()
    rng = np.random.default_rng(seed)
    while stats.kills < kills:
        stats.maps += 1
        path, map_seed = root / f"map-{stats.maps}", seed * 1_000_003 + stats.maps
        try:
            _one_map(path, zygote, min(kills_per_map, kills - stats.kills), map_seed, rng,
                     max_wait, stats)
        except AssertionError as exc:
            if not keep_going:
                raise
            stats.violations.append(f"map {stats.maps} (seed {map_seed}): {exc}")
        shutil.rmtree(path, ignore_errors=True)
        stats.seconds = round(time.monotonic() - started, 2)
        if progress is not None:
            progress(stats)
    return stats


def _one_map(path: Path, zygote: Zygote, kills: int, seed: int, rng: np.random.Generator,
             max_wait: float, stats: KillStats) -> None:
    create_map(path, **KILL_MAP)
    acks = path.parent / f"{path.name}.acks"
    acked: set[int] = set()
    try:
        for _ in range(kills):
            acks.unlink(missing_ok=True)
            pid = zygote.spawn(map=str(path), seed=seed, ack=str(acks), groups=True)
            if rng.random() < 0.15:
                time.sleep(rng.uniform(0, 0.004))
            else:
                wait_for_line(acks, "ready")
                time.sleep(rng.uniform(0, max_wait))
            os.kill(pid, signal.SIGKILL)
            status = zygote.wait(pid)
            assert status["signal"] == signal.SIGKILL, (status, zygote.log.read_text())
            stats.kills += 1
            stats.killed_before_ready += "ready" not in read_lines(acks)
            acked |= read_acks(acks)
            report = verify(path, seed, acked, groups=True)
            assert_ok_but_partials(report)
            stats.sequences_verified += len(acked)
            stats.partial_index_left += bool(report.violations)
            tail = any("uncommitted" in n for n in report.notes)
            stats.uncommitted_rows_left += tail
            stats.killed_inside_group += tail and len(group_of(report.checked["sequences"])) > 1
            if stats.kills % 2:  # what the next writer's open does
                with MapStore.open(path) as store:
                    stats.recovered_by_open += bool(store.recovery)
                with MapStore.open(path, readonly=True) as store:
                    report = check_map(store)
                assert report.ok, report.violations
            else:  # check --repair, on a map no writer has reopened
                fixed = repair_map(path)
                assert fixed.ok and not fixed.skipped, fixed.to_dict()
                # A kill leaves only files past the commit: nothing derived may need a rebuild.
                assert all(r.startswith(CRASH_LEFTOVERS) for r in fixed.repaired), fixed.repaired
                stats.repaired_by_check_repair += bool(fixed.repaired)

        # A last writer runs to completion: the stream continues, the map repaired itself.
        acks.unlink(missing_ok=True)
        status = zygote.run(map=str(path), seed=seed, ack=str(acks), count=5, groups=True)
        assert status == {"signal": None, "code": 0}, zygote.log.read_text()
        assert "done" in read_lines(acks)
        before = len(acked)
        acked |= read_acks(acks)
        report = verify(path, seed, acked, groups=True)
        assert report.ok, report.violations
        assert len(acked) >= before + 5
        assert_search_finds_everything(path)
        stats.sequences_committed += report.checked["sequences"]
        stats.vertices_committed += report.checked["vertices"]
    finally:
        acks.unlink(missing_ok=True)


@dataclass
class CompactKillStats:
    """What :func:`compact_kill_loop` did; ``violations`` must stay empty."""

    kills: int = 0
    maps: int = 0
    old_map_after_kill: int = 0  # killed before the switch: the old generation selected
    new_map_after_kill: int = 0  # killed after it: the new generation selected
    sequences_verified: int = 0  # live sequences compared bit for bit, over all kills
    seconds: float = 0.0
    violations: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def strictly_ok(path: Path) -> None:
    """``check`` passes and no generation is left behind (after a writer's open)."""
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok and not [n for n in report.notes if "generation" in n], (
        report.violations, report.notes)


def compact_kill_loop(root: Path, zygote: Zygote, kills: int, seed: int, *,
                      kills_per_map: int = 30, max_wait: float | None = None,
                      keep_going: bool = False,
                      progress: Callable[[CompactKillStats], None] | None = None
                      ) -> CompactKillStats:
    """SIGKILL compactions at random instants, ``kills`` times; verify after every kill.

    Each map holds six sequences of the worker stream with two removed; a ``compact`` child
    is killed a random delay (up to ``max_wait`` s; default 1.2 times a compaction of the same
    map run to completion on a copy, so kills land on both sides of the switch) after it is
    ready. After each kill the map
    read-only must pass ``check`` and mean exactly what it meant before (:func:`logical_state`:
    every live sequence bit for bit, the removed ones absent, the components of the edges),
    whichever generation is selected; every other kill a writer's open then leaves it strictly
    clean. Every ``kills_per_map`` kills a compaction runs to completion and a new map starts.
    """
    stats = CompactKillStats()
    started = time.monotonic()
    rng = np.random.default_rng(seed)
    while stats.kills < kills:
        stats.maps += 1
        path = root / f"compact-map-{stats.maps}"
        try:
            _one_compacted_map(path, zygote, min(kills_per_map, kills - stats.kills),
                               seed * 1_000_003 + stats.maps, rng, max_wait, stats)
        except AssertionError as exc:
            if not keep_going:
                raise
            stats.violations.append(f"map {stats.maps}: {exc}")
        shutil.rmtree(path, ignore_errors=True)
        stats.seconds = round(time.monotonic() - started, 2)
        if progress is not None:
            progress(stats)
    return stats


def _one_compacted_map(path: Path, zygote: Zygote, kills: int, seed: int,
                       rng: np.random.Generator, max_wait: float | None,
                       stats: CompactKillStats) -> None:
    create_map(path, dim=8, shard_rows=64)
    with MapStore.open(path) as store:
        for i in range(6):
            add_planned(store, seed, i, 40)
        store.remove_sequences([1, 4])
    with MapStore.open(path, readonly=True) as store:
        expected = logical_state(store)
        generation = store.data_path
    acks = path.parent / f"{path.name}.acks"
    if max_wait is None:  # calibrate: how long a whole compaction of this map takes here
        copy = path.parent / f"{path.name}.copy"
        shutil.copytree(path, copy)
        pid = zygote.spawn(map=str(copy), mode="compact", ack=str(acks))
        wait_for_line(acks, "ready")
        begun = time.monotonic()
        wait_for_line(acks, "done")
        max_wait = 1.2 * (time.monotonic() - begun)
        zygote.wait(pid)
        shutil.rmtree(copy)
    for kill in range(kills):
        acks.unlink(missing_ok=True)
        pid = zygote.spawn(map=str(path), mode="compact", ack=str(acks))
        wait_for_line(acks, "ready")
        time.sleep(rng.uniform(0, max_wait))
        os.kill(pid, signal.SIGKILL)
        status = zygote.wait(pid)
        stats.kills += 1
        if status["signal"] != signal.SIGKILL:  # it finished first: a compaction completed
            assert status == {"signal": None, "code": 0}, zygote.log.read_text()
        with MapStore.open(path, readonly=True) as store:
            report = check_map(store)
            assert report.ok, report.violations
            assert logical_state(store) == expected
            switched = store.data_path != generation
            generation = store.data_path
        stats.new_map_after_kill += switched
        stats.old_map_after_kill += not switched
        stats.sequences_verified += len(expected["sequences"])
        if kill % 2:
            MapStore.open(path).close()
            strictly_ok(path)
    acks.unlink(missing_ok=True)
    status = zygote.run(map=str(path), mode="compact", ack=str(acks))
    assert status == {"signal": None, "code": 0}, zygote.log.read_text()
    with MapStore.open(path, readonly=True) as store:
        assert logical_state(store) == expected
    strictly_ok(path)
    acks.unlink(missing_ok=True)


def read_lines(path: Path) -> list[str]:
    """The lines a child acknowledged in ``path`` so far."""
    return path.read_text().split("\n")[:-1] if path.exists() else []


# --- command line ------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    w = sub.add_parser("write")
    w.add_argument("map")
    w.add_argument("--seed", type=int, required=True)
    w.add_argument("--count", type=int)
    w.add_argument("--length", type=int)
    sub.add_parser("hold").add_argument("map")
    sub.add_parser("try-open").add_argument("map")
    sub.add_parser("zygote")
    args = parser.parse_args(argv)

    if args.mode == "write":
        write(args.map, args.seed, args.count, args.length, _stdout_emit)
    elif args.mode == "hold":
        with MapStore.open(args.map):
            _stdout_emit("locked")
            sys.stdin.read()
    elif args.mode == "try-open":
        start = time.monotonic()
        try:
            MapStore.open(args.map).close()
            result = {"error": None, "message": ""}
        except SprintMapError as exc:
            result = {"error": type(exc).__name__, "message": str(exc)}
        result["seconds"] = time.monotonic() - start
        print(json.dumps(result), flush=True)
    else:
        _zygote()
    return 0


if __name__ == "__main__":
    sys.exit(main())
