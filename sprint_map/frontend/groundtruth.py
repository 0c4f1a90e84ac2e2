"""Ground truth for place recognition: is database frame *d* the same place as query frame *q*?

Two alignments, declared per data set (``dataset.json``) or passed as an override:

``"frame"``
    Traversals are frame-aligned (Nordland: the file with the same name, i.e. the same index, is
    the same place). ``q`` matches ``d`` iff ``|q - d| <= tolerance_frames``.
``"position"``
    Each traversal has per-frame positions (``positions.csv``). ``q`` matches ``d`` iff their
    planar distance is at most ``radius_m`` and, when ``heading_deg`` is set, their headings
    differ by at most ``heading_deg`` degrees (a street driven the other way looks different).

Frame numbers are indices into the traversals *as ingested*; with a ``stride`` they are mapped
back to original frames, so tolerances keep their meaning in the data set's own frame units.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from sprint_map.errors import ConfigError, InputError
from sprint_map.util import dataclass_dict

__all__ = ["ALIGNMENTS", "GroundTruth", "GroundTruthSpec"]

ALIGNMENTS = ("frame", "position")


@dataclass(frozen=True)
class GroundTruthSpec:
    """How a data set's traversals correspond (the content of ``dataset.json``).

    Parameters
    ----------
    alignment : {"frame", "position"}
        See the module docstring.
    tolerance_frames : int
        Frame alignment: largest index difference still counted as the same place.
    radius_m : float
        Position alignment: largest distance (metres) still counted as the same place.
    heading_deg : float, optional
        Position alignment: largest heading difference (degrees, 0-180); ``None`` ignores
        headings.
    """

    alignment: str
    tolerance_frames: int = 1
    radius_m: float = 10.0
    heading_deg: float | None = None

    def __post_init__(self) -> None:
        if self.alignment not in ALIGNMENTS:
            raise ValueError(f"alignment must be one of {', '.join(ALIGNMENTS)}")
        if not isinstance(self.tolerance_frames, int) or self.tolerance_frames < 0:
            raise ValueError("tolerance_frames must be a non-negative integer")
        if not self.radius_m >= 0:
            raise ValueError("radius_m must be >= 0")
        if self.heading_deg is not None and not 0 <= self.heading_deg <= 180:
            raise ValueError("heading_deg must be in [0, 180]")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GroundTruthSpec:
        """Build from a dict such as ``{"alignment": "frame", "tolerance_frames": 1}``.

        Raises
        ------
        ConfigError
            On an unknown key or an invalid value.
        """
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict (the ``dataset.json`` form)."""
        return dataclass_dict.to_dict(self)


class GroundTruth:
    """Decides whether retrieved database frames are correct for a query frame.

    Parameters
    ----------
    spec : GroundTruthSpec
        The alignment rule.
    positions : mapping of str to ndarray, optional
        Position alignment: per traversal name, the ``(n, 3 or 4)`` array of
        :func:`~sprint_map.frontend.positions.read_positions` (``frame, x, y[, heading_deg]``),
        one row per ingested frame. Looked up lazily, so it may be a lazy mapping.
    lengths : mapping of str to int or None, optional
        Frame alignment: frames per traversal (``None``: unknown, treated as unbounded). Used
        by :meth:`has_match` only.
    stride : int
        Ingest stride: ingested frame ``i`` is original frame ``i * stride`` (frame alignment
        only; positions already describe the ingested frames).

    Notes
    -----
    Position queries use one KD-tree per database traversal, built on first use:
    :meth:`has_match` costs O(log n + matches) per query frame.
    """

    def __init__(
        self,
        spec: GroundTruthSpec,
        positions: Mapping[str, np.ndarray] | None = None,
        lengths: Mapping[str, int | None] | None = None,
        stride: int = 1,
    ) -> None:
        if spec.alignment == "position" and positions is None:
            raise ConfigError("position alignment needs per-traversal positions")
        if stride < 1:
            raise ValueError("stride must be >= 1")
        self.spec = spec
        self.stride = stride
        self._positions = positions or {}
        self._lengths = lengths or {}
        self._trees: dict[str, tuple[cKDTree, np.ndarray]] = {}

    def correct(
        self, query: str, query_frames: ArrayLike, db: str, db_frames: ArrayLike
    ) -> np.ndarray:
        """Whether each database frame is the same place as its query frame.

        Parameters
        ----------
        query, db : str
            Traversal names.
        query_frames, db_frames : array_like of int
            Broadcast against each other, e.g. ``(Q, 1)`` query frames with ``(Q, K)``
            retrieved frames gives a ``(Q, K)`` answer.

        Returns
        -------
        ndarray of bool
        """
        q = np.asarray(query_frames, dtype=np.int64)
        d = np.asarray(db_frames, dtype=np.int64)
        if self.spec.alignment == "frame":
            near: np.ndarray = np.abs(q - d) * self.stride <= self.spec.tolerance_frames
            return near
        qp, dp = self._table(query), self._table(db)
        a, b = qp[q], dp[d]
        close: np.ndarray = (np.hypot(a[..., 1] - b[..., 1], a[..., 2] - b[..., 2])
                             <= self.spec.radius_m)
        if self.spec.heading_deg is None:
            return close
        out: np.ndarray = close & (_angle_between(a[..., 3], b[..., 3]) <= self.spec.heading_deg)
        return out

    def matches(self, query: str, query_frame: int, db: str) -> np.ndarray:
        """Indices of all database frames of ``db`` that are correct for ``query_frame``.

        Returns
        -------
        ndarray of int64, sorted
        """
        q = int(query_frame)
        if self.spec.alignment == "frame":
            reach = self.spec.tolerance_frames // self.stride
            high = q + reach + 1
            length = self._lengths.get(db)
            if length is not None:
                high = min(high, length)
            return np.arange(max(0, q - reach), max(0, high), dtype=np.int64)
        row = self._table(query)[q]
        if not np.isfinite(row[1:3]).all():  # a frame without a fix matches nothing
            return np.empty(0, dtype=np.int64)
        tree, placed = self._tree(db)
        candidates = np.sort(placed[np.asarray(
            tree.query_ball_point(row[1:3], self.spec.radius_m), dtype=np.int64)])
        if self.spec.heading_deg is None or len(candidates) == 0:
            return candidates
        headings = self._table(db)[candidates, 3]
        return candidates[_angle_between(headings, row[3]) <= self.spec.heading_deg]

    def has_match(self, query: str, query_frames: ArrayLike, db: str | Sequence[str]) -> np.ndarray:
        """Whether each query frame has at least one correct frame in the database traversal(s).

        Queries without one (a street never driven before) cannot be localised; evaluations
        usually report recall over the queries that have a match.

        Returns
        -------
        ndarray of bool, same shape as ``query_frames``
        """
        frames = np.asarray(query_frames, dtype=np.int64)
        names = [db] if isinstance(db, str) else list(db)
        out = np.zeros(frames.shape, dtype=bool)
        for index in np.ndindex(frames.shape):
            out[index] = any(len(self.matches(query, int(frames[index]), n)) for n in names)
        return out

    def _table(self, name: str) -> np.ndarray:
        try:
            table = self._positions[name]
        except KeyError:
            raise InputError(f"no positions for traversal {name!r}") from None
        if self.spec.heading_deg is not None and table.shape[1] < 4:
            raise InputError(
                f"traversal {name!r}: heading tolerance set but its positions have no heading_deg"
            )
        return table

    def _tree(self, name: str) -> tuple[cKDTree, np.ndarray]:
        """The KD-tree of ``name``'s frames with a fix, and those frames' indices."""
        found = self._trees.get(name)
        if found is None:
            xy = self._table(name)[:, 1:3]
            placed = np.flatnonzero(np.isfinite(xy).all(axis=1))
            found = self._trees[name] = (cKDTree(xy[placed]), placed)
        return found


def _angle_between(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Absolute difference of two headings in degrees, in [0, 180]."""
    diff = np.abs((np.asarray(a) - np.asarray(b)) % 360.0)
    out: np.ndarray = np.minimum(diff, 360.0 - diff)
    return out
