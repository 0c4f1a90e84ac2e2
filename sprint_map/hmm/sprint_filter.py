"""SPRINT: the place-recognition HMM run only on the components that hold belief.

Per frame (``docs/architecture.md`` ("The HMM"), "Per-frame data flow"):

1. observe: hits -> likelihood ratios (:mod:`sprint_map.hmm.observation`);
2. locate every hit in the active set; activate the components of the others (graph source,
   through the LRU cache); a bad hit raises here, before the belief is touched;
3. propagate every active component (window + edges; overflow -> sink), scale by
   ``1 - eps - nu``; the sink keeps its mass and receives ``nu``;
4. inject ``eps / n_hits`` at every hit and multiply hits and sink by their likelihood ratios
   (every other vertex has ratio 1: nothing to do);
5. normalise; drop components whose share is below ``prune_threshold``; renormalise;
6. (``decide``) score the most probable vertices by place mass; novelty rules.

Nothing in a step is sized by the map: the work is O(W n_active + nnz(U_active) + k log S_active)
plus, for a newly active component, its load (cached) and an O(n_c + E_c) set-up.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from sprint_map.hmm.active_set import ActiveComponent, ActiveSet
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision, decide, top_candidates
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.observation import ObservationModel
from sprint_map.hmm.transition import FLUSH_BELOW, FLUSH_EVERY, ComponentTransition


class SprintFilter:
    """The SPRINT subgraph HMM over a :class:`~sprint_map.hmm.graph.GraphSource`.

    Parameters
    ----------
    config : HMMConfig
        Model parameters.
    source : GraphSource
        Where components come from (the map facade's LMDB source, or
        :class:`~sprint_map.hmm.graph.MemoryGraphSource`).
    cache : ComponentCache, optional
        Shared LRU cache of components; by default a private one of
        ``config.cache_budget_bytes``.

    Notes
    -----
    A step costs O(W n_active + nnz(U_active) + k log S_active) where ``n_active`` is the
    number of vertices of the active components: never O(map). Memory is the active components'
    belief vectors plus the cache budget. Not thread-safe (one filter per query stream).

    Examples
    --------
    >>> import numpy as np
    >>> from sprint_map.hmm import HMMConfig, MemoryGraphSource, SprintFilter
    >>> f = SprintFilter(HMMConfig(), MemoryGraphSource([50, 50]))
    >>> for t in range(5):
    ...     d = f.step(np.array([10 + t, 70]), np.array([0.1, 0.5]))
    >>> d.vertex_id, d.seq_id, d.image_id
    (14, 0, 14)
    """

    def __init__(self, config: HMMConfig, source: GraphSource,
                 cache: ComponentCache | None = None) -> None:
        if not isinstance(config, HMMConfig):
            raise ValueError("config must be an HMMConfig")
        self.config = config
        self.source = source
        self.cache = cache if cache is not None else ComponentCache(config.cache_budget_bytes)
        self._obs = ObservationModel(config)
        self._active = ActiveSet()
        self._eps = config.restart_prob
        self._nu = config.new_place_prob
        self._scale = 1.0 - config.restart_prob - config.new_place_prob
        self._prune = config.prune_threshold
        self._sink = 1.0
        self._started = False
        self.frames = 0
        self.pruned_mass = 0.0
        self.last_pruned_mass = 0.0

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the belief (start of a new query sequence). The cache is kept."""
        self._active.clear()
        self._obs.reset()
        self._sink = 1.0
        self._started = False
        self.frames = 0
        self.pruned_mass = 0.0
        self.last_pruned_mass = 0.0

    @property
    def n_active_components(self) -> int:
        """Number of components in the active set."""
        return len(self._active)

    @property
    def n_active_vertices(self) -> int:
        """Number of vertices of the active components (the per-step state size)."""
        return self._active.n_vertices

    @property
    def active_component_ids(self) -> list[int]:
        """Ids of the active components."""
        return list(self._active.comps)

    @property
    def sink_prob(self) -> float:
        """Posterior of the sink (1.0 before the first frame)."""
        return self._sink

    def posterior(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The belief over the vertices of the active components.

        Returns
        -------
        vertex_ids : ndarray of int64
            Every vertex of the active components, ascending.
        probs : ndarray of float64
            Their posterior (every vertex outside the active set has posterior 0).
        sink_prob : float

        Notes
        -----
        O(n_active log n_active); for tests and diagnostics, not for the per-frame path.
        """
        vids: list[np.ndarray] = []
        probs: list[np.ndarray] = []
        for comp in self._active:
            vids.append(comp.graph.vertex_ids())
            probs.append(comp.x[comp.trans.vertex_slots()])
        if not vids:
            return np.empty(0, dtype=np.int64), np.empty(0), self._sink
        v = np.concatenate(vids)
        p = np.concatenate(probs)
        order = np.argsort(v, kind="stable")
        return v[order], p[order], self._sink

    # ------------------------------------------------------------------ per frame
    def step(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> Decision:
        """Filter one query frame and decide where it is.

        Parameters
        ----------
        hit_ids : ndarray of int64, shape (k,) or (1, k)
            Retrieved global vertex ids over the whole map; ``-1`` pads.
        hit_dists : ndarray of float, same shape
            Their squared-L2 distances.

        Returns
        -------
        Decision

        Raises
        ------
        ValueError
            On malformed hits or a hit the graph source does not know.

        Notes
        -----
        :meth:`update` then :meth:`decide`; see the class notes for the cost.
        """
        self.update(hit_ids, hit_dists)
        return self.decide()

    def update(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> None:
        """Propagate the belief one frame and fold in the frame's hits (no decision).

        This is the HMM inference step proper (what the paper and ``tools/bench_fig4.py`` time).
        Same parameters and errors as :meth:`step`.
        """
        # This is the hot path of the whole system (and of tools/bench_fig4.py): plain Python
        # over the k hits and the active components, one numpy call per component and stage.
        vids, _, liks, sink_lik, _ = self._obs.evaluate(hit_ids, hit_dists)
        n_hits = len(vids)
        comps = self._active.comps
        # Locate (and activate) before touching the belief: a bad hit leaves the state intact.
        if n_hits == 1:
            hit = self._active.locate(vids[0])
            located = [hit] if hit is not None else self._locate(vids)
        else:
            located = self._locate(vids) if n_hits else []
        if self._started:
            scale = self._scale
            sink = scale * self._sink + self._nu
            exact = self.frames % FLUSH_EVERY == 0
            for comp in comps.values():
                if exact:
                    np.putmask(comp.x, comp.x < FLUSH_BELOW, 0.0)
                if comp.mass > 0.0:  # a just-activated component holds no belief yet
                    trans = comp.trans
                    if trans.simple:
                        # One sequence, no edges (inlined ComponentTransition.propagate): the
                        # W - 1 tail of the convolution is what ran past the sequence end.
                        # Propagation keeps mass, so the component's new mass is known
                        # without summing it (re-summed exactly every FLUSH_EVERY frames).
                        y = np.correlate(comp.x, trans.krev, "full")
                        n = trans.n_state
                        spill = math.fsum(y[n:].tolist())
                        comp.x = y[:n]
                        comp.mass = scale * comp.mass - spill
                        if exact or comp.mass < spill:
                            comp.mass = float(comp.x.dot(trans.ones))
                    else:
                        comp.x, spill = trans.propagate(comp.x)
                        comp.mass = float(comp.x.dot(trans.ones))
                    sink += spill
            if n_hits:
                inject = self._eps / n_hits
            else:
                sink += self._eps
                inject = 0.0
        else:
            # Initialisation from the first frame's hits, not uniform over the map.
            self._started = True
            if n_hits:
                sink = self._nu
                inject = (1.0 - self._nu) / n_hits
            else:
                sink = 1.0
                inject = 0.0
        for (comp, slot), lik in zip(located, liks, strict=True):
            x = comp.x
            old = x.item(slot)
            new = (old + inject) * lik
            x[slot] = new
            comp.mass += new - old
        self._normalise(sink * sink_lik)
        self.frames += 1

    def _locate(self, vids: list[int]) -> list[tuple[ActiveComponent, int]]:
        """(component, slot) of every hit, activating the components not yet active."""
        locate = self._active.locate
        found = [locate(v) for v in vids]
        if None not in found:
            return found  # type: ignore[return-value]
        active = self._active
        missing = [v for v, f in zip(vids, found, strict=True) if f is None]
        comp_ids = np.asarray(self.source.components_of(np.asarray(missing, dtype=np.int64)))
        if comp_ids.shape != (len(missing),):
            raise ValueError("graph source returned a wrong number of component ids")
        added: list[int] = []
        try:
            for cid in dict.fromkeys(comp_ids.tolist()):
                if cid not in active:
                    graph = self.cache.get(int(cid), self.source.load_component)
                    active.add(ComponentTransition(graph, self.config))
                    added.append(int(cid))
            out: list[tuple[ActiveComponent, int]] = []
            for v, f in zip(vids, found, strict=True):
                if f is None:
                    f = locate(v)
                    if f is None:
                        raise ValueError(f"vertex {v} is not in the component the source named")
                out.append(f)
        except BaseException:
            for cid in added:  # a failed frame leaves the active set as it was
                active.remove(cid)
            raise
        return out

    def _normalise(self, sink: float) -> None:
        """Normalise, prune components below ``prune_threshold``, renormalise."""
        comps = self._active.comps
        total = sink
        low = math.inf
        for comp in comps.values():
            mass = comp.mass
            total += mass
            if mass < low:
                low = mass
        if not 0.0 < total < math.inf:
            # Numerical breakdown (all likelihoods underflowed): fall back to "off the map";
            # the restart mass brings the belief back on the next frames.
            self._active.clear()
            self._sink = 1.0
            return
        pruned = 0.0
        if low < self._prune * total:
            limit = self._prune * total
            for cid in [cid for cid, comp in comps.items() if comp.mass < limit]:
                pruned += comps[cid].mass
                self._active.remove(cid)
            total = sink + sum(c.mass for c in comps.values())
            pruned /= pruned + total
        self.last_pruned_mass = pruned
        self.pruned_mass += pruned
        inv = 1.0 / total
        for comp in comps.values():
            x = comp.x
            np.multiply(x, inv, out=x)
            comp.mass *= inv
        self._sink = sink * inv

    def decide(self) -> Decision:
        """The decision for the current belief (see :mod:`sprint_map.hmm.decision`).

        Notes
        -----
        O(n_active) for the candidate search (a max, a comparison and a ``nonzero`` per active
        component) plus O(m (r + h d log d)) for the place masses of the m candidates.
        """
        cfg = self.config
        views = [c.view() for c in self._active]
        candidates = top_candidates(views, cfg.decision_candidates)
        return decide(views, candidates, self._sink, cfg.place_radius, cfg.place_hops,
                      cfg.min_confidence, len(self._active), self._active.n_vertices)

    # ------------------------------------------------------------------ map changes
    def invalidate(self, component_ids: Iterable[int] | None = None) -> None:
        """Re-read components after the map changed (sequences added, components merged).

        Drops ``component_ids`` (all if None) from the cache, then re-maps the belief of every
        active component onto the source's current components by vertex id (vertex ids are
        stable, component ids may change on a merge). The belief is preserved exactly.

        Notes
        -----
        O(n_active) plus the loads of the affected components.
        """
        if component_ids is None:
            self.cache.clear()
        else:
            self.cache.invalidate(component_ids)
        comps = list(self._active)
        if not comps:
            return
        vids = np.concatenate([c.graph.vertex_ids() for c in comps])
        probs = np.concatenate([c.x[c.trans.vertex_slots()] for c in comps])
        keep = probs > 0.0
        vids, probs = vids[keep], probs[keep]
        self._active.clear()
        if not vids.size:
            return
        comp_ids = np.asarray(self.source.components_of(vids))
        for cid in np.unique(comp_ids).tolist():
            graph = self.cache.get(int(cid), self.source.load_component)
            comp = self._active.add(ComponentTransition(graph, self.config))
            sel = comp_ids == cid
            comp.x[comp.trans.slots_of(vids[sel])] = probs[sel]
            comp.mass = float(probs[sel].sum())
