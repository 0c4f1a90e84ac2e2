"""One writer, many readers, in real processes.

- Readers (the library in a loop, and the real ``sprint-map info``, ``check`` and ``localize``)
  run while a writer ingests drives, grows its LMDB map and persists its index: every reading is
  one consistent snapshot (the vertex count is the sum of the lengths of exactly the sequences
  present, the counters equal the records) and ``check`` finds no violation (index files the
  writer is publishing are notes while it holds the LOCK); a reader that keeps
  a snapshot open for a second sees it unchanged, and the writer commits meanwhile (never
  blocked). A reader opened before the map grew adopts the new size.
- A second writer is refused within a second by a message naming the lock (the CLI's one line
  for it: ``tests/cli/test_bad_input.py``).
- A writer killed with -9 leaves no lock (the next writer opens at once) and its LMDB reader
  slot is cleared by the next open; a reader killed with -9 during a writer's session is cleared
  by the writer's next commit. A stuck (live) reader, by contrast, pins old pages: the file grows.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import lmdb
import numpy as np
import pytest

from sprint_map.errors import MapLockedError
from sprint_map.storage.check import check_map
from sprint_map.storage.lmdb_env import MAX_DBS, lock_out_writers
from sprint_map.storage.lock import LOCK_NAME, WriterLock
from sprint_map.storage.store import LMDB_DIR, MapStore

SPRINT_MAP = "sprint-map"
DIM = 16

#: The writer's drives, known to every process: drive i has length(i) frames.
PLAN = textwrap.dedent("""
    import numpy as np
    DIM = 16
    PLACES = np.random.default_rng(7).standard_normal((60, DIM))

    def length(i):
        return 12000 if i % 10 == 3 else 20 + i % 7  # every tenth drive is big: LMDB grows

    def drive(i):
        n = length(i)
        rng = np.random.default_rng(i)
        start = int(rng.integers(0, 60))
        x = PLACES[(start + np.arange(n)) % 60] + 0.3 * rng.standard_normal((n, DIM))
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)
""")

WRITER = PLAN + textwrap.dedent("""
    import json, os, sys, time
    from sprint_map.config import MapConfig, StoreOptions
    from sprint_map.map import SprintMap

    path, count, progress = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    # Created here: the 1 MiB initial map size lasts for this session, so the map must grow.
    config = MapConfig(dim=DIM, store=StoreOptions(shard_rows=4096, initial_map_size=1 << 20,
                                                   index_persist_every=20,
                                                   index_persist_growth=0.05))
    with SprintMap.create(path, config) as m:
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.readline()  # the readers are up
        for i in range(count):
            t0 = time.time()
            if length(i) > 1000:  # appended as it is, with positions: LMDB grows
                m.add_sequence(drive(i), name=f"d{i}", positions=np.ones((length(i), 2)))
            else:
                m.ingest(drive(i), name=f"d{i}")
            print(json.dumps({"ack": i, "t0": t0, "t1": time.time(),
                              "map_size": m.store.env.map_size()}), flush=True)
            with open(progress + ".partial", "w") as f:  # for a reader holding a snapshot
                f.write(str(i))
            os.replace(progress + ".partial", progress)
            time.sleep(0.02)
""")

READER = PLAN + textwrap.dedent("""
    import json, os, sys, time
    from sprint_map.map import SprintMap
    from sprint_map.storage import lmdb_env
    from sprint_map.storage.keys import read_u64
    from sprint_map.storage.records import SequenceRecord

    # Map no more than the initial size, so that the writer's growth reaches this reader.
    lmdb_env.LmdbEnv.__init__.__kwdefaults__["map_size"] = 1 << 20
    path, stop = sys.argv[1], sys.argv[2]  # read until the file ``stop`` exists
    progress = sys.argv[3]  # the writer's last ack

    def acked():
        try:
            with open(progress) as f:
                return int(f.read())
        except (OSError, ValueError):
            return -1
    out = {"snapshots": 0, "checks": 0, "localized": 0, "inconsistent": [], "violations": [],
           "max_sequences": 0, "held": None}
    sums = np.cumsum([0] + [length(i) for i in range(1000)])

    def snapshot(store, txn):
        meta = store.env.db("meta")
        count = lambda name: read_u64(txn.get(name.encode(), db=meta))
        seqs = [SequenceRecord.decode(v) for _, v in txn.cursor(db=store.env.db("sequences"))]
        edges = sum(1 for _ in txn.cursor(db=store.env.db("edges")).iternext(values=False))
        return (count("n_sequences"), count("next_vertex_id"), count("n_edges"),
                [(s.name, s.length) for s in seqs], edges)

    def consistent(snap):
        n, vertices, n_edges, seqs, edges = snap
        return (n == len(seqs) and vertices == sums[n] and n_edges == edges
                and seqs == [(f"d{i}", length(i)) for i in range(n)])

    with SprintMap.open(path, readonly=True) as long_lived:
        size0 = long_lived.store.env.map_size()
        print(json.dumps({"ready": True}), flush=True)
        while not os.path.exists(stop):
            with long_lived.store.env.read() as txn:  # a reader open since the start
                snap = snapshot(long_lived.store, txn)
                if out["held"] is None and snap[0] >= 2:
                    # Keep this snapshot while the writer commits twice more (whatever the
                    # machine's load): the writer goes on, we see no change.
                    t0 = time.time()
                    start = acked()
                    while acked() < start + 2 and time.time() - t0 < 120:
                        time.sleep(0.01)
                    again = snapshot(long_lived.store, txn)
                    out["held"] = {"t0": t0, "t1": time.time(), "same": again == snap}
            out["snapshots"] += 1
            if not consistent(snap):
                out["inconsistent"].append(snap[:3])
            out["max_sequences"] = max(out["max_sequences"], snap[0])
            m = long_lived  # what info/check/localize do (py-lmdb: one open per process)
            info = m.info()
            if info["vertices"] != sums[info["sequences"]]:
                out["inconsistent"].append(("info", info["sequences"], info["vertices"]))
            if out["snapshots"] % 3 == 0:
                report = m.check()
                out["checks"] += 1
                out["violations"] += report.violations
            else:
                decisions, _ = m.localize(drive(500)[:10])
                if any(d.seq_id is not None and d.seq_id >= m.stats()["sequences"]
                       for d in decisions):
                    out["inconsistent"].append(("localize", info["sequences"]))
                out["localized"] += 1
        out["map_size"] = [size0, long_lived.store.env.map_size()]
    print(json.dumps(out))
""")

TRY_OPEN = textwrap.dedent("""
    import json, sys, time
    from sprint_map.errors import MapLockedError
    from sprint_map.storage.store import MapStore
    t0 = time.monotonic()
    try:
        MapStore.open(sys.argv[1]).close()
        print(json.dumps({"opened": True}))
    except MapLockedError as exc:
        print(json.dumps({"seconds": time.monotonic() - t0, "message": str(exc)}))
""")

#: Opens the map, holds a read snapshot (not in mode "idle"), prints "holding", then adds
#: ``count`` sequences and sleeps until killed.
HOLDER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from sprint_map.storage.store import MapStore
    path, mode, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
    store = MapStore.open(path, readonly=(mode != "writer"))
    if mode != "idle":
        txn = store.env.env.begin()  # a read snapshot: a reader slot with this pid
    print("holding", flush=True)
    for i in range(count):
        store.add_sequence(np.ones((3, store.config.dim)), name=f"held-{i}")
    print("added", flush=True)
    time.sleep(600)
""")


def _python(code: str, *args: str, **kwargs: Any) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def _json_lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_readers_see_consistent_snapshots_and_never_block_the_writer(tmp_path, rng):
    path = tmp_path / "live.map"
    query = tmp_path / "query.npy"
    np.save(query, rng.standard_normal((12, DIM)).astype(np.float32))
    progress = tmp_path / "progress"
    writer = _python(WRITER, str(path), "30", str(progress), stdin=subprocess.PIPE)
    readers: list[subprocess.Popen] = []
    try:
        assert writer.stdout is not None and writer.stdin is not None
        assert json.loads(writer.stdout.readline()) == {"ready": True}
        readers.append(_python(READER, str(path), str(tmp_path / "stop"), str(progress)))
        assert readers[0].stdout is not None
        assert json.loads(readers[0].stdout.readline()) == {"ready": True}
        writer.stdin.write("go\n")
        writer.stdin.flush()
        acks = [json.loads(writer.stdout.readline())]
        # The real CLI beside the writer, and a second writer that must be refused at once.
        cli = {cmd: subprocess.Popen([SPRINT_MAP, cmd, str(path), *extra, "--json"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for cmd, extra in (("info", []), ("check", []), ("localize", [str(query)]))}
        second = _python(TRY_OPEN, str(path))  # (the CLI's message: tests/cli/test_bad_input.py)
        out, err = writer.communicate(timeout=300)
        assert writer.returncode == 0, err
        (tmp_path / "stop").touch()
        acks += _json_lines(out)
        results = {cmd: p.communicate(timeout=120) + (p.returncode,) for cmd, p in cli.items()}
        refused = json.loads(second.communicate(timeout=120)[0])
        reader_out, reader_err = readers[0].communicate(timeout=120)
        assert readers[0].returncode == 0, reader_err
    finally:
        for proc in [writer, *readers]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert [a["ack"] for a in acks] == list(range(30))
    # The library reader: consistent snapshots throughout, check clean, the growth adopted.
    seen = json.loads(reader_out)
    assert seen["inconsistent"] == [] and seen["violations"] == []
    assert seen["snapshots"] >= 5 and seen["checks"] >= 1 and seen["localized"] >= 1
    assert seen["max_sequences"] >= 2
    assert seen["map_size"][1] > seen["map_size"][0] == 1 << 20, (seen, acks)  # adopted
    assert max(a["map_size"] for a in acks) > 1 << 20
    # The held snapshot did not move, and the writer committed while it was held.
    held = seen["held"]
    assert held is not None and held["same"]
    during = [a for a in acks if held["t0"] < a["t1"] < held["t1"]]
    assert len(during) >= 2, (held, [(a["t0"], a["t1"]) for a in acks])
    # The real commands beside the writer.
    for cmd, (_stdout, stderr, code) in results.items():
        assert code == 0 or (cmd == "check" and code == 1), (cmd, stderr)
        assert "Traceback" not in stderr
    info = json.loads(results["info"][0])
    assert info["vertices"] == sum(20 + i % 7 if i % 10 != 3 else 12000
                                   for i in range(info["sequences"]))
    assert json.loads(results["check"][0])["violations"] == []
    assert len(json.loads(results["localize"][0])["decisions"]) == 12
    # A second writer: refused at once, the message names the lock file and the holder.
    assert refused["seconds"] < 1.0
    assert refused["message"] == (f"map is locked by another writer (pid {writer.pid}): "
                                  f"{path / LOCK_NAME}")


def _readers(path: Path) -> set[int]:
    """Pids in the LMDB reader table, read without clearing stale slots."""
    env = lmdb.open(str(path / LMDB_DIR), readonly=True, max_dbs=MAX_DBS, max_readers=256)
    try:
        table = env.readers()
    finally:
        env.close()
    return {int(line.split()[0]) for line in table.splitlines()[1:] if line.strip()}


def _add_small(store: MapStore, tag: str, n: int) -> int:
    """Add ``n`` small sequences; return how much ``data.mdb`` grew."""
    data = store.path / LMDB_DIR / "data.mdb"
    before = data.stat().st_size
    for i in range(n):
        store.add_sequence(np.ones((2, store.config.dim)), name=f"{tag}-{i}",
                           positions=np.ones((2, 2)))
    return data.stat().st_size - before


def _start_holder(path: Path, mode: str, count: int = 0) -> subprocess.Popen:
    proc = _python(HOLDER, str(path), mode, str(count))
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "holding"
    assert proc.stdout.readline().strip() == "added"
    return proc


def _kill(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(timeout=60) == -signal.SIGKILL


def test_killed_writers_and_readers_leave_no_lock_and_no_stale_reader_slot(make_map):
    built = make_map((5,), dim=DIM)
    path = built.path
    # LMDB resets its lock file when the last process leaves, so a stale slot matters while
    # others keep the map open: a bystander does, throughout.
    bystander = _start_holder(path, "idle")
    # A writer killed with -9 while it holds a read snapshot and the writer lock.
    writer = _start_holder(path, "writer", count=3)
    try:
        assert writer.pid in _readers(path)  # its slot
        _kill(writer)
    finally:
        writer.kill()
        writer.wait()
    assert writer.pid in _readers(path)  # LMDB cannot clear the slot of a dead process itself
    t0 = time.monotonic()
    store = MapStore.open(path)  # no stale lock: the kernel dropped the flock
    try:
        assert time.monotonic() - t0 < 1.0
        assert writer.pid not in _readers_of(store)  # the writer's open cleared the dead slot
        assert [s.name for s in store.sequences()][-3:] == ["held-0", "held-1", "held-2"]
        _add_small(store, "warm", 30)  # reach a steady state of page reuse
        free_growth = _add_small(store, "free", 150)
        # A live reader that keeps an old snapshot pins pages: the file grows.
        stuck = _start_holder(path, "reader")
        try:
            pinned_growth = _add_small(store, "pinned", 150)
            # Killed with -9: the writer's next commit clears its slot, and the pages are
            # reused again within the same session.
            _kill(stuck)
        finally:
            stuck.kill()
            stuck.wait()
        _add_small(store, "after-kill", 1)
        assert stuck.pid not in _readers_of(store)
        _add_small(store, "rewarm", 30)
        after_growth = _add_small(store, "after", 150)
    finally:
        store.close()
        _kill(bystander)
    assert pinned_growth > 4 * max(free_growth, 4096), (free_growth, pinned_growth)
    assert after_growth <= max(2 * free_growth, 4 * 4096), (free_growth, after_growth)


def _readers_of(store: MapStore) -> set[int]:
    table = store.env.env.readers()
    return {int(line.split()[0]) for line in table.splitlines()[1:] if line.strip()}


def test_lock_free_readers_and_writers_exclude_each_other(make_map):
    """A reader that cannot write LMDB's lock file (a read-only map directory) reads without it,
    so it holds a shared flock on the map's LOCK instead: no writer meanwhile, and none before."""
    built = make_map((3,), dim=DIM)
    lock = WriterLock(built.path)
    lock.acquire()
    try:
        with pytest.raises(MapLockedError, match="cannot register as an LMDB reader"):
            lock_out_writers(built.path)
    finally:
        lock.release()
    fd = lock_out_writers(built.path)
    assert fd is not None
    try:
        with pytest.raises(MapLockedError, match=LOCK_NAME):
            MapStore.open(built.path)
    finally:
        os.close(fd)
    MapStore.open(built.path).close()


def test_check_beside_a_live_writer_treats_files_in_flight_as_notes(make_map):
    built = make_map((5,), dim=DIM)
    writer = _start_holder(built.path, "writer")
    try:
        index = built.path / "index"
        (index / "flat.000000000009.faiss.partial").write_bytes(b"being written")
        (index / "flat.000000000009.faiss").write_bytes(b"renamed after our snapshot")
        with MapStore.open(built.path, readonly=True) as store:
            report = check_map(store)
        assert report.ok, report.violations
    finally:
        _kill(writer)


# --- localize across merging ingests and removes ------------------------------------------------

#: Drives over disjoint stretches of the 60 places start as separate components; the writer's
#: drives each bridge two stretches (their components merge), its removes split them again.
CHURN_PLAN = PLAN + textwrap.dedent("""
    def walk(seed, start, n):
        rng = np.random.default_rng(seed)
        x = PLACES[(start + np.arange(n)) % 60] + 0.3 * rng.standard_normal((n, DIM))
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    def batches(x, rows=20):
        return [x[i : i + rows] for i in range(0, len(x), rows)]
""")

#: Ingests ``count`` drives (localised and merged) and removes the drive ingested two commits
#: earlier after every fourth, pausing between commits; one line per commit. After each remove
#: it waits until every reader (the progress files named after it) has finished a run begun
#: after the remove, so the readers cross commits however loaded the machine is.
CHURN_WRITER = CHURN_PLAN + textwrap.dedent("""
    import json, sys, time
    from sprint_map.map import SprintMap

    path, count, progress = sys.argv[1], int(sys.argv[2]), sys.argv[3:]

    def runs():
        return [int(open(f).read() or 0) for f in progress]

    def readers_ran():
        # two more runs: the second began after this commit
        want, deadline = [r + 2 for r in runs()], time.monotonic() + 300
        while any(r < w for r, w in zip(runs(), want)):
            if time.monotonic() > deadline:
                sys.exit("the readers made no progress in 300 s")
            time.sleep(0.01)

    with SprintMap.open(path) as m:
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.readline()  # the readers are up
        for i in range(count):
            m.ingest(walk(100 + i, 15 * i + 8, 25), name=f"c{i}")
            print(json.dumps({"ingest": i}), flush=True)
            time.sleep(0.1)
            if i % 4 == 3:  # 5 removes in 20 ingests
                m.remove_sequences([f"c{i - 2}"])
                print(json.dumps({"remove": i - 2}), flush=True)
                readers_ran()
""")

#: Localises a 240-frame drive (12 searches of 20 frames) over and over, one open as a server
#: would, until the file ``stop`` exists; counts runs, failures and the map states it saw, and
#: writes its count of runs to the file ``progress`` after each. Mode "smooth" also smooths each
#: drive (``localize --smooth``: a second pass after the first).
CHURN_READER = CHURN_PLAN + textwrap.dedent("""
    import json, os, sys, traceback
    from sprint_map.map import SprintMap

    path, stop, mode, progress = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
    query = batches(walk(900, 0, 240))
    out = {"runs": 0, "failures": [], "states": set()}
    with SprintMap.open(path, readonly=True) as m:
        print(json.dumps({"ready": True}), flush=True)
        while not os.path.exists(stop) or out["runs"] < 3:
            try:
                if mode == "smooth":
                    decisions, _ = m.localize(np.concatenate(query), smooth=True)
                else:
                    decisions = m.localizer().localize(iter(query))
                assert len(decisions) == 240
            except Exception:
                out["failures"].append(traceback.format_exc(limit=-4))
            out["runs"] += 1
            out["states"].add(m.stats()["vertices"])
            with open(progress + ".partial", "w") as f:
                f.write(str(out["runs"]))
            os.replace(progress + ".partial", progress)
    out["states"] = len(out["states"])
    print(json.dumps(out))
""")


@pytest.mark.slow
def test_localize_survives_merging_ingests_and_removes(tmp_path):
    """Issue 14, item 7: a reader's ``localize`` died while a writer committed (a merge:
    "vertex N is not in the component the source named"; a remove: "vertex N belonged to a
    removed sequence"). Every localize reads one pinned snapshot now: 0 failures in library
    readers (causal and smoothed) and in the real ``sprint-map localize`` across 20 merging
    ingests and 5 removes."""
    from sprint_map.config import MapConfig
    from sprint_map.map import SprintMap

    path = tmp_path / "churn.map"
    plan: dict[str, Any] = {}
    exec(CHURN_PLAN, plan)  # the drives every process shares
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        for i in range(4):  # four stretches of 15 places: four components
            m.add_sequence(plan["walk"](i, 15 * i, 15), name=f"d{i}")
    query = tmp_path / "query.npy"
    np.save(query, plan["walk"](900, 0, 240))
    progress = [tmp_path / f"{mode}.runs" for mode in ("causal", "smooth")]
    for file in progress:
        file.write_text("0")
    writer = _python(CHURN_WRITER, str(path), "20", *map(str, progress), stdin=subprocess.PIPE)
    readers = [_python(CHURN_READER, str(path), str(tmp_path / "stop"), mode, str(file))
               for mode, file in zip(("causal", "smooth"), progress, strict=True)]
    cli: list[subprocess.Popen] = []
    try:
        assert writer.stdout is not None and writer.stdin is not None
        assert json.loads(writer.stdout.readline()) == {"ready": True}
        for reader in readers:
            assert reader.stdout is not None
            assert json.loads(reader.stdout.readline()) == {"ready": True}
        writer.stdin.write("go\n")
        writer.stdin.flush()
        # The real CLI beside the writer, one run after another while it writes.
        while writer.poll() is None:
            cli.append(subprocess.Popen([SPRINT_MAP, "localize", str(path), str(query),
                                         "--json", "--quiet"], stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True))
            cli[-1].wait(timeout=120)
        out, err = writer.communicate(timeout=120)
        assert writer.returncode == 0, err
        (tmp_path / "stop").touch()
        seen = [json.loads(r.communicate(timeout=120)[0]) for r in readers]
        assert all(r.returncode == 0 for r in readers)
    finally:
        for proc in [writer, *readers, *cli]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    commits = _json_lines(out)
    assert sum("ingest" in c for c in commits) == 20 and sum("remove" in c for c in commits) == 5
    for reader in seen:
        assert reader["failures"] == [], f"{len(reader['failures'])} of {reader['runs']} runs " \
                                         f"failed; the first:\n{reader['failures'][0]}"
        assert reader["runs"] >= 5 and reader["states"] >= 5, reader  # ran across commits
    for proc in cli:
        stdout, stderr = proc.communicate()
        assert proc.returncode == 0, stderr
        assert len(json.loads(stdout)["decisions"]) == 240
    assert cli
