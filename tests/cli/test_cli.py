"""The CLI through click's CliRunner: JSON contracts, one-line errors, exit codes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import SCHEMA_VERSION
from sprint_map.errors import (
    DescriptorShapeError,
    DuplicateNameError,
    InputError,
    InvalidDescriptorError,
    MapExistsError,
    NotAMapError,
    UnknownSequenceError,
)

DIM = 16


def run(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture
def drives(tmp_path, rng):
    """Three noisy drives over the same 60 places, as .npy files."""
    places = rng.standard_normal((60, DIM))
    paths = []
    for i in range(3):
        x = places + 0.3 * rng.standard_normal(places.shape)
        path = tmp_path / f"drive{i}.npy"
        np.save(path, (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32))
        paths.append(path)
    return paths


@pytest.fixture
def map_path(tmp_path):
    path = tmp_path / "city.map"
    result = run("init", path, "--dim", DIM)
    assert result.exit_code == 0, result.output
    return path


def test_ingest_info_sequences_components_check(map_path, drives, tmp_path):
    csv = tmp_path / "pos.csv"
    csv.write_text("frame,x,y\n" + "".join(f"{i},{i}.0,0\n" for i in range(60)))
    first = json.loads(run("ingest", map_path, drives[0], "--positions", csv, "--json").output)
    assert first == {"seq_id": 0, "name": "drive0", "frames": 60, "frames_stored": 60,
                     "frames_skipped": 0, "sightings": 0, "component": 0,
                     "edges_added": 0, "already_committed": False, "decisions": [],
                     "timing": first["timing"]}
    second = json.loads(run("ingest", map_path, drives[1], "--json").output)
    assert len(second["decisions"]) == 60
    assert set(second["decisions"][0]) == {"frame", "seq_id", "image_id", "prob", "novel_prob",
                                           "distance", "contrast", "confirmed", "verified",
                                           "gnss_dist_m", "merged", "stored_as"}
    assert second["edges_added"] > 0 and second["component"] == 0
    assert {"retrieval_ms_per_frame", "hmm_ms_per_frame"} <= set(second["timing"])
    third = json.loads(run("ingest", map_path, drives[2], "--no-merge", "--json").output)
    assert third["decisions"] == [] and third["edges_added"] == 0 and third["component"] == 2

    info = json.loads(run("info", map_path, "--json").output)
    assert {k: info[k] for k in ("schema_version", "sequences", "vertices", "components", "dim")} \
        == {"schema_version": SCHEMA_VERSION, "sequences": 3, "vertices": 180, "components": 2, "dim": DIM}
    assert info["edges"] == second["edges_added"]
    assert info["index"]["ntotal"] == 180 and info["index"]["type"]
    assert info["disk_bytes"] > 0
    seqs = json.loads(run("sequences", map_path, "--json").output)
    assert [(s["seq_id"], s["name"], s["frames"], s["component"]) for s in seqs] == [
        (0, "drive0", 60, 0), (1, "drive1", 60, 0), (2, "drive2", 60, 2)]
    comps = json.loads(run("components", map_path, "--json").output)
    assert comps == [{"component": 0, "sequences": [0, 1], "vertices": 120},
                     {"component": 2, "sequences": [2], "vertices": 60}]
    result = run("check", map_path, "--json")
    assert result.exit_code == 0 and json.loads(result.output)["ok"]


def test_ingest_several_sources_in_order(map_path, drives, tmp_path):
    result = run("ingest", map_path, *drives, "--json")
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert [(r["seq_id"], r["name"], r["frames"]) for r in out] == [
        (0, "drive0", 60), (1, "drive1", 60), (2, "drive2", 60)]
    assert out[0]["decisions"] == [] and out[1]["edges_added"] > 0 and out[2]["edges_added"] > 0
    # the same drives, one command each: the same decisions
    serial = tmp_path / "serial.map"
    run("init", serial, "--dim", DIM)
    one_by_one = [json.loads(run("ingest", serial, d, "--json").output) for d in drives]
    assert [r["decisions"] for r in one_by_one] == [r["decisions"] for r in out]
    text = run("ingest", map_path, *drives).output.strip().splitlines()
    assert [t for t in text if not t.startswith("Warning: ")] == [f"sequence {i} (drive{i}) was already committed with these 60 frames: "
                    "nothing added" for i in range(3)]


@pytest.mark.parametrize("option", [("--name", "x"), ("--positions", "p.csv")])
def test_ingest_name_and_positions_are_for_one_source(map_path, drives, option):
    result = CliRunner().invoke(main, ["ingest", str(map_path), *map(str, drives[:2]), *option])
    assert result.exit_code == InputError.exit_code
    assert result.output.strip().splitlines() == [
        f"Error: {option[0]} is for one SOURCE; 2 given (each drive is named after its source)"]


def test_ingest_failure_names_the_drive_and_keeps_the_earlier(map_path, drives, tmp_path):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.full((4, DIM), np.nan, np.float32))
    result = CliRunner().invoke(main, ["ingest", str(map_path), str(drives[0]), str(bad)])
    assert result.exit_code == InvalidDescriptorError.exit_code  # checked before any commit
    assert json.loads(run("info", map_path, "--json").output)["sequences"] == 0
    run("ingest", map_path, drives[1], "--name", "drive2")  # drive2's name, other rows
    result = CliRunner().invoke(main, ["ingest", str(map_path), str(drives[0]), str(drives[2]),
                                       str(drives[1])])
    assert result.exit_code == DuplicateNameError.exit_code
    lines = result.output.strip().splitlines()
    assert lines[0].startswith("added sequence 1 (drive0)")
    assert lines[1].startswith(f"Error: {drives[2]}: ") and lines[1].endswith(
        "(1 earlier drive(s) committed)")
    seqs = json.loads(run("sequences", map_path, "--json").output)
    assert [s["name"] for s in seqs] == ["drive2", "drive0"]


def test_localize_is_read_only_and_writes_out(map_path, drives, tmp_path):
    run("ingest", map_path, drives[0])
    before = json.loads(run("info", map_path, "--json").output)
    out = tmp_path / "dec.json"
    result = run("localize", map_path, drives[1], "--json", "--out", out, "--k", 5,
                 "--hmm", "restart_prob=0.02")
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert json.loads(out.read_text()) == data
    assert len(data["decisions"]) == 60 and "timing" in data
    matched = [d for d in data["decisions"] if d["seq_id"] is not None]
    assert len(matched) > 40
    after = json.loads(run("info", map_path, "--json").output)
    assert {k: after[k] for k in ("sequences", "vertices", "edges")} == \
        {k: before[k] for k in ("sequences", "vertices", "edges")}


@pytest.mark.parametrize(
    ("make", "error"),
    [
        (lambda p: np.save(p, np.full((4, DIM), np.nan, np.float32)), InvalidDescriptorError),
        (lambda p: np.save(p, np.zeros((4, DIM + 1), np.float32)), DescriptorShapeError),
        (lambda p: np.save(p, np.zeros((0, DIM), np.float32)), None),
    ],
)
def test_bad_descriptors_give_one_line_and_commit_nothing(map_path, tmp_path, make, error):
    bad = tmp_path / "bad.npy"
    make(bad)
    result = CliRunner().invoke(main, ["ingest", str(map_path), str(bad)])
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert "Traceback" not in result.output
    if error is not None:
        assert result.exit_code == error.exit_code
    assert json.loads(run("info", map_path, "--json").output)["vertices"] == 0


def test_errors_exit_with_their_codes(map_path, drives, tmp_path):
    run("ingest", map_path, drives[0], "--name", "a")
    dup = CliRunner().invoke(main, ["ingest", str(map_path), str(drives[1]), "--name", "a"])
    assert dup.exit_code == DuplicateNameError.exit_code
    assert dup.output.startswith("Error: a sequence named 'a' already exists")
    not_map = CliRunner().invoke(main, ["info", str(tmp_path)])
    assert not_map.exit_code == NotAMapError.exit_code and "not a sprint-map" in not_map.output
    again = CliRunner().invoke(main, ["init", str(map_path), "--dim", "4"])
    assert again.exit_code == MapExistsError.exit_code
    images = CliRunner().invoke(main, ["ingest", str(map_path), str(tmp_path)])
    assert images.exit_code != 0 and "precomputed" in images.output


def test_check_reports_violations_with_exit_1(map_path, drives):
    run("ingest", map_path, drives[0])
    shard = next((map_path / "shards").iterdir())
    with open(shard, "r+b") as fh:
        fh.truncate(100)
    result = CliRunner().invoke(main, ["check", str(map_path)])
    assert result.exit_code == 1
    assert "violation: shard file" in result.output


def test_init_hog_sets_the_dimension(tmp_path):
    result = run("init", tmp_path / "h.map", "--descriptor", "hog")
    assert "dim 1764" in result.output
    info = json.loads(run("info", tmp_path / "h.map", "--json").output)
    assert info["dim"] == 1764 and info["descriptor"] == "hog"


def test_every_command_has_an_example():
    for name, command in main.commands.items():
        assert "Example" in (command.help or ""), name


#: ``edges --json`` and ``unmerge --json``: the keys outside scripts read.
EDGE_KEYS = {"src_seq", "src_image", "dst_seq", "dst_image", "prob", "added_by"}
UNMERGE_KEYS = {"seq_id", "edges_removed", "components"}


def test_edges_and_unmerge(make_map):
    built = make_map((8, 9, 10, 11, 12, 13), dim=DIM, edges=3)
    listed = json.loads(run("edges", built.path, "--json").output)
    assert len(listed) == len(built.edge_set()) and listed
    assert all(set(e) == EDGE_KEYS for e in listed)
    seq = max(range(6), key=lambda s: sum(e["added_by"] == s for e in listed))
    name = built.sequences[seq].name
    preview = json.loads(run("edges", built.path, "--added-by", name, "--json").output)
    assert preview == [e for e in listed if e["added_by"] == seq] and preview
    touching = json.loads(run("edges", built.path, "--seq", seq, "--json").output)
    assert touching == [e for e in listed if seq in (e["src_seq"], e["dst_seq"])]
    text = run("edges", built.path, "--seq", name).output
    assert f"added by {seq} ({name})" in text and "p=" in text

    result = run("unmerge", built.path, name, "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert set(data) == UNMERGE_KEYS
    assert (data["seq_id"], data["edges_removed"]) == (seq, len(preview))
    comps = {c["component"] for c in json.loads(run("components", built.path, "--json").output)}
    assert data["components"] and set(data["components"]) <= comps
    assert json.loads(run("edges", built.path, "--json").output) == [
        e for e in listed if e["added_by"] != seq]
    again = run("unmerge", built.path, seq)
    assert again.output.strip() == f"unmerged sequence {seq}: 0 edges revoked; components now []"
    assert run("check", built.path).exit_code == 0

    for args in (("unmerge", built.path, "9"), ("edges", built.path, "--seq", "nope"),
                 ("edges", built.path, "--added-by", "9")):
        result = CliRunner().invoke(main, [str(a) for a in args])
        assert result.exit_code == UnknownSequenceError.exit_code
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error: no sequence"), result.output
    result = CliRunner().invoke(main, ["edges", str(built.path), "--seq", "12", "--by-name"])
    assert result.output.startswith("Error: no sequence named '12'")


@pytest.mark.parametrize("command", ["remove", "unmerge", "edges"])
@pytest.mark.parametrize("name", ["\uff11", "\u0663", "\u00b2"])
def test_seq_of_non_ascii_digits_is_a_name(tmp_path, drives, command, name):
    """Only ASCII digits make a sequence id: a drive named with other digits (fullwidth,
    Arabic-Indic, a superscript) is found by its name, never read as another drive's id."""
    map_path = tmp_path / "m.map"
    run("init", map_path, "--dim", DIM)
    run("ingest", map_path, drives[0], "--name", name, "--no-merge")  # sequence 0
    run("ingest", map_path, drives[1], "--name", "other")  # sequence 1, merged with 0
    run("ingest", map_path, drives[2], "--name", "third")  # sequence 2
    args = {"remove": [name], "unmerge": [name], "edges": ["--added-by", name]}[command]
    out = run(command, map_path, *args, "--json")
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    if command == "remove":
        assert [r["seq_id"] for r in data["removed"]] == [0]
    elif command == "unmerge":
        assert data["seq_id"] == 0
    else:
        assert data == []  # sequence 0 was added without merging: it added no edge
    left = json.loads(run("sequences", map_path, "--json").output)
    assert {r["seq_id"] for r in left} == ({1, 2} if command == "remove" else {0, 1, 2})


def test_index_learn_and_no_learn_json_contract(tmp_path):
    """``index --learn --json`` prints exactly the contract's keys; ``info --json`` gains
    ``projection``; ``--no-learn`` drops it (issue 33)."""
    from tests.helpers import learn_world

    path = learn_world.build(tmp_path / "m")
    assert json.loads(run("info", path, "--json").output)["projection"] is None
    result = run("index", path, "--learn", "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert set(report) == {"pairs", "dim_in", "dim_out", "adopted", "heldout_recall_before",
                           "heldout_recall_after"}
    assert (report["pairs"], report["dim_in"], report["dim_out"], report["adopted"]) == (
        learn_world.PLACES, learn_world.DIM, 16, True)
    assert json.loads(run("info", path, "--json").output)["projection"] == {
        "pairs": learn_world.PLACES, "dim_out": 16, "trained_at_edges": 2 * learn_world.PLACES}
    assert run("check", path).exit_code == 0
    assert run("index", path, "--no-learn").exit_code == 0
    assert json.loads(run("info", path, "--json").output)["projection"] is None


def test_init_admission_novel_is_stored_and_ingest_reports_what_it_stored(tmp_path, drives):
    path = tmp_path / "fleet.map"
    result = run("init", path, "--dim", DIM, "--admission", "novel")
    assert result.exit_code == 0, result.output
    info = json.loads(run("info", path, "--json").output)
    assert info["admission"] == info["config"]["admission"]["mode"] == "novel"
    assert "admission: novel" in run("info", path).output
    run("ingest", path, drives[0], "--json")
    again = json.loads(run("ingest", path, drives[0], "--name", "again", "--json").output)
    # the very drive again: every frame matched where retrieval alone finds it
    assert (again["frames"], again["frames_stored"], again["frames_skipped"]) == (60, 0, 60)
    assert again["seq_id"] is None and again["sightings"] == 60
    assert all(d["stored_as"] is None for d in again["decisions"])
    line = run("ingest", path, drives[0], "--name", "third").output
    assert line.startswith("stored nothing of third: 60 frames, 60 matched, 60 places seen")
    new = json.loads(run("ingest", path, drives[1], "--name", "new", "--json").output)
    stored = [d["stored_as"] for d in new["decisions"] if d["stored_as"] is not None]
    assert len(stored) == new["frames_stored"] and new["seq_id"] in (None, 1)
    assert [image for _, image in stored] == list(range(len(stored)))
    bad = run("init", tmp_path / "other.map", "--dim", DIM, "--admission", "some")
    assert bad.exit_code != 0 and "some" in bad.output


def test_summarize_json_contract(map_path, drives, tmp_path):
    run("ingest", map_path, drives[0], "--name", "first")
    run("ingest", map_path, drives[0], "--name", "again")  # every frame a view the map has
    data = json.loads(run("summarize", map_path, "--json").output)
    assert {k: data[k] for k in ("vertices_before", "vertices_after", "sequences_before",
                                 "sequences_after")} == {
        "vertices_before": 120, "vertices_after": 60, "sequences_before": 2,
        "sequences_after": 1}
    assert data["sightings"] == 60 and data["bytes_after"] < data["bytes_before"]
    assert run("summarize", map_path).output.startswith("summarised: 60 -> 60 vertices")
    bad = CliRunner().invoke(main, ["summarize", str(map_path), "--per-place", "0"])
    assert bad.exit_code == 2 and "--per-place" in bad.output
    assert run("check", map_path).exit_code == 0
