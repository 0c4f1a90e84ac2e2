"""A GNSS receiver simulated from ground-truth positions: fixes as noisy as real ones.

Real fixes are not ground truth plus white noise. Per frame ``t`` of a drive whose true
position is ``p_t`` (``docs/frontend.md``, "Simulated GNSS"):

* **time-correlated error**: ``e_t = a e_{t-1} + sqrt(1 - a^2) sigma w_t`` per axis (a first-
  order Gauss-Markov process, ``w_t`` standard normal, ``a = exp(-1 / tau_frames)``): each
  axis has standard deviation ``sigma`` at every frame, and the error drifts slowly (over
  ``tau_frames``) instead of jumping from frame to frame, as the atmosphere and the satellite
  geometry make it;
* **dropouts** (tunnels, urban canyons): a run of frames without a fix starts at each frame with
  probability ``dropout_rate`` and lasts ``dropout_frames`` frames (uniform);
* **multipath**: with probability ``jump_rate`` per frame a reflected signal shifts the fix by
  ``jump_m`` metres (uniform) in a random direction for ``jump_frames`` frames (uniform),
  on top of the drift.

The reported accuracy ``sigma_m`` of every fix is ``sigma``: a receiver does not know that a
fix is a multipath outlier. Everything is drawn from one seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sprint_map.util.arrays import Float64Array

__all__ = ["GnssModel", "simulate_fixes"]


@dataclass(frozen=True)
class GnssModel:
    """The simulated receiver (module notes); ``sigma`` in metres, per axis."""

    sigma: float = 10.0
    tau_frames: float = 60.0
    dropout_rate: float = 1 / 400
    dropout_frames: tuple[int, int] = (10, 60)
    jump_rate: float = 1 / 300
    jump_m: tuple[float, float] = (30.0, 80.0)
    jump_frames: tuple[int, int] = (1, 8)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError("sigma must be a finite number > 0")
        if not self.tau_frames > 0:
            raise ValueError("tau_frames must be > 0")
        for name in ("dropout_rate", "jump_rate"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1]")

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def simulate_fixes(truth: Any, model: GnssModel, seed: int | np.random.SeedSequence
                   ) -> Float64Array:
    """Fixes of a drive whose true positions are ``truth`` (``(n, 2+)``: ``x, y`` metres).

    Returns
    -------
    ndarray (n, 3)
        ``x, y, sigma_m`` per frame; a row of NaN for a frame without a fix.

    Notes
    -----
    O(n), one pass.
    """
    xy = np.asarray(truth, dtype=np.float64)[:, :2]
    n = len(xy)
    rng = np.random.default_rng(seed)
    a = math.exp(-1.0 / model.tau_frames)
    drive = math.sqrt(1.0 - a * a) * model.sigma
    noise = rng.normal(size=(n, 2))
    err = np.empty((n, 2))
    e = rng.normal(size=2) * model.sigma  # the process starts in its stationary state
    for t in range(n):
        e = a * e + drive * noise[t]
        err[t] = e
    fixed = np.ones(n, dtype=bool)
    jump = np.zeros((n, 2))
    for t in np.flatnonzero(rng.random(n) < model.dropout_rate).tolist():
        fixed[t:t + int(rng.integers(model.dropout_frames[0], model.dropout_frames[1] + 1))] = False
    for t in np.flatnonzero(rng.random(n) < model.jump_rate).tolist():
        length = int(rng.integers(model.jump_frames[0], model.jump_frames[1] + 1))
        angle = rng.uniform(0, 2 * math.pi)
        size = rng.uniform(*model.jump_m)
        jump[t:t + length] = size * math.cos(angle), size * math.sin(angle)
    out = np.full((n, 3), np.nan)
    out[fixed, :2] = (xy + err + jump)[fixed]
    out[fixed, 2] = model.sigma
    return out
