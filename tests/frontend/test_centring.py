"""Drive centring (sprint_map.frontend.centring): causal, batch-independent, validated first."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.errors import InvalidDescriptorError
from sprint_map.frontend.centring import Centring, CentringStats, DriveCentring, centre_batches


def unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture
def drive() -> np.ndarray:
    return unit(np.random.default_rng(3).standard_normal((120, 16)))


def test_rows_do_not_depend_on_how_the_drive_is_batched(drive):
    whole = DriveCentring(Centring("drive"), 16).apply(drive)
    for size in (1, 7, 64):
        c = DriveCentring(Centring("drive"), 16)
        parts = np.vstack([c.apply(drive[i:i + size]) for i in range(0, len(drive), size)])
        assert parts.tobytes() == whole.tobytes()
    streamed = np.vstack(list(centre_batches(DriveCentring(Centring("drive"), 16),
                                             iter(np.array_split(drive, 5)))))
    assert streamed.tobytes() == whole.tobytes()


def test_a_frame_is_centred_on_the_frames_before_it_only(drive):
    whole = DriveCentring(Centring("drive"), 16).apply(drive)
    prefix = DriveCentring(Centring("drive"), 16).apply(drive[:40])
    assert prefix.tobytes() == whole[:40].tobytes()  # later frames change nothing before them
    # the rule: minus the running mean with one zero prior frame, renormalised
    t = 10
    mean = drive[: t + 1].astype(np.float64).sum(0) / (t + 2)
    want = (drive[t] - mean) / np.linalg.norm(drive[t] - mean)
    np.testing.assert_allclose(whole[t], want, atol=1e-6)
    assert np.allclose(np.linalg.norm(whole, axis=1), 1, atol=1e-5)


def test_a_shared_condition_is_removed():
    rng = np.random.default_rng(0)
    places = rng.standard_normal((50, 32))
    season = 4 * rng.standard_normal(32)
    summer, winter = unit(places + 0.2 * rng.standard_normal((50, 32))), unit(places + season)
    raw_nn = np.argmin(((winter[:, None] - summer[None]) ** 2).sum(-1), axis=1)
    s, w = (DriveCentring(Centring("drive"), 32).apply(x) for x in (summer, winter))
    nn = np.argmin(((w[:, None] - s[None]) ** 2).sum(-1), axis=1)
    assert (nn == np.arange(50)).mean() > (raw_nn == np.arange(50)).mean() + 0.2


def test_mode_none_keeps_rows_and_still_counts(drive):
    c = DriveCentring(Centring("none"), 16)
    assert c.apply(drive).tobytes() == drive.tobytes()
    assert c.stats.frames == 120
    np.testing.assert_allclose(c.stats.mean, drive.mean(0), atol=1e-6)


def test_preview_changes_nothing_and_bad_rows_are_refused_first(drive):
    c = DriveCentring(Centring("drive"), 16)
    c.apply(drive[:5])
    before = c.preview(drive[5:6])
    assert c.frames == 5 and c.preview(drive[5:6]).tobytes() == before.tobytes()
    bad = drive[5:8].copy()
    bad[1, 3] = np.nan
    with pytest.raises(InvalidDescriptorError, match="frame 6"):
        c.apply(bad)
    assert c.frames == 5  # refused: the state is as before
    c.advance(drive[5:6])
    assert c.apply(drive[6:7]).tobytes() == DriveCentring(Centring("drive"), 16).apply(
        drive[:7])[6].reshape(1, -1).tobytes()


def test_prior_weighs_the_first_frames_and_fresh_repeats_it(drive):
    prior = CentringStats(500, drive.mean(0) + 0.5)
    c = DriveCentring(Centring("drive", prior_frames=20), 16, prior)
    rows = c.apply(drive[:3])
    mean0 = (20 * prior.mean.astype(np.float64) + drive[0]) / 21
    np.testing.assert_allclose(rows[0], (drive[0] - mean0) / np.linalg.norm(drive[0] - mean0),
                               atol=1e-6)
    assert c.fresh().apply(drive[:3]).tobytes() == rows.tobytes()
    assert DriveCentring(Centring("drive", prior_frames=0), 16, prior).apply(drive[:3]).tobytes() == \
        DriveCentring(Centring("drive"), 16).apply(drive[:3]).tobytes()


def test_pool_is_frame_weighted():
    a = CentringStats(10, np.ones(4, np.float32))
    b = CentringStats(30, np.zeros(4, np.float32))
    pooled = CentringStats.pool([a, b])
    assert pooled is not None and pooled.frames == 40
    np.testing.assert_allclose(pooled.mean, 0.25)
    assert CentringStats.pool([]) is None


def test_config_is_checked():
    with pytest.raises(ValueError, match="centring mode"):
        Centring("season")
    with pytest.raises(ValueError, match="prior_frames"):
        Centring(prior_frames=-1)
