"""The merge rule (sprint_map.merge.rule) on hand-made drives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sprint_map.localize.localizer import FrameDecision
from sprint_map.merge.rule import MergeRule, run_lengths, select_merges, teleports
from sprint_map.merge.smoothing import local_quantiles


def along(n: int, seq: int = 0, start: int = 10, step: int = 1, prob: float = 0.9,
          first_frame: int = 0, distance: float = 0.1) -> list[FrameDecision]:
    return [FrameDecision(first_frame + i, seq, start + step * i, prob, distance=distance)
            for i in range(n)]


def test_runs_follow_one_drive_across_small_gaps_and_outliers():
    seq = np.array([0, 0, -1, 0, 1, 0, 0, 2, 2])
    img = np.array([5, 6, -1, 8, 90, 10, 11, 3, 4])
    # 0,1,3,5,6 are one run (the no-match and the outlier on drive 1 do not break it)
    assert run_lengths(seq, img, max_gap=2, max_rate=3.0).tolist() == [5, 5, 0, 5, 1, 5, 5, 2, 2]
    # a gap longer than max_gap starts a new run
    assert run_lengths(seq, img, max_gap=1, max_rate=3.0).tolist() == [2, 2, 0, 1, 1, 2, 2, 2, 2]


def test_a_backward_or_too_fast_step_breaks_a_run():
    assert run_lengths(np.zeros(4, int), np.array([10, 9, 8, 7]), 3, 3.0).tolist() == [1] * 4
    assert run_lengths(np.zeros(3, int), np.array([10, 20, 30]), 3, 3.0).tolist() == [1] * 3


def test_a_stalled_stretch_of_a_run_is_not_merged():
    # 30 frames that advance, then 30 stuck on one image while the drive goes on.
    img = np.r_[np.arange(30), np.full(30, 29)]
    lengths = run_lengths(np.zeros(60, int), img, 3, 3.0, min_advance=0.3)
    assert (lengths[:15] == 60).all() and (lengths[-15:] == 0).all()
    assert (run_lengths(np.zeros(60, int), img, 3, 3.0) == 60).all()


def test_min_run_rejects_short_lookalike_stretches():
    drive = along(30) + along(8, seq=1, start=200, first_frame=30) + along(30, first_frame=38,
                                                                          start=60)
    merged = select_merges(drive, MergeRule.permissive(window=3, min_run=20))
    assert merged[:30].all() and not merged[30:38].any() and merged[38:].all()


def test_distance_gate_is_calibrated_on_the_drive():
    near = along(200, distance=0.1)
    far = along(20, seq=1, start=300, first_frame=200, distance=0.3)  # under 10 % of the drive
    rule = MergeRule.permissive(window=3, min_run=20, dist_quantile=0.9)
    merged = select_merges(near + far, rule)
    assert merged[:200].all() and not merged[200:].any()
    # the same distances, all scaled (another light or weather): the same verdict
    scaled = [FrameDecision(d.frame, d.seq_id, d.image_id, d.prob, distance=d.distance * 3)
              for d in near + far]
    assert (select_merges(scaled, rule) == merged).all()
    # without the gate both stretches are long enough
    assert select_merges(near + far, MergeRule.permissive(window=3, min_run=20)).all()


def test_novel_and_unconfident_decisions_are_never_merged():
    drive = along(30)
    drive[5] = FrameDecision(5, 0, 15, 0.9, novel_prob=0.6)
    drive[6] = FrameDecision(6, 0, 16, 0.2)
    merged = select_merges(drive, MergeRule.permissive(threshold=0.5, max_novel=0.5, window=3, min_run=20))
    assert not merged[5] and not merged[6] and merged[:5].all() and merged[7:].all()


def test_unconfirmed_decisions_are_never_merged():
    drive = along(30)
    drive[5] = FrameDecision(5, 0, 15, 0.9, confirmed=False)  # a deeper pass's answer only
    merged = select_merges(drive, MergeRule.permissive(threshold=0.5, window=3, min_run=20))
    assert not merged[5] and merged[:5].all() and merged[6:].all()


@pytest.mark.parametrize("window", [0, 5])
def test_local_quantiles(window):
    values = np.r_[np.full(50, 1.0), np.full(50, 3.0)]
    mask = np.ones(100, bool)
    out = local_quantiles(values, mask, 0.5, window, 3)
    if window:
        assert out[0] == 1.0 and out[-1] == 3.0
    else:
        assert (out == 2.0).all()
    mask[:] = False
    mask[60:] = True  # too few accepted frames near the start: the whole drive's
    out = local_quantiles(values, mask, 0.5, 5, 3)
    assert out[0] == 3.0 and math.isfinite(out[0])


def with_contrast(drive: list[FrameDecision], contrast: float | list[float]
                  ) -> list[FrameDecision]:
    values = contrast if isinstance(contrast, list) else [contrast] * len(drive)
    return [FrameDecision(d.frame, d.seq_id, d.image_id, d.prob, distance=d.distance,
                          contrast=c) for d, c in zip(drive, values, strict=True)]


def test_a_run_that_does_not_stand_out_from_the_map_is_not_merged():
    # A real street (the matched place is the closest thing in the map: contrast 0.7) and a
    # lookalike stretch as long and as consistent, along which something elsewhere in the map
    # is as close (contrast 1.05).
    drive = with_contrast(along(30), 0.7) + with_contrast(
        along(30, seq=1, start=200, first_frame=30), 1.05)
    rule = MergeRule.permissive(window=3, min_run=20, max_contrast=0.95)
    merged = select_merges(drive, rule)
    assert merged[:30].all() and not merged[30:].any()
    assert select_merges(drive, MergeRule.permissive(window=3, min_run=20)).all()  # gate off


def test_the_contrast_gate_reads_the_runs_median():
    # a few frames of a true run whose place had no hit (inf) or a rival (1.2) do not sink it;
    # a lookalike run with a few distinct frames is still rejected
    good = [0.6] * 24 + [math.inf] * 3 + [1.2] * 3
    bad = [1.1] * 20 + [0.5] * 10
    drive = with_contrast(along(30), good) + with_contrast(
        along(30, seq=1, start=200, first_frame=30), bad)
    merged = select_merges(drive, MergeRule.permissive(window=3, min_run=20, max_contrast=0.95))
    assert merged[:30].all() and not merged[30:].any()


def test_decisions_without_contrast_are_not_gated():
    # causal decisions (NaN contrast) pass; NaN frames are left out of a run's median
    drive = along(30)
    assert select_merges(drive, MergeRule.permissive(window=3, min_run=20, max_contrast=0.5)).all()
    mixed = with_contrast(along(30), [math.nan] * 25 + [2.0] * 5)
    assert not select_merges(mixed, MergeRule.permissive(window=3, min_run=20, max_contrast=0.95)).any()


def test_a_drive_cannot_come_back_to_a_stretch_it_has_just_left():
    # City-novel's overcast drive (seed 2): a block matched right (images 119-151), then the
    # next block north, a copy of it, matched to the same images from the next frame on.
    # Both runs pass every other test; at most one is right and neither is merged.
    first = along(50, start=119, step=1)
    copy = along(43, start=128, first_frame=50)
    verified = [FrameDecision(d.frame, d.seq_id, d.image_id, d.prob, verified=True)
                for d in first + copy]
    rule = MergeRule.permissive(window=3, min_run=20)
    for drive in (first + copy, verified):
        assert not select_merges(drive, rule).any()
    # the same two passes a loop apart (120 frames elsewhere): a true revisit, both merged
    loop = [FrameDecision(50 + i, 1, 500 + i, 0.9) for i in range(120)]
    later = along(43, start=128, first_frame=170)
    assert select_merges(first + loop + later, rule).all()


def test_only_the_images_both_runs_claim_are_refused():
    # a long right run, then a lookalike of its last 20 images at once: the run keeps the 80
    # frames nothing contests; the lookalike, all contested, goes
    drive = along(100, start=0) + along(20, start=80, first_frame=100)
    merged = select_merges(drive, MergeRule.permissive(window=3, min_run=20))
    assert merged[:80].all() and not merged[80:].any()
    # what is left must still be a run of min_run frames
    merged = select_merges(along(30, start=0) + along(20, start=15, first_frame=30),
                           MergeRule.permissive(window=3, min_run=20))
    assert not merged.any()


@pytest.mark.parametrize("back", [1, 3, 9])
def test_a_run_that_stalls_and_restarts_a_few_images_back_is_kept(back):
    drive = along(30) + along(30, start=39 - back, first_frame=30)
    assert select_merges(drive, MergeRule.permissive(window=3, min_run=20)).all()


def test_runs_on_images_the_other_run_never_saw_are_no_teleport():
    # the map drive looped: its images 233-264 and 148-203 are neighbouring streets
    drive = along(40, start=233) + along(40, start=148, first_frame=40)
    assert select_merges(drive, MergeRule.permissive(window=3, min_run=20)).all()


def test_a_run_that_skips_over_the_images_of_another_is_no_teleport():
    # the first run steps 10 images at a 3-frame gap (19 -> 29), the second, later, holds
    # only images 21-27: the runs share that range of images but no frame of the first lies
    # on it (a latent lifelong drive crashed here once)
    gap = [FrameDecision(20 + i, None, None, 0.0) for i in range(2)]
    first = along(20, start=0) + gap + along(18, start=29, first_frame=22)
    off = [FrameDecision(40 + i, None, None, 0.0) for i in range(20)]
    second = along(7, start=21, first_frame=60)
    drive = first + off + second
    assert select_merges(drive, MergeRule.permissive(window=3)).sum() == len(first) - 2 + 7
    seq = np.array([-1 if d.seq_id is None else d.seq_id for d in drive])
    img = np.array([-1 if d.image_id is None else d.image_id for d in drive])
    assert not teleports(seq, img, 3, 3.0).any()
