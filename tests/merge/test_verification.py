"""Geometric verification of merge candidates on thumbnails (sprint_map.merge.verification), and
what it changes in the merge: rendered city drives, thumbnails as ``ingest --thumbnails``
keeps them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.frontend.thumbnails import make_thumbnail
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap
from sprint_map.merge.rule import MergeRule, select_merges
from sprint_map.merge.verification import (
    SAMPLE_MIN_INLIERS,
    RunVerifier,
    inliers,
    local_features,
)
from sprint_map.synth import CityConfig, iter_city

#: A small city driven twice, by day then in snow, the second drive on the first one's streets
#: (seed 2: the merge rule's lookalike tests refuse runs of it that are right).
CITY = CityConfig(grid=(3, 3), revisit=1000.0, conditions=("day", "snow"))
SEED, FRAMES = 2, 150


@pytest.fixture(scope="module")
def drives():
    """The two drives: HoG rows, thumbnails and ground truth."""
    from sprint_map.synth.city import GroundTruth

    traversals = list(iter_city(2, FRAMES, seed=SEED, config=CITY, workers=2))
    spec = MapConfig.for_descriptor("hog").descriptor_spec()
    assert spec is not None
    rows = [spec.describe_batch(t.images) for t in traversals]
    thumbs = [[make_thumbnail(image) for image in t.images] for t in traversals]
    gt = GroundTruth(CITY.ground_truth_spec(),
                     positions={t.name: t.positions for t in traversals})
    return traversals, rows, thumbs, gt


def test_two_views_of_a_place_share_many_inliers_other_places_few(drives):
    _, _, thumbs, _ = drives
    day = [local_features(t) for t in thumbs[0]]
    assert all(len(f) > 100 for f in day[::30])
    near = [inliers(day[i], day[i + 1]) for i in range(10, 130, 20)]
    far = [inliers(day[i], day[i + 70]) for i in range(10, 70, 10)]
    assert min(near) > 45, near
    assert [inliers(day[i], day[i + 1]) for i in range(10, 130, 20)] == near  # deterministic
    assert max(far) < 35, far  # the default merge_verify_inliers
    assert inliers(day[0], local_features(b"\xff\xd8 broken \xff\xd9")) == 0


def _run(images, frames=range(60)):
    return [FrameDecision(f, 0, image, 0.9) for f, image in zip(frames, images, strict=True)]


@pytest.mark.parametrize(("case", "verified"), [
    ("right", range(0, 60)),
    ("wrong", ()),
    ("right then wrong", range(0, 31)),  # the right part keeps its stretch, ends on a sample
    ("map without thumbnails", ()),
])
def test_a_run_is_verified_stretch_by_stretch(drives, case, verified):
    _, _, thumbs, _ = drives
    day = thumbs[0]

    def map_thumbnail(seq_id, image_id):  # the map "holds" the day drive as sequence 0
        if case == "map without thumbnails":
            return None
        if case == "wrong" or (case == "right then wrong" and image_id >= 40):
            return day[(image_id + 75) % len(day)]  # another street, the images still advancing
        return day[image_id]

    decisions = _run(range(10, 70))
    query = [day[f + 10 + 1] for f in range(60)]  # the frame after the matched one: same place
    verifier = RunVerifier(query, map_thumbnail, min_inliers=35, min_run=20)
    got = verifier.verified(decisions, np.ones(60, dtype=bool), max_gap=3, max_rate=3.0)
    assert np.flatnonzero(got).tolist() == list(verified)
    assert verifier.samples == 13  # every 5th frame and the last


def test_something_static_in_view_verifies_nothing(drives):
    """A bonnet or an overlay seen in every frame matches everywhere: each sample is also
    checked against a map image CONTROL_OFFSET images away, and scores 0 when that control
    matches as well."""
    import cv2

    _, _, thumbs, _ = drives
    rng = np.random.default_rng(5)
    bonnet = cv2.resize(rng.integers(0, 255, (8, 32), dtype=np.uint8), (96, 24))

    def with_bonnet(jpeg):
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        image[-24:] = bonnet
        return cv2.imencode(".jpg", image)[1].tobytes()

    day = [with_bonnet(t) for t in thumbs[0]]
    elsewhere = [day[(f + 10 + 75) % len(day)] for f in range(60)]  # another street, same bonnet
    assert inliers(local_features(elsewhere[0]), local_features(day[10])) >= 35
    verifier = RunVerifier(elsewhere, lambda s, i: day[i], 35, 20)
    assert not verifier.verified(_run(range(10, 70)), np.ones(60, dtype=bool), 3, 3.0).any()
    # Conservative: the right run is not verified either (its controls match the bonnet too),
    # and merges as the rule alone would have it.
    right = RunVerifier([day[f + 11] for f in range(60)], lambda s, i: day[i], 35, 20)
    assert not right.verified(_run(range(10, 70)), np.ones(60, dtype=bool), 3, 3.0).any()
    plain = RunVerifier([thumbs[0][f + 11] for f in range(60)], lambda s, i: thumbs[0][i], 35, 20)
    assert plain.verified(_run(range(10, 70)), np.ones(60, dtype=bool), 3, 3.0).all()


def test_runs_the_rule_accepts_are_not_verified_again(drives):
    _, _, thumbs, _ = drives
    day = thumbs[0]
    verifier = RunVerifier([day[f + 11] for f in range(60)], lambda s, i: day[i], 35, 20)
    got = verifier.verified(_run(range(10, 70)), np.ones(60, dtype=bool), 3, 3.0,
                            skip=np.ones(60, dtype=bool))
    assert not got.any() and verifier.samples == 0


def test_a_sample_counts_by_the_median_of_it_and_its_neighbours(drives):
    """One weak sample inside a right run does not break its stretch."""
    _, _, thumbs, _ = drives
    day = thumbs[0]
    weak = 30  # the frame whose map image is another street

    def map_thumbnail(seq_id, image_id):
        return day[(image_id + 75) % len(day)] if image_id == 10 + weak else day[image_id]

    verifier = RunVerifier([day[f + 11] for f in range(60)], map_thumbnail, 35, 20)
    got = verifier.verified(_run(range(10, 70)), np.ones(60, dtype=bool), 3, 3.0)
    assert got.all()
    assert SAMPLE_MIN_INLIERS < 35


@pytest.mark.parametrize(("case", "denied"), [
    ("true revisit", ()),  # the drive's own images agree: it passed the place twice
    ("false revisit", range(60, 120)),  # the second pass is another street: it goes
    ("false revisit, map without thumbnails", range(0, 120)),  # nothing proves either pass
    ("false revisit, frames too small to look at", ()),  # Nordland's 64x32: no evidence
])
def test_a_revisit_the_drives_own_images_deny_keeps_only_verified_runs(drives, case, denied):
    """Two runs of a drive matched to the same map images (10..69) claim the drive passed
    that place twice; the drive's own frames at the shared images are matched to each other."""
    _, _, thumbs, _ = drives
    day = thumbs[0]
    first = [day[f + 10 + 1] for f in range(60)]  # the frame after the matched one
    second = first if case == "true revisit" else [day[(f + 10 + 75) % len(day)]
                                                   for f in range(60)]

    def map_thumbnail(seq_id, image_id):
        return None if "without" in case else day[image_id]

    if "small" in case:
        import cv2

        def small(jpeg):
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            return cv2.imencode(".jpg", cv2.resize(image, (64, 48)))[1].tobytes()

        first, second = [small(t) for t in first], [small(t) for t in second]
    decisions = _run([*range(10, 70), *range(10, 70)], frames=range(120))
    verifier = RunVerifier(first + second, map_thumbnail, min_inliers=35, min_run=20)
    got = verifier.contradicted(decisions, np.ones(120, dtype=bool), max_gap=3, max_rate=3.0)
    assert np.flatnonzero(got).tolist() == list(denied)
    # runs on different sequences, or on images they do not share, claim no revisit
    elsewhere = [*_run(range(10, 70)), *(FrameDecision(60 + f, 1, 10 + f, 0.9)
                                         for f in range(60))]
    assert not verifier.contradicted(elsewhere, np.ones(120, dtype=bool), 3, 3.0).any()
    later = _run([*range(10, 70), *range(80, 140)], frames=range(120))
    assert not verifier.contradicted(later, np.ones(120, dtype=bool), 3, 3.0).any()


def test_a_drive_that_contradicts_itself_does_not_merge_the_revisit(drives, tmp_path):
    """The snow drive's first 70 frames driven twice: the same descriptors twice, so the
    second pass is matched to the same day images as the first. With its own thumbnails it
    merges as before; with another street's thumbnails for the second pass (the drive's
    images say it was elsewhere) the second pass is not merged, and nothing is merged that
    the honest drive would not merge."""
    traversals, rows, thumbs, _ = drives
    day, _ = traversals
    twice = np.concatenate([rows[1][:70], rows[1][:70]])
    honest = thumbs[1][:70] * 2
    lying = thumbs[1][:70] + thumbs[1][75:145]
    merged = {}
    with SprintMap.create(tmp_path / "m", MapConfig.for_descriptor("hog")) as m:
        m.add_sequence(rows[0], name=day.name, thumbnails=thumbs[0])
        for label, images in (("honest", honest), ("lying", lying)):
            decisions, _ = m.localize(twice, smooth=True, thumbnails=images)
            merged[label] = m.service.select_merges(decisions)
    assert merged["honest"][:70].sum() >= 40 and merged["honest"][70:].sum() >= 40
    assert not merged["lying"][70:].any()
    assert (merged["honest"] | ~merged["lying"]).all()


def test_the_merge_rule_merges_verified_decisions_only_if_confirmed():
    # A run the contrast gate refuses (a lookalike as close as the match).
    ds = [FrameDecision(i, 0, i, 0.99, contrast=1.2) for i in range(30)]
    rule = MergeRule.permissive(threshold=0.5, window=3, min_run=20, max_contrast=0.95)
    assert not select_merges(ds, rule).any()
    verified = [dataclasses.replace(d, verified=True) for d in ds]
    assert select_merges(verified, rule).all()
    unconfirmed = [dataclasses.replace(d, confirmed=False) for d in verified]
    assert not select_merges(unconfirmed, rule).any()
    assert verified[0].to_dict()["verified"] is True and ds[0].to_dict()["verified"] is False


def test_verification_only_adds_merges_and_they_are_right(drives, tmp_path):
    """Ingest of the snow drive with and without thumbnails, on the same map: the thumbnails
    add merges (runs the lookalike tests refused), and every frame they add is right;
    ``localize(smooth=True)`` with the same thumbnails decides as ingest does."""
    traversals, rows, thumbs, gt = drives
    day, snow = traversals
    results = {}
    for use in (False, True):
        with SprintMap.create(tmp_path / f"m{use}", MapConfig.for_descriptor("hog")) as m:
            m.add_sequence(rows[0], name=day.name, thumbnails=thumbs[0])
            query_thumbs = thumbs[1] if use else None
            localized, _ = m.localize(rows[1], smooth=True, thumbnails=query_thumbs)
            results[use] = m.ingest(rows[1], name=snow.name, thumbnails=query_thumbs)
            assert localized == results[use].decisions
    without, with_ = results[False].merged, results[True].merged
    assert not any(d.verified for d in results[False].decisions)
    assert (with_ | ~without).all(), "verification took a merge away"
    added = np.flatnonzero(with_ & ~without)
    assert len(added) >= 10
    decisions = results[True].decisions
    assert all(decisions[f].verified for f in added)
    right = [bool(gt.correct(snow.name, int(f), day.name, decisions[f].image_id)) for f in added]
    assert all(right)


def test_no_verification_without_the_maps_thumbnails_or_when_off(drives, tmp_path):
    traversals, rows, thumbs, _ = drives
    configs = {"no map thumbnails": MapConfig.for_descriptor("hog"),
               "off": MapConfig.for_descriptor("hog").replace(merge_verify_inliers=0)}
    for label, config in configs.items():
        with SprintMap.create(tmp_path / label, config) as m:
            m.add_sequence(rows[0], name=traversals[0].name,
                           thumbnails=thumbs[0] if label == "off" else None)
            decisions, _ = m.localize(rows[1], smooth=True, thumbnails=thumbs[1])
            assert not any(d.verified for d in decisions), label


def test_verify_inliers_is_checked_and_old_configs_get_the_default():
    with pytest.raises(ValueError, match="verify_inliers"):
        MapConfig(dim=8, merge=MergeRule(verify_inliers=-1))
    stored = MapConfig(dim=8).to_dict()
    del stored["merge"]["verify_inliers"]  # a map written before the field existed
    assert MapConfig.from_dict(stored).merge.verify_inliers == 35
