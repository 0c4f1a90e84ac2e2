"""Where exports and traces land (issue 29 items 1, 2, 10-13): concurrent runs, planted links,
special files, outputs inside the map, unwritable paths, stale partials, the CSV set as a unit,
formula injection."""

from __future__ import annotations

import csv
import errno
import os
import socket
import stat
import threading
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map import export as export_pkg
from sprint_map.cli.main import main
from sprint_map.errors import InputError, StorageIOError
from sprint_map.map import SprintMap
from sprint_map.util import atomic

FORMATS = ["graphml-vertex", "graphml-sequence", "csv", "geojson"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def export(m: SprintMap, fmt: str, path: Path):
    if fmt.startswith("graphml"):
        return m.export_graphml(path, fmt.split("-")[1])
    return m.export_csv(path) if fmt == "csv" else m.export_geojson(path)


def out_file(tmp_path: Path, fmt: str) -> tuple[Path, Path]:
    """(the path given to the export, the file whose partial a link can be planted at)."""
    if fmt == "csv":
        return tmp_path / "csv", tmp_path / "csv" / "sequences.csv"
    return tmp_path / f"out.{fmt}", tmp_path / f"out.{fmt}"


def valid(fmt: str, path: Path) -> bool:
    if fmt.startswith("graphml"):
        return nx.read_graphml(path).number_of_nodes() in (4, 48)
    if fmt == "csv":
        with open(path / "sequences.csv", newline="") as fh:
            return [r["name"] for r in csv.DictReader(fh)] == ["a", "b", 'c, "quoted"', "d"]
    import json
    return len(json.loads(path.read_text())["features"]) >= 3


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_run_inside_another_to_the_same_path_publishes_whole_files(small_map, tmp_path,
                                                                     monkeypatch, fmt):
    """Run B starts and ends while run A is half-way through writing the same OUT (was: both
    used OUT.partial, so A went on writing into the file B published: torn)."""
    target, _ = out_file(tmp_path, fmt)
    name = {"graphml-vertex": "write_vertex_graphml", "graphml-sequence":
            "write_sequence_graphml", "csv": "write_table", "geojson": "write_geojson"}[fmt]
    original = getattr(export_pkg, name)
    nested: list[int] = []
    opened: list[SprintMap] = []

    def wrapper(*args, **kwargs):
        if not nested:
            nested.append(1)
            export(opened[0], fmt, target)  # run B, whole, while A is half-way
        return original(*args, **kwargs)

    monkeypatch.setattr(export_pkg, name, wrapper)
    with SprintMap.open(small_map, readonly=True) as m:
        opened.append(m)
        export(m, fmt, target)  # run A
    assert nested and valid(fmt, target)
    assert not list(target.parent.glob("*.partial")) and not list(tmp_path.glob("**/*.partial"))


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_link_planted_at_the_partial_is_never_written_through(small_map, tmp_path, fmt):
    target, member = out_file(tmp_path, fmt)
    member.parent.mkdir(exist_ok=True)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    os.symlink(victim, member.with_name(member.name + ".partial"))
    with SprintMap.open(small_map, readonly=True) as m:
        export(m, fmt, target)
    assert victim.read_text() == "precious"
    assert stat.S_ISREG(os.lstat(member).st_mode) and valid(fmt, target)


def test_a_trace_never_writes_through_a_planted_link(tmp_path, rng):
    map_path, drive = _npy_map(tmp_path, rng)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "t.npz"
    os.symlink(victim, tmp_path / "t.npz.partial")
    assert run("localize", map_path, drive, "--trace", out, "-q").exit_code == 0
    assert victim.read_text() == "precious" and stat.S_ISREG(os.lstat(out).st_mode)


def _npy_map(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, Path]:
    map_path, drive = tmp_path / "m.map", tmp_path / "a.npy"
    np.save(drive, rng.standard_normal((12, 8)).astype(np.float32))
    assert run("init", map_path, "--dim", 8).exit_code == 0
    assert run("ingest", map_path, drive, "-q").exit_code == 0
    return map_path, drive


@pytest.mark.parametrize("fmt", ["graphml-vertex", "geojson"])
def test_a_fifo_is_written_in_place(small_map, tmp_path, fmt):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()), daemon=True)
    reader.start()
    with SprintMap.open(small_map, readonly=True) as m:
        export(m, fmt, fifo)
    reader.join(30)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)  # not replaced by a regular file
    copy = tmp_path / "copy"
    copy.write_bytes(got[0])
    assert valid(fmt, copy)


def test_a_link_to_a_process_fd_is_written_in_place(small_map, tmp_path):
    read_fd, write_fd = os.pipe()
    link = tmp_path / "stdout"
    os.symlink(f"/proc/self/fd/{write_fd}", link)
    got = []
    reader = threading.Thread(target=lambda: got.append(os.fdopen(read_fd, "rb").read()),
                              daemon=True)
    reader.start()
    try:
        with SprintMap.open(small_map, readonly=True) as m:
            m.export_geojson(link)
    finally:
        os.close(write_fd)
    reader.join(30)
    assert os.path.islink(link) and b'"FeatureCollection"' in got[0]


def test_a_socket_or_a_directory_is_refused(small_map, tmp_path):
    sock_path = tmp_path / "s.sock"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    try:
        with SprintMap.open(small_map, readonly=True) as m:
            for path, words in ((sock_path, "socket"), (tmp_path, "directory")):
                with pytest.raises(InputError, match=words):
                    m.export_geojson(path)
    finally:
        sock.close()


@pytest.mark.parametrize("where", ["map.lmdb/data.mdb", "index/x.graphml", "", "link"])
def test_outputs_inside_the_map_are_refused(small_map, tmp_path, where):
    csv_dir = small_map / "csv"
    if where == "link":
        os.symlink(small_map / "map.lmdb" / "data.mdb", tmp_path / "innocent.graphml")
        os.symlink(small_map / "index", tmp_path / "innocent-csv")
        target, csv_dir = tmp_path / "innocent.graphml", tmp_path / "innocent-csv"
    else:
        target = small_map / where if where else small_map / "x.graphml"
        csv_dir = target.parent if where else csv_dir
    before = (small_map / "map.lmdb" / "data.mdb").read_bytes()
    for args in (["--graphml", target], ["--geojson", target],
                 ["--csv", csv_dir]):
        result = run("export", small_map, *args)
        assert result.exit_code == InputError.exit_code, (args, result.output)
        assert "inside the map" in result.output
    assert (small_map / "map.lmdb" / "data.mdb").read_bytes() == before
    assert run("check", small_map).exit_code == 0


def test_localize_never_writes_into_the_map(tmp_path, rng):
    map_path, drive = _npy_map(tmp_path, rng)
    data = map_path / "map.lmdb" / "data.mdb"
    before = data.read_bytes()
    for option in ("--trace", "--out"):
        result = run("localize", map_path, drive, option, data, "-q")
        assert result.exit_code == InputError.exit_code and "inside the map" in result.output
    assert data.read_bytes() == before and run("check", map_path).exit_code == 0


def test_ingest_refuses_an_unwritable_trace_before_the_commit(tmp_path, rng):
    """Was: the drive committed, then ``Error: cannot write``, exit 16."""
    map_path, drive = _npy_map(tmp_path, rng)
    result = run("ingest", map_path, drive, "--name", "second", "--trace",
                 tmp_path / "nodir" / "x.npz", "-q")
    assert result.exit_code == InputError.exit_code, result.output
    assert "nodir" in result.output
    assert len(SprintMap.open(map_path, readonly=True).sequences()) == 1


def test_a_trace_failing_after_the_commit_is_a_warning(tmp_path, rng, monkeypatch):
    map_path, drive = _npy_map(tmp_path, rng)
    from sprint_map.localize.trace import TraceRecorder

    def fail(*args, **kwargs):
        raise StorageIOError("cannot write t.npz: No space left on device")

    monkeypatch.setattr(TraceRecorder, "save", fail)
    result = CliRunner().invoke(main, ["ingest", str(map_path), str(drive), "--name", "second",
                                       "--trace", str(tmp_path / "t.npz"), "-q"])
    assert result.exit_code == 0, result.output
    assert "Warning: the drive is committed, but its trace was not written" in result.output
    with SprintMap.open(map_path, readonly=True) as m:
        assert [s.name for s in m.sequences()][-1] == "second"
    assert not list(tmp_path.glob("*.partial"))


def test_stale_partials_are_removed_by_the_next_run(small_map, tmp_path):
    out = tmp_path / "g.graphml"
    dead = tmp_path / "g.graphml.999999999-0badcafe.partial"  # no such pid
    legacy = tmp_path / "g.graphml.partial"
    live = tmp_path / f"g.graphml.{os.getppid()}-0badcafe.partial"  # a live process's
    for path in (dead, legacy, live):
        path.write_text("left by a killed run")
    with SprintMap.open(small_map, readonly=True) as m:
        m.export_graphml(out)
    assert not dead.exists() and not legacy.exists() and live.exists()


def test_the_csv_set_is_one_unit(small_map, tmp_path):
    """A full disk while the third file is written leaves the old three files (one snapshot)
    and no partial; was: new sequences.csv and vertices.csv beside the old edges.csv."""
    root = tmp_path / "csv"
    root.mkdir()
    for name in ("sequences.csv", "vertices.csv", "edges.csv"):
        (root / name).write_text("old\n")

    def hook(op, path, info):
        if op == "fsync" and path.name.startswith("edges.csv"):
            raise OSError(errno.ENOSPC, "No space left on device")

    previous = atomic.set_file_hook(hook)
    try:
        with SprintMap.open(small_map, readonly=True) as m, pytest.raises(StorageIOError):
            m.export_csv(root)
    finally:
        atomic.set_file_hook(previous)
    assert {p.name: p.read_text() for p in root.iterdir()} == {
        "sequences.csv": "old\n", "vertices.csv": "old\n", "edges.csv": "old\n"}


@pytest.mark.parametrize("name", ["=HYPERLINK(\"http://x\",\"y\")", "+1", "-2", "@SUM(A1)",
                                  "'quoted", "plain"])
def test_csv_text_cells_are_never_formulas(tmp_path, name):
    from sprint_map.export.tables import read_text_cell, text_cell

    path = tmp_path / "m.map"
    from sprint_map.config import MapConfig
    with SprintMap.create(path, MapConfig(dim=4)) as m:
        m.add_sequence(np.ones((2, 4), np.float32), name=name, source="=cmd|' /C calc'!A0")
        m.export_csv(tmp_path / "csv")
    with open(tmp_path / "csv" / "sequences.csv", newline="") as fh:
        row = next(csv.DictReader(fh))
    for cell, text in ((row["name"], name), (row["source"], "=cmd|' /C calc'!A0")):
        assert not cell.startswith(("=", "+", "-", "@", "\t", "\r"))
        assert read_text_cell(cell) == text and text_cell(text) == cell
