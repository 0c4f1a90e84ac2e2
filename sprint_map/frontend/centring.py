"""Drive centring: what makes a map answer by place, not by condition.

A whole-image descriptor carries the drive's condition (season, light, exposure, the camera's
noise) as a component shared by all of its frames. Once the map holds that condition anywhere,
every query under it is pulled there: a winter query goes to winter drives of other places
before it goes to the summer drive of its own place. Centring removes the shared component:
each frame's descriptor has its drive's running mean subtracted, and is renormalised.

**The rule** (the same for a drive being stored and a query being answered, so both sides of
every distance are alike): frame ``t`` of a drive, descriptor ``x_t``, becomes

    c_t = (x_t - m_t) / ||x_t - m_t||,   m_t = (w p + x_0 + ... + x_t) / (w + t + 1)

``m_t`` is the mean of the frames seen so far and of a prior ``p`` worth ``w`` frames: the
map's mean condition (the frame-weighted mean of the drives it stores, from their
statistics) worth ``prior_frames`` frames, so that the first frames of a drive are centred on
something better than themselves; on an empty map (or with ``prior_frames=0``) one zero
frame (the first frame is then its own direction, not the zero vector). A frame equal to its
mean stays the zero vector. It is causal: a vehicle's answer for frame ``t`` never waits for
later frames, and the rows a drive stores are the rows it was localised with. Its state is the running sum and the
count (O(dim) memory per drive, whatever its length); :class:`CentringStats` is what the map
stores with each drive (its frames and its mean: the drive's condition).

``mode="none"`` (the default) keeps descriptors as they are, and a map created before
centring existed reads its config that way. ``drive`` is opt-in (``init --centring drive``):
on generated worlds with seasons it removes most of the alias cost and its wrong merges, but
on the Nordland pair it costs merge precision (``docs/decisions.md``, "Drive centring, opt-in").

Examples
--------
>>> import numpy as np
>>> centring = DriveCentring(Centring("drive"), dim=2)
>>> rows = centring.apply(np.array([[1.0, 0.0], [0.0, 1.0]], np.float32))
>>> rows.astype(float).round(3).tolist()
[[1.0, 0.0], [-0.447, 0.894]]
>>> centring.stats.frames, centring.stats.mean.tolist()
(2, [0.5, 0.5])
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Descriptors
from sprint_map.util.validation import validate_descriptors

__all__ = ["CENTRING_MODES", "Centring", "CentringStats", "DriveCentring", "centre_batches"]

#: ``none``: descriptors as given (the default); ``drive``: centred on the drive's running mean.
CENTRING_MODES = ("none", "drive")

# a centred vector shorter than this is left as the zero vector (a frame equal to its mean)
_ZERO_NORM = 1e-12


@dataclass(frozen=True)
class Centring:
    """How descriptors enter the map's space (``MapConfig.centring``); see the module
    docstring. ValueError for an unknown ``mode``.

    Parameters
    ----------
    mode : {"none", "drive"}
        ``drive`` centres each frame on its drive's running mean; ``none`` (the default, and
        every map made before centring) keeps descriptors as they are.
    prior_frames : int
        How many frames the map's mean condition weighs in a drive's running mean (0: none).
    """

    mode: str = "none"
    prior_frames: int = 20

    def __post_init__(self) -> None:
        if self.mode not in CENTRING_MODES:
            raise ValueError(f"centring mode must be one of {', '.join(CENTRING_MODES)}, "
                             f"not {self.mode!r}")
        if not isinstance(self.prior_frames, int) or self.prior_frames < 0:
            raise ValueError("centring prior_frames must be a non-negative integer")

    @property
    def enabled(self) -> bool:
        return self.mode != "none"


@dataclass(frozen=True)
class CentringStats:
    """A drive's statistics as the map stores them: its ``frames`` and the ``mean`` of its
    descriptors as given (float32, ``dim``): the drive's condition."""

    frames: int
    mean: np.ndarray

    @staticmethod
    def pool(stats: Iterable[CentringStats]) -> CentringStats | None:
        """The frame-weighted mean of several drives' statistics (None for none). O(n dim)."""
        total = 0
        acc: np.ndarray | None = None
        for s in stats:
            part = s.mean.astype(np.float64) * s.frames
            acc = part if acc is None else acc + part
            total += s.frames
        if acc is None or not total:
            return None
        return CentringStats(total, (acc / total).astype(np.float32))


class DriveCentring:
    """The running state of one drive's centring: :meth:`apply` each batch in drive order.

    Parameters
    ----------
    config : Centring
        The map's centring.
    dim : int
        The map's descriptor dimension.
    prior : CentringStats, optional
        The map's mean condition (:meth:`CentringStats.pool` of its drives' statistics).

    Notes
    -----
    O(n * dim) per batch of n rows; O(dim) state. Not thread-safe: one drive, one caller.
    """

    def __init__(self, config: Centring, dim: int, prior: CentringStats | None = None) -> None:
        self.config = config
        self.dim = dim
        self._sum = np.zeros(dim, np.float64)
        self._frames = 0
        #: the prior it was made with (:meth:`fresh` makes another drive with it)
        self.prior = prior
        #: the prior's weight (frames) and sum (a zero frame when there is none)
        self._w0 = 1.0
        self._sum0 = np.zeros(dim, np.float64)
        if prior is not None and prior.frames and config.prior_frames:
            self._w0 = float(config.prior_frames)
            self._sum0 = prior.mean.astype(np.float64) * config.prior_frames

    def fresh(self) -> DriveCentring:
        """A new drive's centring with this one's config and prior: the same frames give the
        very same rows (a drive centred again at its commit)."""
        return DriveCentring(self.config, self.dim, self.prior)

    @property
    def frames(self) -> int:
        """Frames centred so far."""
        return self._frames

    @property
    def stats(self) -> CentringStats:
        """The drive's statistics so far (what its commit stores)."""
        mean = self._sum / max(self._frames, 1)
        return CentringStats(self._frames, mean.astype(np.float32))

    def _centre(self, rows: Descriptors) -> tuple[Descriptors, Descriptors, np.ndarray]:
        """``(validated rows, centred rows, running sum after them)``. The sums are added in
        frame order one by one and every row is centred by the same operations, so a drive
        centred in batches of any size (one frame, as a vehicle streams) gives the very same
        rows."""
        if (isinstance(rows, np.ndarray) and rows.dtype == np.float32 and rows.ndim == 2
                and rows.shape[1] == self.dim and len(rows) and np.isfinite(rows).all()):
            arr = rows  # valid as it is (the check validate_descriptors would make)
        else:
            arr = validate_descriptors(rows, self.dim, self._frames)
        if len(arr) == 1:  # a streamed frame: the same sums and operations without the scans
            total = self._sum + arr[0]
            if not self.config.enabled:
                return arr, arr, total
            one = arr[0] - (self._sum0 + total) / (self._frames + self._w0 + 1)
            norm = np.sqrt(np.add.reduce(one * one))
            if norm > _ZERO_NORM:
                return arr, (one / norm).astype(np.float32)[None, :], total
            return arr, np.zeros((1, self.dim), np.float32), total
        else:
            sums = np.cumsum(np.vstack([self._sum[None, :], arr.astype(np.float64)]), axis=0)
            total = sums[-1]
            if not self.config.enabled:
                return arr, arr, total
            counts = self._frames + self._w0 + 1 + np.arange(len(arr), dtype=np.float64)
            centred = arr - (self._sum0 + sums[1:]) / counts[:, None]
        norms = np.sqrt(np.add.reduce(centred * centred, axis=1))[:, None]
        out = np.divide(centred, norms, out=np.zeros_like(centred), where=norms > _ZERO_NORM)
        return arr, out.astype(np.float32), total

    def pending(self, rows: Descriptors) -> tuple[Descriptors, Callable[[], None]]:
        """``rows`` centred as :meth:`apply` would, and a call that then takes them as the
        drive's next frames (as :meth:`advance`, without centring them twice): a caller that
        may still fail between the two (a refused frame changes nothing)."""
        arr, out, total = self._centre(rows)

        def take() -> None:
            self._sum = total
            self._frames += len(arr)

        return out, take

    def preview(self, rows: Descriptors) -> Descriptors:
        """``rows`` (the drive's next frames) as :meth:`apply` would give them, without
        advancing the state: a caller that may still refuse the frames (the service) calls
        :meth:`advance` only once they are kept."""
        return self._centre(rows)[1]

    def advance(self, rows: Descriptors) -> None:
        """Take ``rows`` (as given to :meth:`preview`) as the drive's next frames."""
        arr, _, total = self._centre(rows)
        self._sum = total
        self._frames += len(arr)

    def apply(self, rows: Descriptors) -> Descriptors:
        """The drive's next frames, centred (:meth:`preview`, then :meth:`advance`).

        Raises
        ------
        DescriptorShapeError, InvalidDescriptorError
            ``rows`` not ``(n, dim)``, or not finite: checked before anything is computed.
        """
        arr, out, total = self._centre(rows)
        self._sum = total
        self._frames += len(arr)
        return out

    def apply_all(self, rows: Descriptors) -> Descriptors:
        """A whole drive from its first frame (:meth:`apply` on a fresh state); InputError if
        frames were centred already."""
        if self._frames:
            raise InputError("apply_all centres a whole drive: this one has frames already")
        return self.apply(rows)


def centre_batches(centring: DriveCentring, descriptors: Any) -> Any:
    """A drive's ``descriptors`` (an ``(N, dim)`` array, or an iterable of batches, streamed)
    centred by ``centring`` in drive order: an array for an array, else a generator."""
    if isinstance(descriptors, np.ndarray | list):
        return centring.apply(np.asarray(descriptors))
    return (centring.apply(batch) for batch in descriptors)
