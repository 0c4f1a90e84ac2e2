"""Parameters of the SPRINT hidden Markov model (see ``docs/architecture.md``, "The model")."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sprint_map import dataclass_dict


@dataclass(frozen=True)
class HMMConfig:
    """Frozen parameters of the place-recognition HMM.

    Parameters
    ----------
    k : int
        Neighbours retrieved per query frame.
    window : tuple of float
        Forward transition window ``w``: ``w[0]`` is the probability of staying on the same image,
        ``w[i]`` of moving ``i`` images ahead in the same sequence. Normalised on use.
    edge_weight : float
        Relative weight of following an inter-sequence edge versus staying in the own sequence.
    prune_threshold : float
        Components whose share of the belief falls below this leave the active set (paper: 1e-4).
    """

    k: int = 10
    window: tuple[float, ...] = (0.15, 0.35, 0.25, 0.15, 0.1)
    edge_weight: float = 1.0
    prune_threshold: float = 1e-4

    def __post_init__(self) -> None:
        if self.k < 1:
            raise ValueError("k must be >= 1")
        if not self.window or any(w < 0 for w in self.window) or sum(self.window) <= 0:
            raise ValueError("window must be non-empty, non-negative and not all zero")
        if self.edge_weight < 0:
            raise ValueError("edge_weight must be >= 0")
        if not 0 <= self.prune_threshold < 1:
            raise ValueError("prune_threshold must be in [0, 1)")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HMMConfig:
        """Build from a dict (as stored in the map's meta record)."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return dataclass_dict.to_dict(self)
