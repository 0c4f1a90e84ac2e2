"""The naive baseline: the same HMM over every vertex of the map with one sparse matrix.

:class:`FullGraphFilter` runs exactly the model of :class:`~sprint_map.hmm.SprintFilter`
(same observation model, same transition, same decision rules) but keeps a dense belief over the
whole map and propagates it with a scipy CSR matrix, as the paper's "full graph" does. It never
prunes. The tests use it as the reference (with pruning disabled SPRINT must equal it to
rounding) and ``tools/bench_fig4.py`` as the baseline.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import CANDIDATE_FLOOR, BeliefView, Decision, decide
from sprint_map.hmm.graph import ComponentGraph, MemoryGraphSource
from sprint_map.hmm.observation import ObservationModel
from sprint_map.hmm.transition import FLUSH_BELOW, FLUSH_EVERY, full_transition_matrix

__all__ = ["FullGraphFilter"]

_I64 = np.int64


class FullGraphFilter:
    """The place-recognition HMM over all vertices of a map (reference and baseline).

    Parameters
    ----------
    config : HMMConfig
        Model parameters (``prune_threshold`` and ``cache_budget_bytes`` are not used).
    source_or_components : MemoryGraphSource or iterable of ComponentGraph
        The whole map: a source that can list all its components (``all_components()``), or
        the components themselves (their vertex ranges must not overlap).

    Notes
    -----
    A step costs O(nnz(A)) = O(W (n + E)) for the matrix-vector product plus O(n) for the
    normalisation, whatever the hits; :meth:`decide` adds an O(n) ``argpartition``. Memory is
    O(W (n + E)).
    """

    def __init__(self, config: HMMConfig,
                 source_or_components: MemoryGraphSource | Iterable[ComponentGraph]) -> None:
        if not isinstance(config, HMMConfig):
            raise ValueError("config must be an HMMConfig")
        if isinstance(source_or_components, MemoryGraphSource):
            graphs = source_or_components.all_components()
        else:
            graphs = list(source_or_components)
        if not graphs or not all(isinstance(g, ComponentGraph) for g in graphs):
            raise ValueError("need at least one ComponentGraph")
        self.config = config
        self.graphs = graphs
        sizes = self._sizes = np.array([g.n_vertices for g in graphs], dtype=_I64)
        self._offsets = np.zeros(len(graphs), dtype=_I64)
        np.cumsum(sizes[:-1], out=self._offsets[1:])
        self.n_vertices = int(sizes.sum())
        self.matrix = full_transition_matrix(graphs, config, self._offsets.tolist())
        # Global vertex id -> state index, by a search over all sequences' first vertex ids.
        firsts = np.concatenate([g.seq_first for g in graphs])
        lens = np.concatenate([g.seq_len for g in graphs])
        state0 = np.concatenate([off + g.local_first for g, off in zip(graphs, self._offsets,
                                                                       strict=True)])
        order = np.argsort(firsts, kind="stable")
        self._firsts, self._lens, self._state0 = firsts[order], lens[order], state0[order]
        if len(order) > 1 and np.any(self._firsts[1:] < self._firsts[:-1] + self._lens[:-1]):
            raise ValueError("components overlap")
        self._vids = np.empty(self.n_vertices, dtype=_I64)
        for g, off in zip(graphs, self._offsets.tolist(), strict=True):
            self._vids[off: off + g.n_vertices] = g.vertex_ids()
        self._obs = ObservationModel(config, self.sequence_first)
        self._eps = config.restart_prob
        self._nu = config.new_place_prob
        self.reset()

    def sequence_first(self, vertex_ids: np.ndarray) -> np.ndarray:
        """The first vertex id of each vertex's sequence (the drive rival's look-up)."""
        ids = np.asarray(vertex_ids, dtype=_I64)
        at = np.maximum(np.searchsorted(self._firsts, ids, side="right") - 1, 0)
        out: np.ndarray = self._firsts[at]
        return out

    def reset(self) -> None:
        """Forget the belief (all mass off the map until the first frame)."""
        self.x: np.ndarray = np.zeros(self.n_vertices + 1)
        self.x[-1] = 1.0
        self._started = False
        self.frames = 0
        self._obs.reset()
        #: The last frame's (hit states, likelihood ratios, sink ratio), for :meth:`smooth`.
        self._obs_last: tuple[np.ndarray, np.ndarray, float] = (
            np.empty(0, dtype=_I64), np.empty(0), 1.0)

    @property
    def sink_prob(self) -> float:
        """Posterior of the sink."""
        return float(self.x[-1])

    def state_index(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Dense state index of each global vertex id (ValueError if not in the map)."""
        vids = np.asarray(vertex_ids, dtype=_I64)
        pos = np.searchsorted(self._firsts, vids, side="right") - 1
        ok = (pos >= 0) & (vids < self._firsts[np.maximum(pos, 0)] + self._lens[np.maximum(pos, 0)])
        if not np.all(ok):
            raise ValueError("vertex id not in the map")
        out: np.ndarray = self._state0[pos] + (vids - self._firsts[pos])
        return out

    def posterior(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``(vertex_ids ascending, probs, sink_prob)`` over the whole map."""
        order = np.argsort(self._vids, kind="stable")
        return self._vids[order], self.x[:-1][order].copy(), float(self.x[-1])

    def set_posterior(self, vertex_ids: np.ndarray, probs: np.ndarray, sink_prob: float) -> None:
        """Set the belief (tests: run one step from another filter's posterior)."""
        x = np.zeros(self.n_vertices + 1)
        x[self.state_index(vertex_ids)] = probs
        x[-1] = sink_prob
        self.x = x
        self._started = True

    def step(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> Decision:
        """:meth:`update` then :meth:`decide` (same contract as ``SprintFilter.step``)."""
        self.update(hit_ids, hit_dists)
        return self.decide()

    def update(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> None:
        """One HMM step over the whole map (no decision)."""
        obs = self._obs.observe(hit_ids, hit_dists)
        n_hits = len(obs.vertex_ids)
        idx = self.state_index(np.asarray(obs.vertex_ids, dtype=_I64)) if n_hits else None
        if self._started:
            if self.frames % FLUSH_EVERY == 0:
                body = self.x[:-1]
                np.putmask(body, body < FLUSH_BELOW, 0.0)
            x = self.matrix @ self.x
            x[-1] += self._nu
            if n_hits:
                x[idx] += self._eps / n_hits
            else:
                x[-1] += self._eps
        else:
            self._started = True
            x = np.zeros(self.n_vertices + 1)
            if n_hits:
                x[-1] = self._nu
                x[idx] = (1.0 - self._nu) / n_hits
            else:
                x[-1] = 1.0
        if n_hits:
            x[idx] *= np.asarray(obs.lik)
        x[-1] *= obs.sink_lik
        self._obs_last = (np.asarray(idx if n_hits else [], dtype=_I64),
                          np.asarray(obs.lik, dtype=float), float(obs.sink_lik))
        total = x.sum()
        if not np.isfinite(total) or total <= 0.0:
            x[:] = 0.0
            x[-1] = 1.0
        else:
            x *= 1.0 / total
        self.x = x
        self.frames += 1

    def smooth(self, hits: Iterable[tuple[np.ndarray, np.ndarray]]
               ) -> list[tuple[np.ndarray, float]]:
        """Forward-backward over the whole map: the smoothed posterior of every frame.

        The reference of :mod:`sprint_map.hmm.smoother` (same model, dense, never pruned).
        Resets the filter first and leaves it after the last frame.

        Returns
        -------
        list of (probs, sink_prob)
            Per frame, the smoothed posterior over the states in this filter's state order
            (:meth:`state_index`) and the sink's.

        Notes
        -----
        O(N nnz(A)) time and O(N n) memory for N frames: for tests, not for maps.
        """
        self.reset()
        alphas: list[np.ndarray] = []
        obs_list: list[tuple[np.ndarray, np.ndarray, float]] = []
        for ids, dists in hits:
            self.update(ids, dists)
            alphas.append(self.x.copy())
            obs_list.append(self._obs_last)
        out: list[tuple[np.ndarray, float]] = []
        if not alphas:
            return out
        eps, nu = self._eps, self._nu
        beta = np.ones(self.n_vertices + 1)
        matrix_t = self.matrix.T.tocsr()
        for t in range(len(alphas) - 1, -1, -1):
            if t < len(alphas) - 1:
                idx, lik, sink_lik = obs_list[t + 1]
                m = beta.copy()
                m[idx] *= lik
                m[-1] *= sink_lik
                if idx.size:
                    const = eps * float(m[idx].sum()) / idx.size + nu * m[-1]
                else:
                    const = (eps + nu) * m[-1]
                beta = matrix_t @ m + const
                beta /= beta.max()
            gamma = alphas[t] * beta
            gamma /= gamma.sum()
            out.append((gamma[:-1], float(gamma[-1])))
        out.reverse()
        return out

    def decide(self) -> Decision:
        """The decision for the current belief (same rules as ``SprintFilter.decide``)."""
        cfg = self.config
        body = self.x[:-1]
        m = cfg.decision_candidates
        peak = float(body.max()) if body.size else 0.0
        idx = (body >= peak * CANDIDATE_FLOOR).nonzero()[0] if peak > 0.0 else np.empty(0, int)
        if idx.size > m:
            vals = body[idx]
            idx = idx[np.argpartition(vals, vals.size - m)[vals.size - m:]]
        cands = sorted(((p, i) for i, p in zip(idx.tolist(), body[idx].tolist(), strict=True)),
                       key=lambda c: (-c[0], c[1]))
        views: list[BeliefView] = []
        slot_of: dict[int, int] = {}
        candidates: list[tuple[float, int, int]] = []
        for p, i in cands:
            gi = int(np.searchsorted(self._offsets, i, side="right")) - 1
            if gi not in slot_of:
                g = self.graphs[gi]
                off = int(self._offsets[gi])
                slot_of[gi] = len(views)
                views.append(BeliefView(g, g.local_first, body[off: off + g.n_vertices]))
            candidates.append((p, slot_of[gi], i - int(self._offsets[gi])))
        held = np.add.reduceat(body, self._offsets) > 0.0 if body.size else np.zeros(0, bool)
        n_vert = int(self._sizes[held].sum())
        return decide(views, candidates, float(self.x[-1]), cfg.place_radius, cfg.place_hops,
                      cfg.min_confidence, int(held.sum()), n_vert)
