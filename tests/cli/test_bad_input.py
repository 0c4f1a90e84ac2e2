"""Bad input through the real ``sprint-map`` CLI: one line, a distinct exit code, nothing changed.

Every row of :data:`CASES` runs one command on a fresh copy of a small map (precomputed 16-d
descriptors, or HoG over images) and asserts: the exit code of the expected error class, exactly
one output line ``Error: ...`` matching the row's pattern, no exception escaping click, and every
LMDB record, shard byte and index file of the map as before. A few rows run again through a real
``sprint-map`` subprocess, to show that a user sees one line on stderr and no traceback. A full
disk is a real ``RLIMIT_FSIZE`` in a subprocess; a read-only map directory is ``chmod a-w`` (or,
as root, whom permissions do not stop, ``chattr +i``).

Rules these tests fix (see ``docs/architecture.md``, "Failure model"):

- a sequence has at least one frame; one frame is a valid sequence (added, localised, matched);
- sequence names are unique in a map, printable, 1-500 bytes; ``ingest`` names a sequence after
  its source (file stem or directory name), so ingesting other frames under a committed name is
  refused unless ``--name`` differs (the very same frames again are a retry: reported, nothing
  added, exit 0; ``tests/storage/test_integrity.py``).
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import lmdb
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map import errors
from sprint_map.cli.main import main
from sprint_map.config import SCHEMA_VERSION, MapConfig, MergeRule
from sprint_map.errors import (
    ConfigError,
    DescriptorShapeError,
    DuplicateNameError,
    EmptySequenceError,
    InputError,
    InvalidDescriptorError,
    ListenError,
    MapCorruptError,
    MapExistsError,
    MapLockedError,
    NotAMapError,
    ReadOnlyMapError,
    SchemaVersionError,
    SprintMapError,
    StorageIOError,
    UnknownSequenceError,
    UnsafeServeError,
)
from sprint_map.map import SprintMap
from sprint_map.storage.lmdb_env import DB_NAMES, MAX_DBS
from sprint_map.storage.store import INDEX_DIR, LMDB_DIR, SHARDS_DIR, MapStore

DIM = 16
SPRINT_MAP = shutil.which("sprint-map") or "sprint-map"


# --- inputs and maps ----------------------------------------------------------------------------


def _png(rng: np.random.Generator) -> bytes:
    ok, data = cv2.imencode(".png", (rng.random((48, 64)) * 255).astype(np.uint8))
    assert ok
    return data.tobytes()


def _image_dir(root: Path, name: str, rng: np.random.Generator, bad: bytes | None = None,
               bad_name: str = "003.png") -> Path:
    folder = root / name
    folder.mkdir()
    for i in range(3):
        (folder / f"{i:03d}.png").write_bytes(_png(rng))
    if bad is not None:
        (folder / bad_name).write_bytes(bad)
    return folder


def _csv(rows: list[str], header: str = "frame,x,y") -> str:
    return header + "\n" + "".join(r + "\n" for r in rows)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every bad (and borderline good) input file, made once."""
    root = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(5)
    good = rng.standard_normal((40, DIM)).astype(np.float32)
    np.save(root / "good.npy", good)
    np.save(root / "one.npy", good[:1] + 0.01)
    np.save(root / "empty.npy", np.zeros((0, DIM), np.float32))
    for name, value in (("nan", np.nan), ("inf", np.inf), ("minus_inf", -np.inf),
                        ("overflow", 1e30), ("beyond_float32", -1e300)):
        bad = good.astype(np.float64)
        bad[7, 3] = value
        np.save(root / f"{name}.npy", bad)
    np.save(root / "dim.npy", np.zeros((4, DIM + 1), np.float32))
    np.save(root / "flat.npy", np.zeros(DIM, np.float32))
    np.save(root / "int.npy", np.ones((4, DIM), np.int64))
    np.save(root / "complex.npy", np.ones((4, DIM), np.complex64))
    np.save(root / "bool.npy", np.ones((4, DIM), bool))
    np.save(root / "object.npy", np.array([[1.0] * DIM] * 2, dtype=object), allow_pickle=True)
    np.savez(root / "archive.npz", a=good)
    (root / "truncated.npy").write_bytes((root / "good.npy").read_bytes()[:300])
    (root / "text.npy").write_bytes(b"these are not descriptors")
    (root / "zero_bytes.npy").write_bytes(b"")
    # Images.
    png = _png(rng)
    ok, jpeg = cv2.imencode(".jpg", (rng.random((48, 64)) * 255).astype(np.uint8))
    assert ok
    _image_dir(root, "images", rng)
    (root / "other").mkdir()
    _image_dir(root / "other", "images", rng)  # same name, other images
    _image_dir(root, "truncated_png", rng, png[: len(png) // 2])
    _image_dir(root, "truncated_jpeg", rng, jpeg.tobytes()[:-200], "003.jpg")
    _image_dir(root, "not_an_image", rng, b"GIF89a? no, just text")
    _image_dir(root, "empty_image", rng, b"")
    (_image_dir(root, "dangling_link", rng) / "003.png").symlink_to(root / "nowhere.png")
    unreadable = _image_dir(root, "unreadable", rng, png)
    (unreadable / "003.png").chmod(0)
    (root / "no_images").mkdir()
    (root / "no_images" / "notes.txt").write_text("no images here")
    (root / "video.mp4").write_bytes(os.urandom(4096))
    # Positions for the 3 frames of images/ (or the 40 of good.npy).
    frames3 = [f"{i},{i}.0,0" for i in range(3)]
    (root / "pos_ok.csv").write_text(_csv(frames3))
    (root / "pos_range.csv").write_text(_csv(["0,0,0", "1,3e9,0", "2,2,0"]))
    (root / "pos_sigma.csv").write_text(_csv([f"{i},{i}.0,0,{1 - i}" for i in range(3)],
                                             header="frame,x,y,sigma_m"))
    (root / "pos_lat.csv").write_text(_csv(["0,59.9,10.7", "1,95.0,10.7"],
                                           header="frame,lat,lon"))
    (root / "pos_long.csv").write_text(_csv([*frames3, "3,3.0,0"]))
    (root / "pos_header.csv").write_text(_csv(frames3, header="t,east,north"))
    (root / "pos_nan.csv").write_text(_csv([*frames3[:2], "2,nan,0"]))
    (root / "pos_repeat.csv").write_text(_csv([*frames3[:2], "1,1.0,0"]))
    (root / "pos_fields.csv").write_text(_csv([*frames3[:2], "2,2.0"]))
    (root / "pos_binary.csv").write_bytes(b"frame,x,y\n\xff\xfe\x00\x01\n")
    (root / "bad_config.json").write_text("{not json")
    # Configs of the right keys but the wrong types (issue 14, item 12): accepted, the map
    # then crashed every later command (shard_rows 1.5) or took "no" for true.
    for key, value in (("shard_rows", 1.5), ("merge_both_ways", "no"), ("index_pca_dim", 1.5),
                       ("hmm", {"window": [0.5, "x"]})):
        (root / f"config_{key}.json").write_text(json.dumps({key: value}))
    # Text that is not UTF-8 (issue 14, item 10): a file name and a token file.
    np.save(root / os.fsdecode(b"bad\xff.npy"), good)
    (root / "token_latin1.txt").write_bytes(b"s3cr\xe9t\n")
    (root / "config_latin1.json").write_bytes(b'{"descriptor": "caf\xe9"}')
    return root


@pytest.fixture(scope="module")
def templates(tmp_path_factory: pytest.TempPathFactory, inputs: Path) -> dict[str, Path]:
    """``npy``: precomputed map with sequence "first"; ``img``: HoG map with sequence "images";
    ``newer``: a map of a schema version newer than this code's; ``badconfig``: a map whose
    stored config has a value of the wrong type (``shard_rows`` 1.5); ``laterconfig``: one whose
    stored config has an option a later release added (``hmm.later_option``)."""
    root = tmp_path_factory.mktemp("templates")
    paths = {"npy": root / "npy.map", "img": root / "img.map", "newer": root / "newer.map",
             "badconfig": root / "badconfig.map", "laterconfig": root / "laterconfig.map"}
    with SprintMap.create(paths["npy"], MapConfig(dim=DIM)) as m:
        m.add_sequence(np.load(inputs / "good.npy"), name="first")
        m.search(np.load(inputs / "one.npy"), k=1)  # the index is persisted at close: a failed
    with SprintMap.create(paths["img"], MapConfig.for_descriptor("hog")) as m:  # command that
        source = m.open_source(inputs / "images")  # loaded it has nothing new to write
        m.ingest(source.iter_batches(), name="images")
        m.search(m.descriptors(0)[:1], k=1)
    shutil.copytree(paths["npy"], paths["newer"])
    env = lmdb.open(str(paths["newer"] / LMDB_DIR), max_dbs=MAX_DBS)
    meta = env.open_db(b"meta")  # before the write txn: open_db would wait for it
    with env.begin(write=True) as txn:
        txn.put(b"schema_version", str(SCHEMA_VERSION + 1).encode(), db=meta)
    env.close()
    shutil.copytree(paths["npy"], paths["badconfig"])
    env = lmdb.open(str(paths["badconfig"] / LMDB_DIR), max_dbs=MAX_DBS)
    meta = env.open_db(b"meta")
    with env.begin(write=True) as txn:
        config = json.loads(txn.get(b"config", db=meta))
        config["store"]["shard_rows"] = 1.5
        txn.put(b"config", json.dumps(config).encode(), db=meta)
    env.close()
    shutil.copytree(paths["npy"], paths["laterconfig"])
    env = lmdb.open(str(paths["laterconfig"] / LMDB_DIR), max_dbs=MAX_DBS)
    meta = env.open_db(b"meta")
    with env.begin(write=True) as txn:
        config = json.loads(txn.get(b"config", db=meta))
        config["hmm"]["later_option"] = 3  # as a later release stores its new field
        txn.put(b"config", json.dumps(config).encode(), db=meta)
    env.close()
    return paths


def snapshot(path: Path) -> dict[str, Any]:
    """Every LMDB record, every shard byte, every index file of the map at ``path``."""
    if not (path / LMDB_DIR / "data.mdb").is_file():
        return {"listing": sorted(str(p.relative_to(path)) for p in path.rglob("*"))
                if path.exists() else None}
    env = lmdb.open(str(path / LMDB_DIR), readonly=True, lock=False, max_dbs=MAX_DBS)
    try:
        with env.begin() as txn:
            records = {name: list(txn.cursor(db=env.open_db(name.encode(), txn=txn)))
                       for name in DB_NAMES}
    finally:
        env.close()
    files = {str(p.relative_to(path)): p.read_bytes()
             for sub in (SHARDS_DIR, INDEX_DIR) for p in sorted((path / sub).iterdir())}
    return {"lmdb": records, "files": files}


# --- the table ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """``args`` use ``{map}`` and ``{in}``; ``error`` None means the input is valid."""

    args: str
    error: type[SprintMapError] | None
    message: str = ""  # a substring of the one line
    map: str = "npy"  # template name, or "missing", "empty-dir", "file"


CASES: dict[str, Case] = {
    # Descriptors (.npy) for a map of precomputed descriptors.
    "nan": Case("ingest {map} {in}/nan.npy", InvalidDescriptorError, "row 7 contains NaN or Inf"),
    "inf": Case("ingest {map} {in}/inf.npy", InvalidDescriptorError, "row 7 contains NaN or Inf"),
    "minus-inf": Case("ingest {map} {in}/minus_inf.npy", InvalidDescriptorError, "row 7"),
    # an overflow is no descriptor either (its float32 squared distances would be Inf)
    "overflow": Case("ingest {map} {in}/overflow.npy", InvalidDescriptorError,
                     "row 7 is out of range (element 3 is 1e+30, beyond +-1e+15"),
    "beyond-float32": Case("ingest {map} {in}/beyond_float32.npy", InvalidDescriptorError,
                           "row 7 is out of range (element 3 is -1e+300"),
    "wrong-dim": Case("ingest {map} {in}/dim.npy", DescriptorShapeError,
                      "descriptors have 17 dimensions, the map has 16"),
    "one-dimensional": Case("ingest {map} {in}/flat.npy", DescriptorShapeError, "2-D"),
    "dtype-int": Case("ingest {map} {in}/int.npy", DescriptorShapeError, "dtype int64"),
    "dtype-complex": Case("ingest {map} {in}/complex.npy", DescriptorShapeError, "complex64"),
    "dtype-bool": Case("ingest {map} {in}/bool.npy", DescriptorShapeError, "dtype bool"),
    "dtype-object": Case("ingest {map} {in}/object.npy", InputError, "cannot read .npy"),
    "npz-archive": Case("ingest {map} {in}/archive.npz", InputError, "give a .npy"),
    "truncated-npy": Case("ingest {map} {in}/truncated.npy", InputError, "cannot read .npy"),
    "text-as-npy": Case("ingest {map} {in}/text.npy", InputError, "cannot read .npy"),
    "zero-byte-npy": Case("ingest {map} {in}/zero_bytes.npy", InputError, "cannot read .npy"),
    "empty-sequence": Case("ingest {map} {in}/empty.npy", EmptySequenceError, "no descriptors"),
    "missing-source": Case("ingest {map} {in}/absent.npy", InputError, "no such file"),
    "localize-nan": Case("localize {map} {in}/nan.npy", InvalidDescriptorError, "row 7"),
    "localize-wrong-dim": Case("localize {map} {in}/dim.npy", DescriptorShapeError, "17"),
    "images-into-precomputed": Case("ingest {map} {in}/images", InputError, "precomputed"),
    # One frame is a sequence; names are unique, printable.
    "one-frame": Case("ingest {map} {in}/one.npy", None),
    "one-frame-localize": Case("localize {map} {in}/one.npy", None),
    # remove: an unknown id or name removes nothing (the one sequence "first" stays).
    "remove-unknown-id": Case("remove {map} 0 7", UnknownSequenceError, "no sequence 7"),
    "remove-unknown-name": Case("remove {map} first second", UnknownSequenceError,
                                "no sequence named 'second'"),
    # Other descriptors under a committed name (the same ones are a retry: reported, exit 0).
    "duplicate-name": Case("ingest {map} {in}/one.npy --name first", DuplicateNameError,
                           "a sequence named 'first' already exists"),
    "duplicate-default-name": Case("ingest {map} {in}/other/images", DuplicateNameError,
                                   "'images' already exists", map="img"),
    # Names and paths that are not UTF-8 (argv and file names decode with surrogateescape).
    "name-not-utf8": Case("ingest {map} {in}/good.npy --name a\udcffb", InputError,
                          "sequence name b'a\\xffb' is not UTF-8 text"),
    "source-path-not-utf8": Case("ingest {map} {in}/bad\udcff.npy", InputError,
                                 "bad\\xff.npy' is not UTF-8 text"),
    "remove-name-not-utf8": Case("remove {map} \udcff", InputError,
                                 "sequence name b'\\xff' is not UTF-8 text"),
    "name-empty": Case("ingest {map} {in}/good.npy --name ", InputError,
                       "an empty name is not a name"),  # was: named after the source
    "init-config-not-utf8": Case("init {map} --dim 4 --config {in}/config_latin1.json",
                                 InputError, "cannot read config", map="missing"),
    "remove-empty-name": Case("remove {map} ", UnknownSequenceError,
                              "no sequence named '' in the map"),
    "init-path-not-utf8": Case("init {map} --dim 4", InputError, "case\\xff.map' is not UTF-8 "
                               "text", map="undecodable"),
    "serve-token-not-utf8": Case("serve {map} --token-file {in}/token_latin1.txt", InputError,
                                 "token_latin1.txt is not UTF-8 text"),
    "name-with-newline": Case("ingest {map} {in}/good.npy --name a\nb", InputError,
                              "non-printing characters"),
    # Images and video for a HoG map.
    "truncated-png": Case("ingest {map} {in}/truncated_png --name x", InputError,
                          "003.png: cannot decode image", map="img"),
    "truncated-jpeg": Case("ingest {map} {in}/truncated_jpeg --name x", InputError,
                           "003.jpg: truncated image file", map="img"),
    "not-an-image": Case("ingest {map} {in}/not_an_image --name x", InputError,
                         "cannot decode image", map="img"),
    "empty-image": Case("ingest {map} {in}/empty_image --name x", InputError,
                        "003.png: empty image file", map="img"),
    "dangling-link": Case("ingest {map} {in}/dangling_link --name x", InputError,
                          "003.png: cannot read image (No such file or directory)", map="img"),
    "unreadable-image": Case("ingest {map} {in}/unreadable --name x", InputError,
                             "003.png: cannot read image (Permission denied)", map="img"),
    "no-images": Case("ingest {map} {in}/no_images", InputError, "no image files", map="img"),
    "garbage-video": Case("ingest {map} {in}/video.mp4", InputError, "video.mp4", map="img"),
    "npy-into-hog-map": Case("ingest {map} {in}/good.npy", DescriptorShapeError,
                             "descriptors have 16 dimensions", map="img"),
    # Positions that do not match the frames (images/ has 4 frames).
    # (a frame without a row is a frame without a fix, not an error)
    "positions-long": Case("ingest {map} {in}/images --name x --positions {in}/pos_long.csv",
                           InputError, "pos_long.csv:5: frame 3 is beyond the drive (3 frames)",
                           map="img"),
    "positions-sigma": Case("ingest {map} {in}/images --name x --positions {in}/pos_sigma.csv",
                            InputError, "pos_sigma.csv:3: sigma_m must be > 0 metres, got 0",
                            map="img"),
    "positions-range": Case("ingest {map} {in}/images --name x --positions {in}/pos_range.csv",
                            InputError, "GNSS fixes: frame 1: x, y [3000000000.0, 0.0] out of "
                            "range", map="img"),
    "localize-positions-sigma": Case("localize {map} {in}/images --positions "
                                     "{in}/pos_sigma.csv", InputError,
                                     "pos_sigma.csv:3: sigma_m must be > 0 metres, got 0",
                                     map="img"),
    "positions-lat": Case("ingest {map} {in}/images --name x --positions {in}/pos_lat.csv",
                          InputError, "pos_lat.csv:3: lat 95 is outside [-90, 90]", map="img"),
    "positions-header": Case("ingest {map} {in}/images --name x --positions {in}/pos_header.csv",
                             InputError, "pos_header.csv:1: bad header", map="img"),
    "positions-nan": Case("ingest {map} {in}/images --name x --positions {in}/pos_nan.csv",
                          InputError, "pos_nan.csv:4: x is not finite", map="img"),
    "positions-repeated": Case("ingest {map} {in}/images --name x --positions "
                               "{in}/pos_repeat.csv", InputError, "pos_repeat.csv:4", map="img"),
    "positions-fields": Case("ingest {map} {in}/images --name x --positions {in}/pos_fields.csv",
                             InputError, "pos_fields.csv:4: expected 3 fields", map="img"),
    "positions-binary": Case("ingest {map} {in}/images --name x --positions {in}/pos_binary.csv",
                             InputError, "pos_binary.csv", map="img"),
    "positions-missing": Case("ingest {map} {in}/images --name x --positions {in}/absent.csv",
                              InputError, "absent.csv: cannot read positions", map="img"),
    # serve: refused before anything is served (a token file is any non-empty text file).
    "serve-public-no-token": Case("serve {map} --host 0.0.0.0", UnsafeServeError,
                                  "refusing to listen on 0.0.0.0 without a bearer token"),
    "serve-foreign-address": Case("serve {map} --host 192.0.2.1 --token-file {in}/pos_ok.csv",
                                  ListenError, "cannot listen on 192.0.2.1:8000"),
    # Paths that are not maps, maps we cannot read.
    **{f"not-a-map-{cmd}": Case(f"{cmd} {{map}}" + (" {in}/good.npy" if cmd in (
        "ingest", "localize") else ""), NotAMapError, "not a sprint-map directory", map=kind)
       for cmd, kind in (("ingest", "empty-dir"), ("localize", "file"), ("info", "missing"),
                         ("check", "empty-dir"), ("sequences", "file"),
                         ("components", "missing"))},
    **{f"newer-schema-{cmd}": Case(f"{cmd} {{map}}" + (" {in}/good.npy" if cmd in (
        "ingest", "localize") else ""), SchemaVersionError,
        f"map schema version {SCHEMA_VERSION + 1} is not supported by this sprint-map (it "
        f"reads version {SCHEMA_VERSION} and older); "
        "upgrade sprint-map", map="newer")
       for cmd in ("ingest", "localize", "info", "check")},
    "init-existing": Case("init {map} --dim 4", MapExistsError, "non-empty path"),
    "init-dim-0": Case("init {map} --dim 0", ConfigError, "dim must be a positive", map="missing"),
    "init-bad-config": Case("init {map} --config {in}/bad_config.json", InputError,
                            "cannot read config", map="missing"),
    "init-float-shard-rows": Case("init {map} --dim 4 --config {in}/config_shard_rows.json",
                                  ConfigError, "MapConfig.store: shard_rows must be an integer, got 1.5",
                                  map="missing"),
    "init-string-bool": Case("init {map} --dim 4 --config {in}/config_merge_both_ways.json",
                             ConfigError, "MapConfig.merge: both_ways must be true or false, "
                             "got 'no'", map="missing"),
    "init-float-pca-dim": Case("init {map} --dim 4 --config {in}/config_index_pca_dim.json",
                               ConfigError, "MapConfig.store: index_pca_dim must be an integer, got 1.5",
                               map="missing"),
    "init-nested-window": Case("init {map} --dim 4 --config {in}/config_hmm.json", ConfigError,
                               "MapConfig.hmm: window must be a list of numbers", map="missing"),
    # A stored config that fails validation is a corrupt map (it was a crash in every command).
    **{f"stored-config-{cmd}": Case(f"{cmd} {{map}}" + (" {in}/one.npy" if cmd in (
        "ingest", "localize") else ""), MapCorruptError, "corrupt map record config: MapConfig.store: "
        "shard_rows must be an integer, got 1.5", map="badconfig")
       for cmd in ("info", "check", "ingest", "localize")},
    # An option no field has is a later release's map: the newer schema's error, not damage.
    **{f"later-config-{cmd}": Case(f"{cmd} {{map}}" + (" {in}/one.npy" if cmd in (
        "ingest", "localize") else ""), SchemaVersionError, "option(s) this sprint-map does not "
        "know (MapConfig.hmm.later_option): it was made by a newer sprint-map", map="laterconfig")
       for cmd in ("info", "check", "ingest", "localize")},
    "hmm-float-k": Case("localize {map} {in}/good.npy --hmm k=1.5", ConfigError,
                        "HMMConfig: k must be an integer, got 1.5"),
    "hmm-string-bool-merge": Case("ingest {map} {in}/good.npy --name x --hmm place_hops=true",
                                  ConfigError, "HMMConfig: place_hops must be an integer, got "
                                  "True"),
    # Model options.
    "k-zero": Case("localize {map} {in}/good.npy --k 0", ConfigError, "k must be an integer"),
    "unknown-hmm-option": Case("ingest {map} {in}/good.npy --name x --hmm bogus=1", ConfigError,
                               "unknown option(s) bogus"),
}


def _map_path(case: Case, templates: dict[str, Path], tmp_path: Path) -> Path:
    path = tmp_path / "case.map"
    if case.map == "undecodable":  # a path that is not UTF-8, absent
        path = tmp_path / os.fsdecode(b"case\xff.map")
    if case.map in templates:
        shutil.copytree(templates[case.map], path)
    elif case.map == "empty-dir":
        path.mkdir()
    elif case.map == "file":
        path.write_text("not a map")
    return path


def _args(case: Case, path: Path, inputs: Path) -> list[str]:
    return [a.replace("{map}", str(path)).replace("{in}", str(inputs))
            for a in case.args.split(" ")]


def assert_one_line_error(output: str, error: type[SprintMapError], message: str) -> None:
    lines = output.strip().splitlines()
    assert len(lines) == 1, output
    assert lines[0].startswith("Error: "), output
    assert message in lines[0], output
    assert "Traceback" not in output


@pytest.mark.parametrize("name", CASES)
def test_bad_input_is_one_line_a_distinct_exit_and_changes_nothing(
        name, inputs, templates, tmp_path):
    case = CASES[name]
    if name == "unreadable-image" and os.geteuid() == 0:
        pytest.skip("root reads a file of mode 000; the dangling-link row covers an "
                    "unreadable frame")
    path = _map_path(case, templates, tmp_path)
    before = snapshot(path)
    result = CliRunner().invoke(main, _args(case, path, inputs))
    # Nothing but click's own exit escaped the command.
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    if case.error is None:
        assert result.exit_code == 0, result.output
        if case.args.startswith("ingest"):
            with MapStore.open(path, readonly=True) as store:
                assert store.stats()["sequences"] == 2
                assert [s.length for s in store.sequences()] == [40, 1]
        return
    assert result.exit_code == case.error.exit_code, result.output
    assert_one_line_error(result.output, case.error, case.message)
    assert snapshot(path) == before


def test_exit_codes_are_distinct_per_error_class():
    classes = [c for c in vars(errors).values()
               if isinstance(c, type) and issubclass(c, SprintMapError)]
    codes = [c.exit_code for c in classes]
    assert len(set(codes)) == len(classes) >= 15
    assert not {0, 1, 2} & set(codes)  # 1: OS errors and check's violations; 2: click usage
    assert issubclass(EmptySequenceError, InputError)  # caught as bad input, with its own code


def test_every_error_class_is_exercised():
    tried = {case.error for case in CASES.values()}
    tried |= {ReadOnlyMapError, MapLockedError, StorageIOError}  # below
    tried |= {errors.ReplicaLostError}  # tests/fleet/test_serve_ray.py kills a replica
    tried |= {errors.IncompatibleMapError, errors.UnconnectedJoinError}  # tests/merge/test_join.py
    untested = {c.__name__ for c in vars(errors).values()
                if isinstance(c, type) and issubclass(c, SprintMapError)} - {
        c.__name__ for c in tried if c is not None}
    # The base class is for API misuse only (corruption: the stored-config rows here, the rest in
    # tests/storage/test_check.py and the fuzz).
    assert untested == {"SprintMapError"}


def test_a_bad_stride_is_a_usage_error_not_a_traceback(inputs, templates, tmp_path):
    path = _map_path(Case("", None), templates, tmp_path)
    result = CliRunner().invoke(main, ["ingest", str(path), str(inputs / "good.npy"),
                                       "--stride", "0"])
    assert result.exit_code == 2 and result.exception is None or isinstance(
        result.exception, SystemExit)
    assert "Invalid value for '--stride'" in result.output and "Traceback" not in result.output


def test_a_second_writer_is_refused_naming_the_lock(inputs, templates, tmp_path):
    path = _map_path(Case("", None), templates, tmp_path)
    before = snapshot(path)
    with MapStore.open(path):
        result = CliRunner().invoke(main, ["ingest", str(path), str(inputs / "one.npy")])
    assert result.exit_code == MapLockedError.exit_code
    assert_one_line_error(result.output, MapLockedError, f"pid {os.getpid()}): {path}/LOCK")
    assert snapshot(path) == before


# --- a read-only map directory --------------------------------------------------------------


@pytest.fixture
def read_only_map(templates: dict[str, Path], tmp_path: Path) -> Iterator[Path]:
    """A copy of the ``npy`` map that this process cannot write: mode a-w, or for root (whom
    modes do not stop) the immutable attribute. Skipped only if neither is possible."""
    path = _map_path(Case("", None), templates, tmp_path)
    entries = [path, *path.rglob("*")]
    undo: Callable[[], Any]
    if os.geteuid() != 0:
        for entry in entries:
            entry.chmod(entry.stat().st_mode & ~0o222)

        def undo() -> None:
            for entry in entries:
                entry.chmod(entry.stat().st_mode | 0o200)
    else:
        made = subprocess.run(["chattr", "-R", "+i", str(path)], capture_output=True)
        if made.returncode != 0:
            pytest.skip(f"running as root, and chattr +i failed ({made.stderr!r}): no way to "
                        "make a directory read-only for root here")

        def undo() -> None:
            subprocess.run(["chattr", "-R", "-i", str(path)], check=True)
    try:
        with pytest.raises(OSError) as denied:
            (path / "probe").write_text("x")
        assert denied.value.errno in (errno.EACCES, errno.EPERM)
        yield path
    finally:
        undo()


def test_a_read_only_map_refuses_writes_and_serves_reads(read_only_map, inputs):
    before = snapshot(read_only_map)
    result = CliRunner().invoke(main, ["ingest", str(read_only_map), str(inputs / "one.npy")])
    assert result.exit_code == ReadOnlyMapError.exit_code
    assert_one_line_error(result.output, ReadOnlyMapError, "map is not writable")
    # Readers work: without write access to LMDB's lock file they read lock-free, holding a
    # shared flock on the map's LOCK so that no writer can start meanwhile.
    for args in (["info", "--json"], ["check"], ["sequences"]):
        result = CliRunner().invoke(main, [args[0], str(read_only_map), *args[1:]])
        assert result.exit_code == 0, (args, result.output)
    result = CliRunner().invoke(main, ["localize", str(read_only_map), str(inputs / "one.npy"),
                                       "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["decisions"][0]["seq_id"] == 0
    assert snapshot(read_only_map) == before


# --- real subprocesses: what a user sees --------------------------------------------------------


def _limit_file_size(limit: int) -> Callable[[], None]:
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
    return apply


def test_real_processes_print_one_line_and_no_traceback(inputs, templates, tmp_path):
    """The installed ``sprint-map`` entry point, in parallel processes (each starts in ~2 s)."""
    runs = {}
    for name in ("nan", "truncated-png", "newer-schema-info", "not-a-map-check"):
        case = CASES[name]
        (tmp_path / name).mkdir()
        path = _map_path(case, templates, tmp_path / name)
        runs[name] = (case, path, snapshot(path), subprocess.Popen(
            [SPRINT_MAP, *_args(case, path, inputs)], stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True))
    # A full disk: every write past 64 kB fails (EFBIG), here the shard file of a big drive.
    (tmp_path / "full").mkdir()
    path = _map_path(Case("", None), templates, tmp_path / "full")
    big = tmp_path / "big.npy"
    np.save(big, np.random.default_rng(1).standard_normal((8000, DIM)).astype(np.float32))
    runs["full-disk"] = (Case("", StorageIOError, "cannot write descriptor shard "
                              "shard-000000.f32: File too large"), path, snapshot(path),
                         subprocess.Popen([SPRINT_MAP, "ingest", str(path), str(big)],
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          text=True, preexec_fn=_limit_file_size(64 << 10)))
    for name, (case, path, before, proc) in runs.items():
        out, err = proc.communicate(timeout=120)
        assert case.error is not None
        assert proc.returncode == case.error.exit_code, (name, err)
        assert out == "", name
        assert_one_line_error(err, case.error, case.message)  # no OpenCV/libpng chatter either
        assert snapshot(path) == before, name


def test_one_frame_sequences_are_valid_everywhere(tmp_path, inputs):
    """The rule: a one-frame sequence is a sequence. As the whole map, as a query, as a drive
    merged into a map of one-frame sequences: added, localised, matched."""
    good = np.load(inputs / "good.npy")
    # (The default merge rule wants a run of frames along a drive: no one-frame drive passes.)
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM, merge=MergeRule(min_run=0))) as m:
        m.add_sequence(good[:1], name="only")
        single = m.ingest(good[:1] + 0.001, name="again")  # a one-frame drive, localised
        assert single.decisions[0].seq_id == 0 and single.added.edges_added > 0
        drive = m.ingest(good[:5], name="drive")  # a longer drive against one-frame sequences
        assert len(drive.decisions) == 5
        decisions, _ = m.localize(good[:1])
        assert decisions[0].seq_id in (0, 1, 2)
        assert [s.length for s in m.sequences()] == [1, 1, 5]
        assert m.check().ok
