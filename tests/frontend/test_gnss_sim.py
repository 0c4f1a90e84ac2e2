"""The simulated GNSS receiver (sprint_map/frontend/gnss.py): drift, dropouts, multipath."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.frontend.gnss import GnssModel, simulate_fixes


def truth(n: int) -> np.ndarray:
    return np.c_[np.arange(n) * 5.0, np.zeros(n), np.full(n, 90.0)]  # heading ignored


def test_seeded_and_shaped():
    a = simulate_fixes(truth(500), GnssModel(), 3)
    b = simulate_fixes(truth(500), GnssModel(), 3)
    c = simulate_fixes(truth(500), GnssModel(), 4)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (500, 3) and not np.array_equal(a, c, equal_nan=True)
    fixed = ~np.isnan(a[:, 0])
    assert (a[fixed, 2] == 10.0).all() and np.isnan(a[~fixed]).all()


@pytest.mark.parametrize("sigma", [3.0, 10.0, 30.0])
def test_drift_is_time_correlated_with_the_given_sigma(sigma):
    model = GnssModel(sigma=sigma, dropout_rate=0.0, jump_rate=0.0, tau_frames=60.0)
    errs = np.concatenate([simulate_fixes(truth(3000), model, s)[:, :2] - truth(3000)[:, :2]
                           for s in range(8)])
    assert np.std(errs) == pytest.approx(sigma, rel=0.15)
    e = simulate_fixes(truth(3000), model, 99)[:, 0] - truth(3000)[:, 0]
    lag1 = np.corrcoef(e[1:], e[:-1])[0, 1]
    assert lag1 > 0.95  # a random walk, not white noise
    assert np.std(np.diff(e)) < 0.3 * sigma


def test_dropouts_are_runs_of_frames():
    model = GnssModel(dropout_rate=1 / 200, dropout_frames=(10, 60), jump_rate=0.0)
    out = simulate_fixes(truth(5000), model, 1)
    missing = np.isnan(out[:, 0]).astype(int)
    starts = np.flatnonzero(np.diff(np.r_[0, missing]) == 1)
    ends = np.flatnonzero(np.diff(np.r_[missing, 0]) == -1)
    lengths = ends - starts + 1
    assert len(lengths) >= 10 and lengths.min() >= 10


def test_multipath_jumps_are_30_to_80_m_and_rare():
    clean = GnssModel(sigma=2.0, dropout_rate=0.0, jump_rate=0.0)
    jumpy = GnssModel(sigma=2.0, dropout_rate=0.0, jump_rate=1 / 100, jump_frames=(1, 5))
    a = simulate_fixes(truth(5000), clean, 7)
    b = simulate_fixes(truth(5000), jumpy, 7)
    shift = np.hypot(*(b[:, :2] - a[:, :2]).T)  # the same drift, the jumps on top
    jumped = shift > 0
    assert 0.01 < jumped.mean() < 0.1
    assert shift[jumped].min() >= 30 - 1e-9 and shift[jumped].max() <= 80 + 1e-9


@pytest.mark.parametrize("field", [{"sigma": 0.0}, {"sigma": float("nan")},
                                   {"tau_frames": 0.0}, {"dropout_rate": 1.5},
                                   {"jump_rate": -0.1}])
def test_model_refuses_bad_parameters(field):
    with pytest.raises(ValueError):
        GnssModel(**field)
