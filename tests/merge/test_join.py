"""Joining maps (``SprintMap.join``, ``sprint-map join``): the copy, the merge, bad inputs.

Two maps of one road: TARGET holds two drives, SOURCE two more of the same road (positions with
an accuracy, thumbnails, their merge edges, a sighting) and one of another road. The oracle of
the merge is ``ingest``: a drive joined alone gets exactly the edges ingesting it into a copy of
TARGET adds. A refused join leaves both maps byte for byte as they were.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.errors import (
    DuplicateNameError,
    IncompatibleMapError,
    InputError,
    MapCorruptError,
    MapLockedError,
    StorageIOError,
    UnconnectedJoinError,
    UnknownSequenceError,
)
from sprint_map.map import SprintMap
from sprint_map.storage import join as storage_join
from sprint_map.storage import lmdb_env
from sprint_map.testing.faults import FaultInjector, installed
from tests.helpers.road_map import DIM, Road, thumbnails

SIGMA = 3.0


def positions(xy: np.ndarray) -> np.ndarray:
    """x, y, heading, time, sigma_m: fixes with an accuracy."""
    n = len(xy)
    return np.c_[xy, np.full(n, np.nan), np.arange(n, dtype=float), np.full(n, SIGMA)]


def fixes(xy: np.ndarray) -> np.ndarray:
    return np.c_[xy, np.full(len(xy), SIGMA)]


@pytest.fixture
def road() -> Road:
    return Road.make(np.random.default_rng(7))


@pytest.fixture
def drives(road: Road) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(8)
    other = Road.make(np.random.default_rng(9), origin=(0.0, 900.0))
    out = {name: road.drive(rng, 120, start=4 * i)
           for i, name in enumerate(["t0", "t1", "s0", "s1"])}
    out["far"] = other.drive(rng, 60)
    return out


def ingest(m: SprintMap, name: str, drive: tuple[np.ndarray, np.ndarray]) -> Any:
    desc, xy = drive
    return m.ingest(desc, name=name, positions=positions(xy), thumbnails=thumbnails(xy),
                    fixes=fixes(xy))


@pytest.fixture
def maps(tmp_path: Path, drives: dict[str, Any]) -> tuple[Path, Path]:
    target, source = tmp_path / "target", tmp_path / "source"
    with SprintMap.create(target, MapConfig(dim=DIM)) as m:
        for name in ("t0", "t1"):
            ingest(m, name, drives[name])
    with SprintMap.create(source, MapConfig(dim=DIM)) as m:
        for name in ("s0", "s1", "far"):
            ingest(m, name, drives[name])
        m.store.record_sightings("s1-again", [(1, 5, 0.25), (1, 6, 0.5)])
    return target, source


def files(path: Path) -> dict[str, str]:
    """Every file of a map but LMDB's reader table, by content."""
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file() and p.name != "lock.mdb"}


def state(path: Path) -> dict[str, Any]:
    """What a user reads of a map: sequences with rows, positions and thumbnails, edges with
    provenance, components; ``check`` passes."""
    with SprintMap.open(path, readonly=True) as m:
        assert m.check().ok, m.check().to_dict()
        seqs = []
        for s in m.sequences():
            pos = m.positions(s.seq_id)
            seqs.append((s.seq_id, s.name, s.length, m.descriptors(s.seq_id).tobytes(),
                         None if pos is None else pos.tobytes(),
                         [m.thumbnail(s.seq_id, i) for i in range(s.length)]))
        edges = [(e.to_dict(), e.frame) for e in m.edges()]
        comps = [(c.component, c.sequences, c.vertices) for c in m.components()]
    return {"sequences": seqs, "edges": edges, "components": comps}


# --- the copy ------------------------------------------------------------------------------------


def test_no_merge_copies_every_drive_with_what_it_carries(maps):
    target, source = maps
    before = files(source)
    with SprintMap.open(target) as m:
        result = m.join(source, merge=False)
    assert files(source) == before  # never written
    data = result.to_dict()
    assert [d["name"] for d in data["drives"]] == ["s0", "s1", "far"]
    assert data["cross_edges"] == 0 and data["vertices_copied"] == 300
    with SprintMap.open(source, readonly=True) as src, \
            SprintMap.open(target, readonly=True) as m:
        assert m.check().ok
        src_edges = {(e.src_seq, e.src_image, e.dst_seq, e.dst_image, e.prob, e.added_by,
                      e.frame, e.time) for e in src.edges()}
        ids = {s.seq_id: m.store.sequence_by_name(s.name).seq_id for s in src.sequences()}
        for s in src.sequences():
            new = ids[s.seq_id]
            assert np.array_equal(m.descriptors(new), src.descriptors(s.seq_id))
            assert np.array_equal(m.positions(new), src.positions(s.seq_id), equal_nan=True)
            assert [m.thumbnail(new, i) for i in range(s.length)] == \
                [src.thumbnail(s.seq_id, i) for i in range(s.length)]
            with m.store.env.read() as a, src.store.env.read() as b:
                assert m.store.sequence_digest(new, a) == src.store.sequence_digest(s.seq_id, b)
        for image in (5, 6):
            got, want = m.store.sighting(ids[1], image), src.store.sighting(1, image)
            assert got is not None and want is not None
            assert dataclasses.replace(got, seq_id=1) == want
        back = {new: old for old, new in ids.items()}
        joined = {(back[e.src_seq], e.src_image, back[e.dst_seq], e.dst_image, e.prob,
                   back[e.added_by], e.frame, e.time) for e in m.edges()
                  if e.src_seq in back or e.dst_seq in back}
        assert joined == src_edges
        assert src_edges  # the source's own merges came along
        sizes = sorted(len(c.sequences) for c in m.components())
        assert sizes == [1, 2, 2]  # t0+t1, s0+s1, far: no cross-map edge without a merge


def test_the_drives_statistics_are_carried_renumbered(tmp_path, drives):
    """Each imported drive's ``drive_stats`` record (its condition) arrives under its new id."""
    target, source = tmp_path / "t", tmp_path / "s"
    with SprintMap.create(target, MapConfig(dim=DIM)) as m:
        ingest(m, "t0", drives["t0"])
    with SprintMap.create(source, MapConfig(dim=DIM)) as m:
        for name in ("s0", "s1"):
            ingest(m, name, drives[name])
        with m.store.env.read() as txn:
            theirs = dict(txn.cursor(db=m.store.env.db("drive_stats")))
    with SprintMap.open(target) as m:
        m.join(source, merge=False)
        with m.store.env.read() as txn:
            got = dict(txn.cursor(db=m.store.env.db("drive_stats")))
        assert m.check().ok
    assert sorted(theirs) == [(0).to_bytes(4, "big"), (1).to_bytes(4, "big")]
    assert got[(1).to_bytes(4, "big")] == theirs[(0).to_bytes(4, "big")]
    assert got[(2).to_bytes(4, "big")] == theirs[(1).to_bytes(4, "big")]
    assert len(got) == 3


def test_a_per_drive_database_added_later_is_carried(tmp_path, monkeypatch, drives):
    """A database keyed by ``>I`` seq_id that this module does not know by name (a per-drive
    database another version adds) is copied with the drive, renumbered."""
    monkeypatch.setattr(lmdb_env, "DB_NAMES", (*lmdb_env.DB_NAMES, "drive_extra"))
    monkeypatch.setattr(lmdb_env, "OPTIONAL_DBS", lmdb_env.OPTIONAL_DBS | {"drive_extra"})
    monkeypatch.setattr(storage_join, "DB_NAMES", lmdb_env.DB_NAMES)
    target, source = tmp_path / "t", tmp_path / "s"
    with SprintMap.create(target, MapConfig(dim=DIM)) as m:
        ingest(m, "t0", drives["t0"])
    with SprintMap.create(source, MapConfig(dim=DIM)) as m:
        for name in ("s0", "s1"):
            ingest(m, name, drives[name])

        def put(txn: Any) -> None:
            db = m.store.env.db("drive_extra")
            for seq in (0, 1):
                txn.put(seq.to_bytes(4, "big"), f"extra of {seq}".encode(), db=db)

        m.store.env.write(put)
    with SprintMap.open(target) as m:
        m.join(source, merge=False)
        with m.store.env.read() as txn:
            got = dict(txn.cursor(db=m.store.env.db("drive_extra")))
    assert got == {(1).to_bytes(4, "big"): b"extra of 0", (2).to_bytes(4, "big"): b"extra of 1"}


def test_joining_twice_is_a_no_op(maps):
    target, source = maps
    with SprintMap.open(target) as m:
        m.join(source)
    after = state(target)
    with SprintMap.open(target) as m:
        again = m.join(source).to_dict()
    assert again["imported"] == 0 and again["already_present"] == 3
    assert state(target) == after


def test_a_drive_already_there_keeps_its_edges_to_the_imported_ones(maps):
    """Join s0 alone, then everything: s1 is imported and its merge edges with s0 are carried
    to the target's copy of s0; s0 is not copied twice."""
    target, source = maps
    with SprintMap.open(target) as m:
        first = m.join(source, drives=["s0"], merge=False).to_dict()
        second = m.join(source, merge=False).to_dict()
        s0 = first["drives"][0]["seq_id"]
        names = [s.name for s in m.sequences()]
        s1 = m.store.sequence_by_name("s1").seq_id
        assert any(e.src_seq == s1 and e.dst_seq == s0 for e in m.edges())
        assert m.check().ok
    assert names == ["t0", "t1", "s0", "s1", "far"]
    assert [d["already_present"] for d in second["drives"]] == [True, False, False]


def test_name_clashes_are_refused_with_the_names_or_resolved_by_a_prefix(maps, tmp_path,
                                                                        drives):
    target, source = maps
    clash = tmp_path / "clash"
    with SprintMap.create(clash, MapConfig(dim=DIM)) as m:
        ingest(m, "t0", (drives["s0"][0][:50], drives["s0"][1][:50]))
        ingest(m, "t1", (drives["s1"][0][:50], drives["s1"][1][:50]))
    before = files(target)
    with SprintMap.open(target) as m, \
            pytest.raises(DuplicateNameError, match="'t0', 't1'.*--prefix"):
        m.join(clash)
    assert files(target) == before
    with SprintMap.open(target) as m:
        names = [d.name for d in m.join(clash, prefix="van7-").drives]
    assert names == ["van7-t0", "van7-t1"]


# --- the merge ------------------------------------------------------------------------------------


def test_a_joined_drive_gets_the_edges_ingest_would_add(maps, tmp_path, drives):
    target, _ = maps
    alone = tmp_path / "alone"
    with SprintMap.create(alone, MapConfig(dim=DIM)) as m:
        ingest(m, "s0", drives["s0"])
    ingested = tmp_path / "ingested"
    shutil.copytree(target, ingested)
    with SprintMap.open(ingested) as m:
        done = ingest(m, "s0", drives["s0"])
        want = [(e.to_dict(), e.frame) for e in m.edges(added_by="s0")]
        comps = [(c.sequences, c.vertices) for c in m.components()]
    with SprintMap.open(target) as m:
        result = m.join(alone)
        got = [(e.to_dict(), e.frame) for e in m.edges(added_by="s0")]
        assert [(c.sequences, c.vertices) for c in m.components()] == comps
    assert done.edges_added > 0 and got == want
    (drive,) = result.drives
    assert drive.cross_edges == done.edges_added and drive.connected


def test_json_reports_cross_edges_and_connectivity(maps):
    target, source = maps
    out = CliRunner().invoke(main, ["join", str(target), str(source), "--json"])
    assert out.exit_code == 0, out.output
    import json

    data = json.loads(out.output)
    by_name = {d["name"]: d for d in data["drives"]}
    assert by_name["s0"]["cross_edges"] > 0 and by_name["s0"]["connected"]
    assert by_name["s1"]["connected"]
    assert by_name["far"]["cross_edges"] == 0 and not by_name["far"]["connected"]
    assert state(target)["components"]


def test_require_connected_refuses_and_changes_nothing(maps):
    target, source = maps
    before = files(target)
    with SprintMap.open(target) as m, pytest.raises(UnconnectedJoinError, match="'far'"):
        m.join(source, require_connected=True)
    assert files(target) == before
    with SprintMap.open(target) as m:
        result = m.join(source, drives=["s0", "s1"], require_connected=True)
    assert all(d.connected for d in result.drives)


def test_unmerge_revokes_the_joins_merge_and_remove_forgets_a_joined_drive(maps):
    target, source = maps
    with SprintMap.open(target) as m:
        result = {d.name: d for d in m.join(source).drives}
        cross = [e for e in m.edges(added_by="s0") if e.dst_seq < 2 or e.src_seq < 2]
        assert len(cross) == result["s0"].cross_edges > 0
        undone = m.unmerge("s0")
        assert undone.edges_removed >= len(cross)
        assert not [e for e in m.edges(added_by="s0")]
        m.remove_sequences(["s1"])
        assert "s1" not in [s.name for s in m.sequences()]
        assert m.check().ok


# --- bad inputs: one clear error, both maps unchanged -------------------------------------------


@pytest.mark.parametrize("config, match", [
    (MapConfig(dim=DIM + 1), "dim is 32 in the target and 33"),
    (MapConfig.for_descriptor("hog"), "descriptor is 'precomputed'"),
])
def test_incompatible_maps_are_refused_naming_the_difference(maps, tmp_path, config, match):
    target, _ = maps
    other = tmp_path / "other"
    with SprintMap.create(other, config) as m:
        m.add_sequence(np.ones((3, config.dim), np.float32), name="z")
    before, before_other = files(target), files(other)
    with SprintMap.open(target) as m, pytest.raises(IncompatibleMapError, match=match):
        m.join(other)
    assert files(target) == before and files(other) == before_other


def test_other_descriptor_parameters_are_refused_naming_them(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for path, params in ((a, {}), (b, {"width": 16, "height": 32})):
        config = MapConfig.for_descriptor("patchnorm", params)
        with SprintMap.create(path, config) as m:
            m.add_sequence(np.ones((3, config.dim), np.float32), name="z")
    with SprintMap.open(a) as m, pytest.raises(IncompatibleMapError,
                                               match="descriptor_params.height is 16 in the "
                                                     "target and 32 in the source"):
        m.join(b)


def test_different_coordinate_frames_are_refused(maps, tmp_path):
    target, _ = maps
    geo = tmp_path / "geo"
    with SprintMap.create(geo, MapConfig(dim=DIM)) as m:
        m.add_sequence(np.ones((2, DIM), np.float32), name="z", positions=np.zeros((2, 2)))
        m.store.set_geo_frame({"crs": "utm", "zone": 32, "south": False, "epsg": 32632})
    with SprintMap.open(target) as m, pytest.raises(IncompatibleMapError,
                                                    match="local metric.*UTM zone 32N"):
        m.join(geo)


@pytest.mark.parametrize("case", ["itself", "missing drive", "locked", "not a map"])
def test_bad_inputs_are_one_clear_error(maps, tmp_path, case):
    target, source = maps
    before, before_source = files(target), files(source)
    errors = {"itself": (InputError, "is the target map itself"),
              "missing drive": (UnknownSequenceError, "no drive named 'nope', 'nada'"),
              "locked": (MapLockedError, "being written by another process"),
              "not a map": (Exception, "not a sprint-map directory")}
    kind, match = errors[case]
    with SprintMap.open(target) as m:
        writer = SprintMap.open(source) if case == "locked" else None
        try:
            with pytest.raises(kind, match=match):
                if case == "itself":
                    m.join(target)
                elif case == "missing drive":
                    m.join(source, drives=["s0", "nope", "nada"])
                elif case == "not a map":
                    m.join(tmp_path)
                else:
                    m.join(source)
        finally:
            if writer is not None:
                writer.close()
    assert files(target) == before and files(source) == before_source


def test_a_full_disk_fails_the_join_and_changes_nothing(maps):
    target, source = maps
    before = state(target)
    with SprintMap.open(target) as m, \
            installed(FaultInjector(2, errno.ENOSPC, ops={"write"})), \
            pytest.raises(StorageIOError, match="No space left"):
        m.join(source, merge=False)
    assert state(target) == before
    with SprintMap.open(target) as m:  # and the join runs once there is room again
        assert m.join(source, merge=False).to_dict()["imported"] == 3
    assert state(target) != before


def test_cli_errors_are_one_line(maps, tmp_path):
    target, source = maps
    out = CliRunner().invoke(main, ["join", str(target), str(target)])
    assert out.exit_code == InputError.exit_code
    assert out.output.strip().startswith("Error:") and len(out.output.strip().splitlines()) == 1
    out = CliRunner().invoke(main, ["join", str(target), str(source), "--require-connected"])
    assert out.exit_code == UnconnectedJoinError.exit_code


def test_localising_in_other_processes_equals_serial(maps, tmp_path):
    """A farm's tasks (here: spawned processes, as Ray's workers) localise each drive against
    the target opened read-only (:func:`sprint_map.fleet.join.localise_joined_drive`), in
    parallel and out of order: the same join as the serial one."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from sprint_map.fleet.join import localise_joined_drive

    target, source = maps
    serial = tmp_path / "serial"
    shutil.copytree(target, serial)
    with SprintMap.open(serial) as m:
        m.join(source)

    def farm(records: Any) -> Any:
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(localise_joined_drive, str(target), str(source), r.seq_id,
                                   None) for r in reversed(records)]
            return [f.result() for f in futures][::-1]

    with SprintMap.open(target) as m:
        m.join(source, localise_many=farm)
    assert state(target)["edges"] == state(serial)["edges"]


def test_stray_records_past_the_targets_last_drive_refuse_the_join(maps):
    """LMDB's appending put skips a key that does not sort last without an error: a per-drive
    record of a sequence id the target has not reached yet (a corrupt target) must fail the
    join, not lose the imported drive's records."""
    target, source = maps
    with SprintMap.open(target) as m:
        m.store.env.write(lambda txn: txn.put((99).to_bytes(4, "big") + (0).to_bytes(4, "big"),
                                              b"x", db=m.store.env.db("thumbnails")))
    before = files(target)
    with SprintMap.open(target) as m, pytest.raises(MapCorruptError, match="'thumbnails'"):
        m.join(source, merge=False)
    assert files(target) == before
