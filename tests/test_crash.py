"""Crash consistency with real processes and real SIGKILLs.

(a) A writer SIGKILLs itself at each named crash point of the commit protocol; (b) a writer is
killed at random instants, over and over, and restarted. After every kill the map must pass
``check``, hold every acknowledged sequence bit for bit, and hold each other sequence either
wholly or not at all. Writers add the deterministic stream of ``tests/crash_worker.py``, so the
test regenerates what each sequence must contain.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import time
from functools import cache
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.storage.check import CheckReport, check_map
from sprint_map.storage.crash import CRASH_ENV, CRASH_POINTS
from sprint_map.storage.keys import read_u64
from sprint_map.storage.store import MapStore

WORKER_PATH = Path(__file__).with_name("crash_worker.py")


def _load_worker() -> ModuleType:
    # By path, so this works whatever pytest's import mode puts on sys.path.
    spec = importlib.util.spec_from_file_location("crash_worker", WORKER_PATH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["crash_worker"] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


worker = _load_worker()

#: A partial index file is the one trace a kill may leave that ``check`` reports on a map no
#: writer has reopened yet; the next writable open deletes it.
PARTIAL_INDEX = re.compile(r"^leftover temp file index/flat\.\d{12}\.faiss\.partial$")


@cache
def planned(seed: int, index: int, dim: int, length: int | None) -> Any:
    return worker.planned_sequence(seed, index, dim, length)


def expected_edges(seed: int, index: int, dim: int, length: int | None,
                   first: list[int]) -> dict[tuple[int, int], tuple[float, int | None]]:
    out = {}
    for spec in planned(seed, index, dim, length).edges:
        ends = [first[index if s is None else s] + image for s, image in (spec.src, spec.dst)]
        out[(ends[0], ends[1])] = (spec.weight, spec.frame)  # a repeat keeps the later one
    return out


def verify(path: Path, seed: int, acked: set[int], length: int | None = None) -> CheckReport:
    """Open read-only and assert the map holds exactly a prefix of the worker stream.

    Descriptors and positions are compared in bulk (all shards against the concatenated
    stream) so that re-verifying the whole map after every kill stays cheap. Returns the check
    report; the caller decides which violations a fresh crash may leave.
    """
    with MapStore.open(path, readonly=True) as store:
        dim = store.config.dim
        records = store.sequences()
        n = len(records)
        assert acked <= set(range(n)), f"acknowledged {sorted(acked - set(range(n)))} missing"
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
        assert set(edges) <= set(range(n))
        return check_map(store)


def assert_ok_but_partials(report: CheckReport) -> None:
    unexpected = [v for v in report.violations if not PARTIAL_INDEX.match(v)]
    assert not unexpected, report.violations


def assert_search_finds_everything(path: Path) -> None:
    with MapStore.open(path, readonly=True) as store:
        total = store.stats()["vertices"]
        rows = store.shards.rows(0, total, total)
        _, ids = store.search(rows, k=1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(total))


def create_map(path: Path, **config: Any) -> None:
    MapStore.create(path, MapConfig(**config)).close()


# --- (a) named crash points ------------------------------------------------------------------

PRESENT_AFTER = {"add.committed", "index.partial_written", "index.published"}
assert set(CRASH_POINTS) > PRESENT_AFTER


@pytest.mark.parametrize("point", CRASH_POINTS)
def test_kill_at_each_crash_point(tmp_path, point):
    path, seed, length = tmp_path / "m", 7, 40
    # shard_rows=64: the fourth sequence (rows 120..159) spills into a new shard; persisting
    # the index after every add makes the index crash points fire inside that add.
    create_map(path, dim=8, shard_rows=64, index_persist_every=1, index_persist_growth=0)
    with MapStore.open(path) as store:  # three acknowledged sequences, by this process
        for i in range(3):
            worker.add_planned(store, seed, i, length)
    proc = subprocess.run(
        [sys.executable, str(WORKER_PATH), "write", str(path), "--seed", str(seed),
         "--count", "3", "--length", str(length)],
        capture_output=True, text=True, timeout=300, env={**os.environ, CRASH_ENV: point},
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert proc.stdout.split() == ["ready"]  # killed inside its first add: sequence 3

    report = verify(path, seed, {0, 1, 2}, length)
    with MapStore.open(path, readonly=True) as store:
        in_flight_committed = store.stats()["sequences"] == 4
    assert in_flight_committed == (point in PRESENT_AFTER)
    if point == "index.partial_written":
        assert report.violations == [
            "leftover temp file index/flat.000000000160.faiss.partial"]
    else:
        assert report.ok, report.violations
    # Killed after the rows were written but before the commit: 8 rows (of 32 bytes) past the
    # committed end of shard 1, and an uncommitted shard 2 (not the check's business: LMDB
    # does not know it).
    rows_written_uncommitted = point in {"add.shards_written", "add.before_commit"}
    if rows_written_uncommitted:
        assert any("shard-000001.f32 has 256 uncommitted bytes" in n for n in report.notes)
    if point in {"add.committed", "index.partial_written"}:
        # The index file still covers the first three sequences; the first search after the
        # crash must catch up from the shards (assert_search_finds_everything below).
        assert "index lags the map by 40 vertices (caught up on load)" in report.notes

    with MapStore.open(path) as store:  # recovery, then the stream continues
        recovery = store.recovery
        for i in range(store.stats()["sequences"], 6):
            worker.add_planned(store, seed, i, length)
    if rows_written_uncommitted:
        assert recovery == ["truncated shard-000001.f32 to 56 committed rows",
                            "removed uncommitted shard shard-000002.f32"]
    elif point == "index.partial_written":
        assert recovery == ["removed leftover temp file flat.000000000160.faiss.partial"]
    else:
        assert recovery == []
    report = verify(path, seed, set(range(6)), length)
    assert report.ok, report.violations
    assert_search_finds_everything(path)


# --- (b) random kills -------------------------------------------------------------------------


class Zygote:
    """Client of ``crash_worker.py zygote``: forks ready-to-run writers in milliseconds."""

    def __init__(self, log: Path) -> None:
        self.log = log
        self._stderr = log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, str(WORKER_PATH), "zygote"], stdin=subprocess.PIPE,
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
        return int(self._ask({"op": "spawn", **request})["pid"])

    def wait(self, pid: int) -> dict[str, Any]:
        return self._ask({"op": "wait", "pid": pid})

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self._stderr.close()


@pytest.fixture
def zygote(tmp_path):
    z = Zygote(tmp_path / "zygote.log")
    yield z
    z.close()


def wait_for_line(path: Path, word: str, timeout: float = 120.0) -> list[str]:
    """Poll an ack file until it holds ``word`` (generous timeout: only a hang trips it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        lines = path.read_text().split("\n") if path.exists() else []
        if word in lines:
            return lines
        time.sleep(0.005)
    raise AssertionError(f"no {word!r} in {path} after {timeout} s")


def read_acks(path: Path) -> set[int]:
    text = path.read_text() if path.exists() else ""
    return {int(line.split()[1]) for line in text.split("\n") if line.startswith("ack ")}


def kill_loop(tmp_path: Path, zygote: Zygote, kills: int, seed: int) -> dict[str, int]:
    path = tmp_path / "m"
    # Small shards and frequent index persists put shard creation and index publication
    # among the moments a kill can hit.
    create_map(path, dim=16, shard_rows=128, index_persist_every=150)
    rng = np.random.default_rng(seed)
    acked: set[int] = set()
    sizes = []
    # What the kills hit, for the report printed by the tests (never asserted: it is timing).
    seen = {"kills": kills, "before_ready": 0, "partial_index_left": 0, "uncommitted_rows_left": 0}
    for k in range(kills):
        acks = tmp_path / f"acks-{k}"
        pid = zygote.spawn(map=str(path), seed=seed, ack=str(acks))
        if rng.random() < 0.15:
            time.sleep(rng.uniform(0, 0.02))  # during open and recovery
            seen["before_ready"] += 1
        else:
            wait_for_line(acks, "ready")
            time.sleep(rng.uniform(0, 0.25))
        os.kill(pid, signal.SIGKILL)
        status = zygote.wait(pid)
        assert status["signal"] == signal.SIGKILL, (status, zygote.log.read_text())
        acked |= read_acks(acks)
        report = verify(path, seed, acked)
        assert_ok_but_partials(report)
        sizes.append(report.checked["sequences"])
        seen["partial_index_left"] += bool(report.violations)
        seen["uncommitted_rows_left"] += any("uncommitted" in n for n in report.notes)

    # A last writer runs to completion: the stream continues, the map repairs itself.
    acks = tmp_path / "acks-final"
    pid = zygote.spawn(map=str(path), seed=seed, ack=str(acks), count=5)
    assert zygote.wait(pid) == {"signal": None, "code": 0}, zygote.log.read_text()
    assert "done" in acks.read_text().split("\n")
    acked |= read_acks(acks)
    report = verify(path, seed, acked)
    assert report.ok, report.violations
    assert report.checked["sequences"] == (sizes[-1] if sizes else 0) + 5
    assert_search_finds_everything(path)
    seen["sequences"] = report.checked["sequences"]
    seen["vertices"] = report.checked["vertices"]
    return seen


def test_random_kills(tmp_path, zygote):
    print(kill_loop(tmp_path, zygote, kills=30, seed=11))


@pytest.mark.slow
def test_random_kills_long(tmp_path, zygote):
    print(kill_loop(tmp_path, zygote, kills=150, seed=12))


# --- readers beside a writer ----------------------------------------------------------------


def test_readers_see_consistent_snapshots_while_a_writer_adds(tmp_path, zygote):
    """Read-only opens in this process while another process commits: every snapshot is a
    complete prefix of the stream, and a search sees every committed row."""
    path, seed = tmp_path / "m", 5
    create_map(path, dim=16, shard_rows=128, index_persist_every=150)
    acks = tmp_path / "acks"
    pid = zygote.spawn(map=str(path), seed=seed, ack=str(acks))
    try:
        wait_for_line(acks, "ready")
        seen = []
        acked_at_start = len(read_acks(acks))
        deadline = time.monotonic() + 120
        # Keep reading until the writer has committed more since the first read, so reads and
        # writes did interleave (no timing assumption: only a hang trips the deadline).
        while len(seen) < 10 or len(read_acks(acks)) <= acked_at_start + 5:
            assert time.monotonic() < deadline, "writer made no progress"
            before = read_acks(acks)
            with MapStore.open(path, readonly=True) as store:
                n = store.stats()["sequences"]
                if n:
                    last = store.sequences()[-1]
                    rows = store.descriptors(last.seq_id)
                    _, ids = store.search(np.asarray(rows), k=1)
                    np.testing.assert_array_equal(
                        ids[:, 0], np.arange(last.first_vertex, last.first_vertex + last.length))
            verify_snapshot_prefix(path, seed)
            assert before <= set(range(n))
            seen.append(n)
        assert seen == sorted(seen)
    finally:
        os.kill(pid, signal.SIGKILL)
        zygote.wait(pid)
    assert_ok_but_partials(verify(path, seed, read_acks(acks)))


def verify_snapshot_prefix(path: Path, seed: int) -> None:
    """The data half of :func:`verify` (``check`` is not meant for a map being written)."""
    with MapStore.open(path, readonly=True) as store:
        dim = store.config.dim
        first = 0
        for i, rec in enumerate(store.sequences()):
            plan = planned(seed, i, dim, None)
            assert (rec.name, rec.first_vertex, rec.length) == (
                plan.name, first, len(plan.descriptors))
            assert store.descriptors(i).tobytes() == plan.descriptors.tobytes()
            first += rec.length
