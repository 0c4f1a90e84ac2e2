"""Fault injection: I/O errors on every file call in turn, a full disk, a full LMDB map, and
simulated power loss.

Each write operation (``add_sequence`` with edges, a streamed ``ingest`` that localises and merges,
an index persist, a group commit of appended drives) is first run on a copy of a template map with a :class:`CallRecorder` on the
file seam (``sprint_map.util.atomic``) to enumerate its calls; then, on a fresh copy each
time, the 1st, 2nd, ... call is failed with EIO and with ENOSPC. The oracle is the map's state
(every sequence, descriptor byte, position, edge, component) before and after a clean run of the
same operation: after the fault, and after a writer's reopen, the map must be in exactly one of
the two states (the "after" one only when the call returned), and ``check`` must pass.

``RLIMIT_FSIZE`` (a full disk) and an LMDB map that cannot grow (``RLIMIT_AS``) need a process of
their own: they run in a subprocess, and the map is verified in this one.

Power loss: :class:`PowerLossSimulator` cuts the power at every call of a writer's session in
turn (open with recovery, adds spanning shards, index persists, close) and rewrites the files as
a disk might hold them; LMDB keeps exactly the commits that returned. After a writer's reopen,
``check`` passes and the map holds every acknowledged sequence and at most the one in flight.
"""

from __future__ import annotations

import errno
import json
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import InvalidDescriptorError, StorageIOError
from sprint_map.map import SprintMap
from sprint_map.storage import sequence_writer
from sprint_map.storage.check import check_map
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import INDEX_DIR, LMDB_DIR, SHARDS_DIR, MapStore
from sprint_map.testing.faults import (
    CallRecorder,
    FaultInjector,
    PowerCut,
    PowerLossSimulator,
    installed,
)
from sprint_map.util import atomic

DIM = 4
ERRNOS = {"EIO": errno.EIO, "ENOSPC": errno.ENOSPC}


# --- the oracle ---------------------------------------------------------------------------------


def map_state(path: Path) -> dict[str, Any]:
    """Everything a user can read from the map, timestamps aside; asserts that check passes."""
    with MapStore.open(path, readonly=True) as store:
        return map_state_of_open(store)


def reopen_and_state(path: Path) -> dict[str, Any]:
    """What the next session sees: a writer's open (recovery) and close, then the state."""
    MapStore.open(path).close()
    return map_state(path)


def abandon(store: MapStore) -> None:
    """What the death of the process does to an open store: nothing flushed, LMDB as it is."""
    store.shards.close()
    store.env.close()
    store.env = None  # type: ignore[assignment]
    if store.writer_lock is not None:
        store.writer_lock.release()


# --- the template map and the operations ---------------------------------------------------------


def _drive(seed: int, n: int) -> np.ndarray:
    x = np.random.default_rng(seed).standard_normal((n, DIM)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of 3 sequences (13 vertices; shards of 8 rows, the second one open), an index file
    persisted after every commit, and a leftover uncommitted tail a writer's open must cut."""
    path = tmp_path_factory.mktemp("faults") / "template"
    config = MapConfig(dim=DIM, store=StoreOptions(shard_rows=8, index_persist_every=1, index_persist_growth=0))
    with MapStore.create(path, config) as store:
        store.add_sequence(_drive(1, 6), name="a", positions=np.zeros((6, 2)))
        store.add_sequence(_drive(2, 4), name="b", edges=[EdgeSpec((None, 0), (0, 5), 0.9, 0)])
        store.add_sequence(_drive(3, 3), name="c")
    return path


def fresh(template: Path, tmp_path: Path, name: str) -> Path:
    dest = tmp_path / name
    shutil.copytree(template, dest)
    return dest


def op_add(path: Path) -> None:
    """A merge: 11 rows over two shards (one new file), positions, edges to two sequences."""
    with MapStore.open(path) as store:
        store.add_sequence(
            _drive(4, 11), name="new", positions=np.arange(33.0).reshape(11, 3),
            edges=[EdgeSpec((None, 1), (0, 2), 0.8, 1), EdgeSpec((1, 3), (None, 10), 0.6, 10)],
        )


def op_ingest(path: Path) -> None:
    """The lifelong step: localise a drive in 3 streamed batches, merge it with its edges."""
    with SprintMap.open(path) as m:
        drive = _drive(1, 6) + 0.01 * _drive(5, 6)
        m.ingest(iter([drive[:2], drive[2:5], drive[5:]]), name="new")


def op_persist(path: Path) -> None:
    """An index persist: the index is loaded (a search) and written (``flush``)."""
    with MapStore.open(path) as store:
        store.search(_drive(6, 1), k=2)
        for stale in (path / INDEX_DIR).iterdir():  # make the persist rewrite the file
            stale.unlink()
        store.index.active.persisted = 0
        store.flush()


def add_group(store: MapStore) -> None:
    """Appended drives in one group commit (``ingest A B C --no-merge``): g (positions, an edge
    to a), x (its stream fails after its first batch crossed into a new shard file: dropped)
    and h (streamed, an edge to g, staged in the same group); one fsync, one transaction."""
    with store.begin_group() as group:
        group.add(_drive(7, 5), name="g", positions=np.ones((5, 2)),
                  edges=[EdgeSpec((None, 0), (0, 1), 0.5, 0)])
        with pytest.raises(InvalidDescriptorError):
            group.add(iter([_drive(8, 4), np.full((1, DIM), np.nan)]), name="x")
        g = group.staged[0].seq_id
        group.add(iter([_drive(9, 3), _drive(10, 2)]), name="h",
                  edges=[EdgeSpec((None, 4), (g, 0), 0.7, 4)])
        assert [r.sequence.name for r in group.commit()] == ["g", "h"]


def op_group(path: Path) -> None:
    with MapStore.open(path) as store:
        add_group(store)


OPERATIONS: dict[str, Callable[[Path], None]] = {
    "add": op_add, "ingest": op_ingest, "persist": op_persist, "group": op_group,
}


def recorded_calls(template: Path, tmp_path: Path, op: Callable[[Path], None]
                   ) -> list[tuple[str, Path]]:
    """The file calls ``op`` makes between opening the map and closing it."""
    path = fresh(template, tmp_path, "recorded")
    recorder = CallRecorder()
    with installed(recorder):
        op(path)
    shutil.rmtree(path)
    return [(call, target.relative_to(path)) for call, target in recorder.calls]


# --- I/O errors on every call in turn -----------------------------------------------------------


@pytest.mark.parametrize("op_name", OPERATIONS)
def test_io_error_on_every_file_call(template, tmp_path, op_name):
    op = OPERATIONS[op_name]
    before = map_state(template)
    calls = recorded_calls(template, tmp_path, op)
    clean = fresh(template, tmp_path, "clean")
    op(clean)
    after = reopen_and_state(clean)
    assert after != before or op_name == "persist"
    assert {c for c, _ in calls} >= {"write", "fsync", "fsync_dir", "replace"}
    injected = 0
    for n, (call, target) in enumerate(calls, start=1):
        for err_name, err in ERRNOS.items():
            path = fresh(template, tmp_path, f"{op_name}-{n}-{err_name}")
            injector = FaultInjector(n, err, seed=n)
            raised: StorageIOError | None = None
            with installed(injector):
                try:
                    op(path)
                except StorageIOError as exc:
                    raised = exc
            case = f"{err_name} on call {n} ({call} {target.name})"
            assert [(c, t.relative_to(path)) for c, t in injector.failed] == [(call, target)], case
            injected += 1
            if raised is not None:
                message = str(raised)
                assert "\n" not in message and "(injected)" in message, case
            # A failed fsync is final: the file is never fsynced again unless rewritten first
            # (its dirty pages may be gone: a second fsync could "succeed" over lost data).
            if call == "fsync":
                failed_at = [entry[2] for entry in injector.log].index(True)
                later = [c for c, t, _ in injector.log[failed_at + 1:] if t == path / target]
                assert later[:1] != ["fsync"], case
            state = reopen_and_state(path)
            if op_name == "persist":
                assert raised is not None and state == before, case
            else:
                # Failed <=> nothing committed; returned <=> committed once (a failure after
                # the commit, saving the index cache, is a warning, never an error).
                assert state == (before if raised is not None else after), case
            shutil.rmtree(path)
    assert injected == 2 * len(calls)


@pytest.mark.parametrize("op_name", ["add", "ingest"])
def test_a_dead_disk_fails_the_rollback_too_and_the_next_open_recovers(template, tmp_path,
                                                                       op_name):
    """Every call from the first write on fails: the rollback cannot truncate the shards. The
    original error is the one reported; the rows stay invisible; the next open removes them."""
    before = map_state(template)
    path = fresh(template, tmp_path, "dead")
    shard = path / SHARDS_DIR / "shard-000001.f32"
    injector = FaultInjector(1, errno.EIO, ops={"fsync"}, sticky=True)
    with installed(injector), pytest.raises(StorageIOError, match="cannot write descriptor shard"):
        OPERATIONS[op_name](path)
    assert injector.failed[:2] == [("fsync", shard), ("truncate", shard)]
    assert shard.stat().st_size > 5 * DIM * 4  # the uncommitted rows are still there
    assert reopen_and_state(path) == before


def test_rollback_failure_is_kept_as_a_warning(template, tmp_path):
    path = fresh(template, tmp_path, "warn")
    store = MapStore.open(path)
    try:
        injector = FaultInjector(2, errno.EIO, ops={"fsync", "truncate"}, sticky=True)
        with installed(injector), pytest.raises(StorageIOError, match="Input/output error"):
            store.add_sequence(_drive(7, 3))
        assert any("uncommitted rows not yet removed" in w for w in store.warnings)
        # The same session can go on: the next append cuts the stale tail first.
        store.add_sequence(_drive(8, 2), name="after")
    finally:
        store.close()
    state = reopen_and_state(path)
    assert [s[1] for s in state["sequences"]] == ["a", "b", "c", "after"]


def test_index_failures_after_the_commit_are_warnings_not_errors(template, tmp_path):
    """A failed index persist must not fail an add whose sequence is committed: a retry would
    add it twice (or be refused as a duplicate name, confusingly)."""
    path = fresh(template, tmp_path, "idx")
    with MapStore.open(path) as store:
        with installed(FaultInjector(1, errno.ENOSPC, ops={"replace"}, sticky=True)):
            result = store.add_sequence(_drive(9, 2), name="kept")
            store.close()  # persisting at close fails too: a warning as well
        assert result.sequence.name == "kept"
        assert len(store.warnings) == 2
        assert all("No space left on device (injected)" in w for w in store.warnings)
    state = reopen_and_state(path)
    assert state["sequences"][-1][1] == "kept"


def test_the_seam_covers_every_file_call_of_the_write_paths():
    """Durable writes go through ``atomic``: no module of the store calls the OS directly
    (but the lock file, which holds no data, and index_store's removal of stale index files,
    which the power-loss simulator reconciles from the directory listing)."""
    storage = Path(sequence_writer.__file__).parent
    direct = ("os.pwrite(", "os.write(", "os.fsync(", "os.replace(", "os.rename(",
              "os.truncate(", "os.ftruncate(", ".write_bytes(", ".write_text(")
    # lock.py: the lock file holds no data.
    exempt = ("atomic.py", "faults.py", "lock.py")
    offenders = []
    for module in sorted(storage.glob("*.py")):
        if module.name in exempt:
            continue
        text = module.read_text()
        offenders += [f"{module.name}: {call}" for call in direct if call in text]
    assert offenders == []


# --- RLIMIT_FSIZE and RLIMIT_AS: a process of their own -----------------------------------------

LIMITED_WORKER = textwrap.dedent("""
    import json, resource, sys
    import numpy as np
    from sprint_map.config import MapConfig, StoreOptions
    from sprint_map.errors import SprintMapError
    from sprint_map.storage.store import MapStore

    def vm_bytes():
        for line in open("/proc/self/status"):
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024

    path, what, rows = sys.argv[1], sys.argv[2], int(sys.argv[3])
    rng = np.random.default_rng(0)
    out = {}
    if what == "address-space":
        # The map size given at creation lasts for this session only: fill the map nearly to
        # its end here, so that the commit below overflows it and the map must grow.
        size = 8 << 20
        store = MapStore.create(path, MapConfig(dim=4, store=StoreOptions(shard_rows=1 << 20,
                                                      initial_map_size=size)))
        used = lambda: (store.env.env.info()["last_pgno"] + 1) * 4096
        while used() < size - (320 << 10):
            k = max(200, (size - used() - (320 << 10)) // 64)
            store.add_sequence(np.ones((k, 4)), positions=rng.standard_normal((k, 4)))
        out["filled"] = store.stats()
    else:
        store = MapStore.open(path)
    data = rng.standard_normal((rows, store.config.dim)).astype(np.float32)
    pos = rng.standard_normal((rows, 4))
    if what == "fsize-index":
        store.search(data[:1], k=1)  # the index is loaded; the flush below writes it
    if what.startswith("fsize"):
        limit = int(sys.argv[4])
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
    else:  # address space for the commit (4 MiB), not for mapping the map twice as large
        resource.setrlimit(resource.RLIMIT_AS, (vm_bytes() + (4 << 20), resource.RLIM_INFINITY))
    try:
        if what == "fsize-index":
            store.flush()
        else:
            store.add_sequence(data, name="big", positions=pos)
        out["result"] = "ok"
    except SprintMapError as exc:
        out["error"], out["message"] = type(exc).__name__, str(exc)
    store.close()
    out["warnings"] = list(store.warnings)
    print(json.dumps(out))
""")


def start_limited(path: Path, what: str, rows: int, limit: int = 0) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", LIMITED_WORKER, str(path), what, str(rows),
                             str(limit)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def result_of(proc: subprocess.Popen) -> dict[str, Any]:
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    return json.loads(out)


def run_limited(path: Path, what: str, rows: int, limit: int = 0) -> dict[str, Any]:
    return result_of(start_limited(path, what, rows, limit))


def test_a_full_disk_rlimit_fsize(template, tmp_path):
    """``RLIMIT_FSIZE`` makes every write past the limit fail with EFBIG: on a shard, on LMDB's
    data file at commit, and on the index file. Each aborts with one line and commits nothing."""
    # 1. A shard: 20000 rows of 16 bytes need 320 kB in one file, past LMDB's file size.
    shard_map = tmp_path / "fsize-shard"
    with MapStore.create(shard_map, MapConfig(dim=DIM, store=StoreOptions(shard_rows=1 << 20))) as store:
        store.add_sequence(_drive(1, 5), name="a")
    shard_before = map_state(shard_map)
    size = (shard_map / LMDB_DIR / "data.mdb").stat().st_size
    shard_proc = start_limited(shard_map, "fsize-shard", 20000, limit=size + (64 << 10))
    # 2. LMDB's data file: shards of 8 rows stay tiny, 6000 positions do not fit in LMDB.
    before = map_state(template)
    path = fresh(template, tmp_path, "fsize-lmdb")
    size = (path / LMDB_DIR / "data.mdb").stat().st_size
    out = run_limited(path, "fsize-lmdb", 6000, limit=size + 4096)
    shard_out = result_of(shard_proc)
    assert shard_out["error"] == "StorageIOError"
    assert shard_out["message"] == ("cannot write descriptor shard shard-000000.f32: "
                                    "File too large")
    assert reopen_and_state(shard_map) == shard_before
    assert out["error"] == "StorageIOError"
    # LMDB reports the short write at the limit as EIO (a write error, whatever its cause).
    assert out["message"] in ("LMDB write failed: mdb_txn_commit: File too large",
                              "LMDB write failed: mdb_txn_commit: Input/output error")
    assert reopen_and_state(path) == before


def test_a_full_disk_while_writing_the_index(template, tmp_path):
    """The index file: an explicit flush fails, the one at close is a warning; no torn file is
    published (FAISS's ``write_index`` returns normally after a failed write)."""
    before = map_state(template)
    path = fresh(template, tmp_path, "fsize-index")
    for stale in (path / INDEX_DIR).iterdir():
        stale.unlink()
    out = run_limited(path, "fsize-index", 1, limit=64)
    assert out["error"] == "StorageIOError" and "flat.000000000013.faiss" in out["message"]
    assert out["warnings"] and "index cache not saved" in out["warnings"][0]  # at close
    assert reopen_and_state(path) == before
    assert not list((path / INDEX_DIR).iterdir())


def test_lmdb_map_full_in_a_batch_grows_and_retries_once_committed(tmp_path, monkeypatch):
    """The commit of 30000 positions overflows a 1 MiB map in the middle of its transaction:
    the map doubles and the transaction re-runs from scratch; it commits exactly once."""
    config = MapConfig(dim=DIM, store=StoreOptions(shard_rows=50000, initial_map_size=1 << 20))
    runs = []
    with MapStore.create(tmp_path / "m", config) as store:
        store.add_sequence(_drive(1, 5), name="first")
        commit = sequence_writer.write_sequence

        def counting(store, txn, record, *args):
            runs.append(record.name)
            return commit(store, txn, record, *args)

        monkeypatch.setattr(sequence_writer, "write_sequence", counting)
        n = 30000
        store.add_sequence(_drive(2, n), name="big", positions=np.ones((n, 2)),
                           edges=[EdgeSpec((None, 7), (0, 1), 0.7, 7)])
        assert store.env.map_size() >= 2 << 20
        assert runs.count("big") >= 2  # re-run after growing
    state = reopen_and_state(tmp_path / "m")
    assert state["stats"] == {"sequences": 2, "vertices": n + 5, "edges": 1, "components": 1}
    assert state["sequences"][1][1] == "big"


def test_lmdb_map_that_cannot_grow_fails_cleanly(tmp_path):
    """With no address space left for a larger map, growing fails: one line, nothing committed,
    and the map opens as before in the next process."""
    out = run_limited(tmp_path / "m", "address-space", 12000)
    assert out["error"] == "StorageIOError", out
    assert out["message"].startswith("the map's LMDB is full (8388608 bytes) and cannot grow to "
                                     "16777216 bytes: mdb_env_set_mapsize: Cannot allocate memory")
    assert out["message"].endswith("nothing was committed")
    state = reopen_and_state(tmp_path / "m")
    assert state["stats"] == out["filled"]
    assert "big" not in [s[1] for s in state["sequences"]]


# --- simulated power loss -----------------------------------------------------------------------


def _session_steps() -> list[tuple[str, Callable[[MapStore], None]]]:
    """A writer's session after the template: each step is acknowledged once it returns."""
    return [
        ("add d", lambda s: s.add_sequence(_drive(10, 9), name="d",
                                           positions=np.ones((9, 3)),
                                           edges=[EdgeSpec((None, 0), (2, 1), 0.7, 0)])),
        ("add e", lambda s: s.add_sequence(_drive(11, 2), name="e",
                                           edges=[EdgeSpec((1, 0), (None, 1), 0.5, 1)])),
        ("flush", lambda s: s.flush()),
        ("add f (streamed)", _add_streamed),
        ("group g, h (x dropped)", add_group),
    ]


def _add_streamed(store: MapStore) -> None:
    with store.begin_sequence("f") as writer:
        for batch in np.array_split(_drive(12, 7), 3):
            writer.append(batch)
        writer.commit(edges=[EdgeSpec((None, 6), (0, 0), 0.9, 6)])


def _dirty(template: Path, tmp_path: Path, name: str) -> Path:
    """The template after a crash: an uncommitted shard tail and a leftover partial index."""
    path = fresh(template, tmp_path, name)
    with open(path / SHARDS_DIR / "shard-000001.f32", "ab") as fh:
        fh.write(b"\x7f" * 37)
    (path / INDEX_DIR / "flat.000000000099.faiss.partial").write_bytes(b"junk")
    return path


def _run_session(path: Path, hook: Any) -> int:
    """Open, run the steps, close, under ``hook``; return how many steps were acknowledged."""
    acked = 0
    store = None
    with installed(hook):
        try:
            store = MapStore.open(path)
            for _, step in _session_steps():
                step(store)
                acked += 1
            store.close()
        except PowerCut:
            if store is not None and store.env is not None:
                abandon(store)
    return acked


def test_power_loss_at_every_file_call(template, tmp_path):
    # The state after each acknowledged step, from a clean run.
    path = _dirty(template, tmp_path, "clean")
    states = [reopen_and_state(path)]
    with MapStore.open(path) as store:
        for _, step in _session_steps():
            step(store)
            store.flush()
            states.append(map_state_of_open(store))
    counter = PowerLossSimulator(_dirty(template, tmp_path, "count"))
    assert _run_session(counter.root, counter) == len(_session_steps())
    total = counter.calls
    assert total > 30
    cuts = lost = 0
    for cut_at in range(1, total + 1):
        for seed in (0, 1):
            path = _dirty(template, tmp_path, f"cut-{cut_at}-{seed}")
            sim = PowerLossSimulator(path, cut_at=cut_at, seed=cut_at * 2 + seed)
            acked = _run_session(path, sim)
            assert sim.cut, cut_at
            changes = sim.apply()
            lost += bool(changes)
            cuts += 1
            state = reopen_and_state(path)
            # Every acknowledged step survives; the one in flight is wholly there or absent.
            assert state in states[acked: acked + 2], (cut_at, seed, changes)
            shutil.rmtree(path)
    assert cuts == 2 * total and lost > 0


def map_state_of_open(store: MapStore) -> dict[str, Any]:
    """:func:`map_state` of a map this process holds open (for reading or writing)."""
    report = check_map(store)
    assert report.ok, report.violations
    seqs = []
    for rec in store.sequences():
        pos = store.positions(rec.seq_id)
        seqs.append((rec.seq_id, rec.name, rec.length, rec.first_vertex, rec.source,
                     store.descriptors(rec.seq_id).tobytes(),
                     None if pos is None else pos.tobytes()))
    return {
        "stats": store.stats(),
        "sequences": seqs,
        "edges": sorted((e.src, e.dst, e.weight, e.query_seq, e.frame) for e in store.edges()),
        "components": sorted((c.component, tuple(c.sequences), c.vertices)
                             for c in store.components()),
    }


def test_simulator_tears_unsynced_writes(tmp_path):
    """The simulator itself: unsynced data is dropped/torn, fsynced data and entries survive."""
    root = tmp_path / "m"
    (root / SHARDS_DIR).mkdir(parents=True)
    kept, loose = root / SHARDS_DIR / "kept", root / SHARDS_DIR / "loose"
    results = set()
    for seed in range(40):
        for f in (kept, loose):
            f.unlink(missing_ok=True)
        sim = PowerLossSimulator(root, seed=seed)
        with installed(sim):
            for f in (kept, loose):
                fd = atomic.open_for_write(f)
                atomic.write_at(fd, f, memoryview(b"0123456789"), 0)
                if f is kept:
                    atomic.fsync(fd, f)
                atomic.write_at(fd, f, memoryview(b"abcdef"), 10)
                __import__("os").close(fd)
            atomic.fsync_dir(root / SHARDS_DIR)
        sim.apply()
        assert kept.read_bytes()[:10] == b"0123456789"
        results.add(loose.read_bytes())
    assert b"" in results and b"0123456789abcdef" in results
    assert any(0 < len(r) < 16 for r in results) and any(b"\0" in r for r in results)



def test_publish_refuses_a_short_write(tmp_path):
    """``publish(expected_size=...)`` catches a writer that fails silently (as FAISS does)."""
    target = tmp_path / "file"
    with pytest.raises(StorageIOError, match=r"short write \(3 of 10 bytes\)"):
        atomic.publish(target, lambda p: p.write_bytes(b"abc"), expected_size=10)
    assert list(tmp_path.iterdir()) == []
    atomic.publish(target, lambda p: p.write_bytes(b"abc"), expected_size=3)
    assert target.read_bytes() == b"abc"


CLI_WITH_FAULT = textwrap.dedent("""
    import errno, sys
    from sprint_map.cli.main import main
    from sprint_map.testing.faults import FaultInjector, installed
    op, nth, err = sys.argv[1], int(sys.argv[2]), getattr(errno, sys.argv[3])
    with installed(FaultInjector(nth, err, ops={op})):
        main(sys.argv[4:])
""")


def test_the_cli_reports_an_injected_fault_in_one_line(template, tmp_path):
    """The real ``sprint-map ingest`` in a subprocess, its first shard fsync failing with EIO:
    one line on stderr, exit code of StorageIOError, the map as before."""
    path = fresh(template, tmp_path, "cli")
    drive = tmp_path / "drive.npy"
    np.save(drive, _drive(20, 9))
    before = map_state(path)
    proc = subprocess.run([sys.executable, "-c", CLI_WITH_FAULT, "fsync", "1", "EIO",
                           "ingest", str(path), str(drive)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == StorageIOError.exit_code, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "Error: cannot write descriptor shard shard-000001.f32: "
        "Input/output error (injected)"]
    assert reopen_and_state(path) == before


def test_the_cli_warns_when_only_the_index_cache_could_not_be_saved(template, tmp_path):
    """ENOSPC on publishing the index, after the commit: the drive is added (exit 0) and the
    CLI says, on stderr, that the cache was not saved."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    path = fresh(template, tmp_path, "cli-warn")
    drive = tmp_path / "drive.npy"
    np.save(drive, _drive(21, 4))
    with installed(FaultInjector(1, errno.ENOSPC, ops={"replace"}, sticky=True)):
        result = CliRunner().invoke(main, ["ingest", str(path), str(drive), "--no-merge"])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("added sequence 3 (drive)")
    warnings = result.stderr.splitlines()
    assert warnings and all(w.startswith("Warning: ") for w in warnings)
    assert "No space left on device (injected)" in warnings[0]
    assert reopen_and_state(path)["sequences"][-1][1] == "drive"
