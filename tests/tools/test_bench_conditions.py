"""tools/bench_conditions.py: the multi-condition lifelong benchmark, end to end on tiny streams."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import ConfigError
from sprint_map.frontend import GroundTruth, GroundTruthSpec
from tools import bench_conditions, condition_worlds
from tools.condition_worlds import Drive


def test_set_changes_flat_and_dotted_keys() -> None:
    base = MapConfig(dim=8)
    changed = bench_conditions.apply_sets(base, ["merge_min_run=7", "hmm.k=13",
                                                 "index_type=flat"])
    assert changed.merge.min_run == 7 and changed.hmm.k == 13
    assert changed.store.index_type == "flat"
    assert dataclasses.replace(changed.hmm, k=base.hmm.k) == base.hmm  # the rest kept
    with pytest.raises(ConfigError):
        bench_conditions.apply_sets(base, ["hmm.no_such_field=1"])
    with pytest.raises(SystemExit):
        bench_conditions.apply_sets(base, ["no-equals-sign"])


def test_an_arm_keeps_json_values_whole() -> None:
    """A value runs to the next KEY=: JSON keeps its quotes and spaces (shlex stripped them)."""
    label, sets = bench_conditions.parse_arm('centred centring={"mode": "drive"} hmm.k=13')
    assert (label, sets) == ("centred", ['centring={"mode": "drive"}', "hmm.k=13"])
    changed = bench_conditions.apply_sets(MapConfig(dim=8), sets)
    assert changed.centring.mode == "drive" and changed.hmm.k == 13
    assert bench_conditions.parse_arm("raw") == ("raw", [])
    for bad in ("k=1 hmm.k=2", "centred drive"):
        with pytest.raises(SystemExit):
            bench_conditions.parse_arm(bad)


def test_cross_season_frames_are_held_only_under_the_other_season() -> None:
    def line(lo: int, n: int) -> np.ndarray:
        return np.column_stack([np.arange(n), np.arange(lo, lo + n, dtype=float), np.zeros(n)])

    gt = GroundTruth(GroundTruthSpec("position", radius_m=0.5),
                     positions={"a": line(0, 10), "b": line(10, 10), "q": line(0, 20)})
    rows = np.zeros((20, 4), dtype=np.float32)
    a, b = Drive("a", "summer", "-", rows[:10]), Drive("b", "winter", "-", rows[:10])
    winter, summer = Drive("q", "winter", "-", rows), Drive("q", "summer", "-", rows)
    cross = bench_conditions.cross_season
    assert cross(winter, [a, b], gt).tolist() == [True] * 10 + [False] * 10
    assert cross(summer, [a, b], gt).tolist() == [False] * 10 + [True] * 10
    # No drive of the query's season in the map: nothing pulls it away, no cross-season frame.
    assert not cross(winter, [a], gt).any()


def test_latent_stream_end_to_end_with_an_arm(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "conditions.json"
    assert bench_conditions.main(["--world", "latent", "--seeds", "0", "--drives", "5",
                                  "--frames", "40", "--probes", "2", "--set", "hmm.k=12",
                                  "--arm", "minrun merge_min_run=9",
                                  "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    [run] = data["seeds"]
    assert set(run["arms"]) == {"default", "minrun"}
    assert run["arms"]["minrun"]["map_config"]["merge"]["min_run"] == 9
    assert run["arms"]["default"]["map_config"]["merge"]["min_run"] != 9
    assert {arm["map_config"]["hmm"]["k"] for arm in run["arms"].values()} == {12}  # --set: all
    rows = run["arms"]["default"]["rows"]
    assert [r["drive"] for r in rows] == [1, 2, 3, 4]
    assert [r["season"] for r in rows] == ["summer", "winter", "winter", "summer"]
    for r in rows:
        # The holders are earlier drives with a true match; the alias cost is whole - holders.
        earlier = [d["name"] for d in rows if d["drive"] < r["drive"]]
        assert set(r["holders"]) <= {"t00-day-summer", *earlier}
        for kind in ("causal", "smoothed"):
            assert r[f"alias_{kind}_points"] == pytest.approx(100 * (
                r[f"whole_{kind}_sprint_recall@1"] - r[f"holders_{kind}_sprint_recall@1"]),
                abs=0.02)
        assert r["whole_frames_with_match"] == r["holders_frames_with_match"]
        assert 0 <= r["merged_wrong"] <= r["merged"] and r["unmapped_merged"] <= r["unmapped"]
        for prefix in ("whole", "holders"):
            for kind in ("causal", "smoothed"):
                assert 0 <= r[f"{prefix}_cross_{kind}_sprint_correct"] <= r["cross_frames"]
    # The later half (drives 2..4) is also answered by the map before it.
    assert ["snapshot_frames_with_match" in r for r in rows] == [False, True, True, True]
    # Held-back probes (the next two drives of the world) are answered at the half and the end,
    # and scored on the same frames: those the map at the half can match.
    probes = run["arms"]["default"]["probes"]
    assert [p["name"] for p in probes] == ["t05-snow-summer", "t06-day-winter"]
    assert all(p["name"] not in r["holders"] for p in probes for r in rows)
    for p in probes:
        assert p["after_on_before_frames_with_match"] == p["before_frames_with_match"]
        assert p["after_frames_with_match"] >= p["before_frames_with_match"]
    summary = run["arms"]["default"]["summary"]
    assert summary["cross_season"]["frames"] == sum(r["cross_frames"] for r in rows)
    assert summary["merged"] == sum(r["merged"] for r in rows)
    assert summary["probes"]["frames"] == sum(p["before_frames_with_match"] for p in probes)
    assert set(data["mean"]["default"]) == set(bench_conditions.HEADLINE)
    printed = capsys.readouterr().out
    assert "alias cost" in printed and "minus default" in printed


def fake_nordland(root: Path, frames: int = 60) -> Path:
    """A frame-aligned summer/winter pair: one random scene per frame, winter brighter with
    a flat band, 64x32 grey PNGs named as Nordland's."""
    rng = np.random.default_rng(5)
    scene = np.cumsum(rng.normal(0, 1, (frames + 8, 32, 64)), axis=0)
    for season in ("summer", "winter"):
        (root / season).mkdir(parents=True)
        for k in range(frames):
            img = scene[k : k + 8].mean(axis=0)
            img = (img - img.min()) / (np.ptp(img) + 1e-9) * 200
            if season == "winter":
                img[20:] = 235
            grey = np.repeat(img.astype(np.uint8)[:, :, None], 3, axis=2)
            cv2.imwrite(str(root / season / f"images-{10 * (k + 1):05d}.png"), grey)
    return root


def test_nordland_cut_is_drives_of_segments_one_season_each(tmp_path: Path) -> None:
    root = fake_nordland(tmp_path / "nordland")
    world = condition_worlds.nordland_world(3, root, frames=60, segments=6, drives=5)
    assert len(world.drives) == 5
    for drive, about in zip(world.drives, world.about["drives"], strict=True):
        first, stop = about["segments"]
        assert 2 <= stop - first <= 4 and drive.season in ("summer", "winter")
        lo, hi = about["ride_frames"]
        assert len(drive.rows) == hi - lo and drive.rows.shape[1] == 1764
        assert 0.7 <= about["gamma"] <= 1.4 and 2 <= about["noise"] <= 6
    # Ground truth is the ride's frame index, +/- 1 frame, across drives too.
    a = world.drives[0]
    assert world.gt.correct(a.name, 0, a.name, 1) and not world.gt.correct(a.name, 0, a.name, 2)
    spans = [range(*d["ride_frames"]) for d in world.about["drives"]]
    pairs = [(i, j) for i in range(5) for j in range(i) if set(spans[i]) & set(spans[j])]
    assert pairs  # seed 3 cuts overlapping drives
    i, j = pairs[0]
    ride = max(spans[i][0], spans[j][0])
    qa, qb = ride - spans[i][0], ride - spans[j][0]
    name_i, name_j = world.drives[i].name, world.drives[j].name
    assert world.gt.correct(name_i, qa, name_j, qb) and not world.gt.correct(
        name_i, qa, name_j, qb + 2)


def test_nordland_stream_end_to_end(tmp_path: Path) -> None:
    root = fake_nordland(tmp_path / "nordland")
    out = tmp_path / "n.json"
    assert bench_conditions.main(["--world", "nordland", "--nordland", str(root), "--seeds", "1",
                                  "--frames", "60", "--segments", "6", "--drives", "4",
                                  "--json", str(out)]) == 0
    data: dict[str, Any] = json.loads(out.read_text())
    rows = data["seeds"][0]["arms"]["default"]["rows"]
    assert len(rows) == 3
    world = data["seeds"][0]["world"]
    assert world["segments"] == 6
    assert [p["season"] for p in world["probes"]] == ["summer", "winter"]
    assert [p["name"] for p in data["seeds"][0]["arms"]["default"]["probes"]] == [
        "p00-summer", "p01-winter"]
