"""Fuzz the map directory: damage each file of a small map in turn, then run the CLI on it.

Two small maps cover every kind of file a map has: a flat-index map that was compacted
(``CURRENT``, a generation directory, several shards, the flat index file) and a map with the
segmented IVF index (``segments.json``, the model, a segment file); both have ``LOCK``,
``data.mdb`` and ``lock.mdb``. Each file is, in turn, flipped (16 bytes XOR-ed at its start,
middle and end), scattered (one bit flipped at 12 seeded offsets), truncated to half, or
deleted; then ``info``, ``check``, ``localize``, ``export`` (the three formats) and
``ingest`` run as real processes of the ``sprint-map`` command line (forked from a warmed-up
server, ``tests/helpers/map_fuzz_worker.py``: the same ``main`` the console script runs; ``check`` again
after an ``ingest`` that succeeded). Promises (issue 14):

- no traceback (stderr never holds ``Traceback``) and no signal (no SIGBUS/SIGSEGV);
- no silent change to committed data: when the last ``check`` passes, the committed sequences'
  descriptors read back equal to the pristine map's; otherwise the damage was reported.

Traces (issue 29) are fuzzed the same way: a trace of the pristine map, flipped, scattered,
truncated, or rebuilt with one array missing, reshaped, retyped, non-finite, a huge declared
member, a deeply nested ``meta``; each is read by ``read_trace`` and, if it is accepted, every
trace route of the viewer must answer 200 with valid JSON.

The counts are printed (``-s``) and kept in ``COUNTS`` for the report.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import SprintMapError
from sprint_map.storage.store import MapStore

DIM = 16
WORKER = Path(__file__).parent / "helpers" / "map_fuzz_worker.py"
COUNTS: dict[str, int] = {}


class Cli:
    """The client of a ``map_fuzz_worker.py`` fork server."""

    def __init__(self, scratch: Path) -> None:
        self.scratch = scratch
        self.proc = subprocess.Popen([sys.executable, str(WORKER)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdout.readline() == "ready\n"

    def __call__(self, *args: Any) -> tuple[int, str]:
        """``(return code, stderr)`` of ``sprint-map ARGS`` (a negative code: a signal)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        out, err = self.scratch / "stdout", self.scratch / "stderr"
        self.proc.stdin.write(json.dumps({"args": [str(a) for a in args], "stdout": str(out),
                                          "stderr": str(err)}) + "\n")
        self.proc.stdin.flush()
        reply = json.loads(self.proc.stdout.readline())
        return int(reply["code"]), err.read_text(errors="replace")

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


@pytest.fixture(scope="module")
def cli(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cli]:
    client = Cli(tmp_path_factory.mktemp("cli"))
    yield client
    client.close()


def _compacted_flat_map(path: Path, rng: np.random.Generator) -> None:
    with MapStore.create(path, MapConfig(dim=DIM, store=StoreOptions(shard_rows=64, index_type="flat"))) as store:
        for i in range(4):
            store.add_sequence(rng.standard_normal((50, DIM)).astype(np.float32), name=f"d{i}")
        store.remove_sequences([1])
        store.compact()
        store.search(np.zeros((1, DIM), np.float32), k=1)  # the flat index, persisted at close


def _segmented_map(path: Path, rng: np.random.Generator) -> None:
    config = MapConfig(dim=DIM, store=StoreOptions(index_type="ivf-sq8", index_segment_rows=128, index_nlist=4, index_nprobe=2, index_merge_factor=4))
    with MapStore.create(path, config) as store:
        for i in range(3):
            store.add_sequence(rng.standard_normal((200, DIM)).astype(np.float32), name=f"d{i}")
        store.search(np.zeros((1, DIM), np.float32), k=1)


MAPS: dict[str, Callable[[Path, np.random.Generator], None]] = {
    "flat-compacted": _compacted_flat_map, "segmented": _segmented_map}


def committed(path: Path) -> dict[str, np.ndarray]:
    """Every committed sequence's descriptors, by name."""
    with MapStore.open(path, readonly=True) as store:
        return {s.name: np.array(store.descriptors(s.seq_id)) for s in store.sequences()}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict[str, Any]]]:
    root = tmp_path_factory.mktemp("pristine")
    rng = np.random.default_rng(14)
    out = {}
    for kind, make in MAPS.items():
        make(root / kind, rng)
        out[kind] = (root / kind, committed(root / kind))
    query = rng.standard_normal((20, DIM)).astype(np.float32)
    np.save(root / "drive.npy", query)
    return out


def flip(file: Path) -> None:
    data = bytearray(file.read_bytes())
    for at in {0, len(data) // 2, max(0, len(data) - 16)}:
        data[at : at + 16] = bytes(b ^ 0xFF for b in data[at : at + 16])
    file.write_bytes(bytes(data))


def scatter(file: Path) -> None:
    """One bit flipped at each of 12 seeded offsets (LMDB pages, rows, codes, headers)."""
    data = bytearray(file.read_bytes())
    rng = np.random.default_rng([14, len(data)])
    for at in rng.integers(0, max(1, len(data)), 12).tolist() if data else []:
        data[at] ^= 1 << int(rng.integers(0, 8))
    file.write_bytes(bytes(data))


def truncate(file: Path) -> None:
    with file.open("r+b") as fh:
        fh.truncate(file.stat().st_size // 2)


def delete(file: Path) -> None:
    file.unlink()


MUTATIONS = {"flip": flip, "scatter": scatter, "truncate": truncate, "delete": delete}


def test_every_file_of_a_map_flipped_truncated_or_deleted(pristine, cli, tmp_path):
    drive = next(iter(pristine.values()))[0].parent / "drive.npy"
    counts = dict.fromkeys(("cases", "commands", "tracebacks", "signals", "silent_changes",
                            "reported", "unaffected"), 0)
    kinds: set[str] = set()
    failures = []
    for kind, (source, before) in pristine.items():
        files = sorted(p.relative_to(source) for p in source.rglob("*") if p.is_file())
        for rel in files:
            kinds.add(_file_kind(rel))
            for name, mutate in MUTATIONS.items():
                case = f"{kind}:{rel}:{name}"
                path = tmp_path / "map"
                shutil.rmtree(path, ignore_errors=True)
                shutil.copytree(source, path, symlinks=True)
                mutate(path / rel)
                results: dict[str, tuple[int, str]] = {}
                exported = tmp_path / "exported"
                shutil.rmtree(exported, ignore_errors=True)
                exported.mkdir()
                for command in (["info"], ["check"], ["localize", drive, "--quiet"],
                                ["export", "--graphml", exported / "g.graphml", "--csv",
                                 exported / "csv", "--geojson", exported / "m.geojson"],
                                ["ingest", drive, "--quiet", "--name", "fuzz"]):
                    results[command[0]] = cli(command[0], path, *command[1:])
                stray = [p for p in exported.rglob("*") if p.name.endswith(".partial")]
                if stray:
                    failures.append(f"{case}: export left {stray}")
                if results["ingest"][0] == 0:
                    results["check-after"] = cli("check", path)
                counts["cases"] += 1
                counts["commands"] += len(results)
                for ran, (code, stderr) in results.items():
                    if "Traceback" in stderr:
                        counts["tracebacks"] += 1
                        failures.append(f"{case}: {ran} traceback: {stderr[-800:]}")
                    if code < 0:
                        counts["signals"] += 1
                        failures.append(f"{case}: {ran} killed by signal {-code}")
                final = results.get("check-after", results["check"])[0]
                if final != 0:
                    counts["reported"] += 1
                    continue
                try:
                    after = committed(path)
                except SprintMapError:
                    counts["reported"] += 1
                    continue
                lost = [n for n, rows in before.items()
                        if n not in after or not np.array_equal(after[n], rows)]
                if lost:
                    counts["silent_changes"] += 1
                    failures.append(f"{case}: check passes but sequences {lost} changed")
                else:
                    counts["unaffected"] += 1
    COUNTS.update(counts)
    print(f"\nmap fuzz: {counts}; file kinds: {sorted(kinds)}")
    assert {"LOCK", "CURRENT", "data.mdb", "lock.mdb", "shard", "flat index", "manifest",
            "model", "segment"} <= kinds, kinds
    assert not failures, "\n".join(failures)


def _file_kind(rel: Path) -> str:
    name = rel.name
    if name.startswith("shard-"):
        return "shard"
    if name.startswith("flat."):
        return "flat index"
    if name == "segments.json":
        return "manifest"
    if name.startswith(("model.", "pca.")):
        return "model"
    if name.startswith("seg."):
        return "segment"
    return name


def _trace_of(path: Path, drive: Path, out: Path) -> None:
    from sprint_map.localize.trace import TraceRecorder
    from sprint_map.map import SprintMap

    with SprintMap.open(path, readonly=True) as m:
        loc = m.localizer()
        rec = TraceRecorder(m)
        rec.attach(loc)
        loc.localize(np.load(drive))
        rec.save(out)


def _rebuilt(arrays: dict[str, np.ndarray], rng: np.random.Generator
             ) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
    """Structural damage: each array missing, cut short, reshaped, retyped, non-finite."""
    for key in sorted(arrays):
        value = arrays[key]
        yield f"{key}:missing", {k: v for k, v in arrays.items() if k != key}
        yield f"{key}:short", arrays | {key: value[: max(0, len(value) - 1)] if value.ndim
                                        else value}
        yield f"{key}:reshaped", arrays | {key: value.reshape(-1)[:, None] if value.size else
                                           np.zeros((2, 2))}
        yield f"{key}:text", arrays | {key: np.array(["x"] * max(1, value.size))}
        if value.dtype.kind == "f":
            bad = value.copy()
            if bad.size:
                bad.reshape(-1)[int(rng.integers(0, bad.size))] = np.nan
            yield f"{key}:nan", arrays | {key: bad}
        if value.dtype.kind in "iu" and value.size:
            bad = value.copy()
            bad.reshape(-1)[int(rng.integers(0, bad.size))] = -7
            yield f"{key}:negative", arrays | {key: bad}
    meta = json.loads(str(arrays["meta"]))
    for field, value in (("frames", -1), ("frames", 10**9), ("frames", "many"),
                         ("version", 99), ("format", "other")):
        yield f"meta.{field}={value}", arrays | {"meta": np.array(json.dumps(
            meta | {field: value}))}
    yield "meta:nested", arrays | {"meta": np.array("[" * 100_000 + "]" * 100_000)}
    yield "meta:nan", arrays | {"meta": np.array(json.dumps(meta).replace(
        '"k": ', '"k": NaN, "x": '))}
    yield "meta:not-json", arrays | {"meta": np.array("{")}


def _huge_member(out: Path, arrays: dict[str, np.ndarray]) -> None:
    """A small file whose ``hit_dist`` declares 1 GiB (and holds zeros compressed)."""
    import zipfile
    np.savez_compressed(out, **{k: v for k, v in arrays.items() if k != "hit_dist"})
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1, np.float32))
    header["shape"] = (2**28,)
    with zipfile.ZipFile(out, "a", compression=zipfile.ZIP_DEFLATED) as archive, \
            archive.open("hit_dist.npy", "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        chunk = bytes(1 << 20)
        for _ in range(1024):
            fh.write(chunk)


def test_damaged_traces_are_refused_or_served_whole(pristine, tmp_path):
    """Every damaged trace is refused by ``read_trace`` (InputError, nothing else) or served:
    then the viewer's trace routes all answer 200 with JSON (no 500, no traceback)."""
    from fastapi.testclient import TestClient

    from sprint_map.errors import InputError
    from sprint_map.localize.trace import read_trace
    from sprint_map.map import SprintMap
    from sprint_map.viewer.app import create_view_app
    from sprint_map.viewer.overview import MapOverview

    source = pristine["flat-compacted"][0]
    drive = source.parent / "drive.npy"
    good = tmp_path / "good.npz"
    _trace_of(source, drive, good)
    with np.load(good) as data:
        arrays = {k: data[k] for k in data.files}
    rng = np.random.default_rng(29)
    cases: list[tuple[str, Path]] = []
    for name, mutate in MUTATIONS.items():
        if name != "delete":
            bad = tmp_path / f"{name}.npz"
            shutil.copy(good, bad)
            mutate(bad)
            cases.append((name, bad))
    for i, (name, damaged) in enumerate(_rebuilt(arrays, rng)):
        bad = tmp_path / f"r{i}.npz"
        np.savez_compressed(bad, **damaged)
        cases.append((name, bad))
    np.save(tmp_path / "plain.npy", arrays["hit_dist"])
    cases.append(("npy", tmp_path / "plain.npy"))
    _huge_member(tmp_path / "huge.npz", arrays)
    cases.append(("huge member", tmp_path / "huge.npz"))
    cases.append(("directory", tmp_path))
    counts = {"cases": len(cases), "refused": 0, "served": 0}
    failures = []
    refused: set[str] = set()
    with SprintMap.open(source, readonly=True) as m:
        summary = MapOverview(m)
        for name, path in cases:
            try:
                trace = read_trace(path)
            except InputError:
                counts["refused"] += 1
                refused.add(name)
                continue
            except Exception as exc:  # noqa: BLE001  (the promise: InputError only)
                failures.append(f"{name}: {type(exc).__name__}: {exc}")
                continue
            client = TestClient(create_view_app(summary, trace), raise_server_exceptions=False)
            answers = [client.get("/viewer/api/trace")]
            answers += [client.get(f"/viewer/api/trace/frames?start={s}&count=500")
                        for s in range(0, trace.frames + 1, 500)]
            bad = [a.status_code for a in answers if a.status_code != 200]
            if bad:
                failures.append(f"{name}: served, but the trace routes answered {bad}")
            counts["served"] += 1
    COUNTS.update({f"trace_{k}": v for k, v in counts.items()})
    print(f"\ntrace fuzz: {counts}")
    assert {"huge member", "npy", "truncate", "meta:nested", "directory"} <= refused
    assert not failures, "\n".join(failures)
