"""SPRINT: the place-recognition HMM run only where the belief is.

Two levels of sparsity (``docs/hmm.md``, "The active set"). The *active set* holds the
components (connected by edges) that hold belief, as in the paper; inside each active component
only the *live support* is propagated: windows of slots of its sequences
(:mod:`sprint_map.hmm.support`). In a lifelong map every merge adds edges until most of the map
is one component, so the second level is what keeps a step independent of the map.

Per frame (``docs/hmm.md``, "Per-frame data flow inside"):

1. observe: hits -> likelihood ratios (:mod:`sprint_map.hmm.observation`);
2. locate every hit in the active set; activate the components of the others (graph source,
   through the LRU cache); a bad hit raises here, before the belief is touched;
3. propagate the windows of every active component (window + edges leaving them; overflow ->
   sink), scaled by ``1 - eps - nu``; windows grow by ``W - 1``, edge targets open windows;
   the sink keeps its mass and receives ``nu``;
4. inject ``eps / n_hits`` at every hit and multiply hits and sink by their likelihood ratios
   (every other vertex has ratio 1: nothing to do); a hit outside the windows opens one;
5. prune components whose share is below ``prune_threshold``; every ``TRIM_EVERY`` frames
   trim window slots whose share is below ``support_threshold``; normalise (lazily: one global
   factor, see :class:`SprintFilter`);
6. (``decide``) score the most probable live vertices by place mass; novelty rules.

Nothing in a step is sized by the map or by a component: the work is O(W live + edges leaving
the live windows + k log S_active), plus, for a newly active component, its load (cached) and an
O(n_c + E_c log E_c) set-up.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections import OrderedDict
from collections.abc import Iterable, ValuesView
from itertools import accumulate
from operator import attrgetter

import numpy as np

from sprint_map.hmm.active_set import ActiveComponent, ActiveSet
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision, decide, top_candidates
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.observation import ObservationModel, sequence_first_of
from sprint_map.hmm.support import TRIM_EVERY, runs
from sprint_map.hmm.transition import FLUSH_BELOW, FLUSH_EVERY, ComponentTransition

__all__ = ["BEAM_AHEAD", "MANY_HITS", "RESCALE_AT", "SprintFilter", "TRANSITION_MEMO", "inject_many"]

#: Lazy normalisation: the raw belief is rescaled in place when its normaliser leaves
#: [1 / RESCALE_AT, RESCALE_AT] (a frame's likelihood ratios are at most e**200 ~ 1e87, so raw
#: values stay far from float64 overflow and underflow).
RESCALE_AT = 1e60
_add = np.add.reduce
_NO_SLOTS = np.zeros(0, dtype=np.int64)
_NO_VALUES = np.zeros(0)
#: Transitions of recently active components kept for re-activation (their set-up is O(n_c)).
TRANSITION_MEMO = 32
#: Frames with at least this many hits are located and injected with array operations
#: (:func:`inject_many`; the deep searches of the lag and the smoothing pass); fewer, hit by
#: hit in Python (cheaper for a handful). The same floats either way.
MANY_HITS = 16
#: A component met by a frame's hits is not activated when the beam
#: (``max_active_components``) would drop it at the end of that frame anyway: only its mass
#: counts in the frame's sums. The same floats either way (tests turn it off to compare).
BEAM_AHEAD = True


class _Beamed:
    """A component the beam drops in the frame that meets it: only its mass."""

    __slots__ = ("mass",)

    def __init__(self, mass: float) -> None:
        self.mass = mass


_mass = attrgetter("mass")


class SprintFilter:
    """The SPRINT subgraph HMM over a :class:`~sprint_map.hmm.graph.GraphSource`.

    ``config`` holds the model parameters; ``source`` is where components come from (the map's
    LMDB source or :class:`~sprint_map.hmm.graph.MemoryGraphSource`); ``cache`` is a shared LRU
    :class:`ComponentCache` (default: a private one of ``config.cache_budget_bytes``).
    ``pruned_mass``, ``trimmed_mass``: belief dropped so far by component pruning and support
    trimming (each step's share, summed; ``last_pruned_mass``, ``last_trimmed_mass`` the last
    step's); ``frames``: frames filtered since the last reset.

    A step costs O(W live + E_live + k log S_active) (``live``: slots of the live windows,
    ``E_live``: edges leaving them): never O(map) nor O(component), but for a newly active
    component's load. Memory: a slot vector per active component plus the cache budget. Not
    thread-safe (one filter per query stream). The belief is normalised lazily: slot vectors and
    the sink hold a raw belief, the posterior is ``raw * z`` with ``z = 1 / raw total`` (every
    read applies it); raw values are rescaled only when ``z`` leaves ``[1e-60, 1e60]``.

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
        self._obs = ObservationModel(config, sequence_first_of(source))
        self._one_hit_lik = self._obs.one_hit_lik
        self._sink_lik_const = self._obs.sink_lik_const
        self._active = ActiveSet()
        self._transitions: OrderedDict[int, ComponentTransition] = OrderedDict()
        self._eps = config.restart_prob
        self._nu = config.new_place_prob
        self._scale = 1.0 - config.restart_prob - config.new_place_prob
        self._prune = config.prune_threshold
        self._max_active = config.max_active_components
        self._support = config.support_threshold
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the belief (start of a new query sequence). The cache is kept."""
        self._active.clear()
        self._obs.reset()
        self._sink = 1.0  # raw
        self._z = 1.0  # posterior = raw * z
        self._started = False
        self._n_propagated = 0
        self.frames = 0
        self.pruned_mass = 0.0
        self.last_pruned_mass = 0.0
        self.trimmed_mass = 0.0
        self.last_trimmed_mass = 0.0

    @property
    def n_active_components(self) -> int:
        """Number of components in the active set."""
        return len(self._active)

    @property
    def n_active_vertices(self) -> int:
        """Vertices propagated by the last update (the per-step state size).

        The live windows the step propagated (edge targets included), summed over the active
        components; 0 after the first frame (nothing to propagate yet). Not the size of the
        components: see :attr:`n_component_vertices`.
        """
        return self._n_propagated

    @property
    def n_live_vertices(self) -> int:
        """Vertices in the live windows now (what the next step propagates, before growth)."""
        return sum(c.n_live for c in self._active)

    @property
    def n_component_vertices(self) -> int:
        """Vertices of the active components (what the paper's filter would propagate)."""
        return self._active.n_vertices

    @property
    def active_component_ids(self) -> list[int]:
        """Ids of the active components."""
        return list(self._active.comps)

    @property
    def sink_prob(self) -> float:
        """Posterior of the sink (1.0 before the first frame)."""
        return self._sink * self._z

    def component_probs(self) -> dict[int, float]:
        """Posterior mass of each active component (O(active components))."""
        z = self._z
        return {cid: c.mass * z for cid, c in self._active.comps.items()}

    def posterior(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The belief over the vertices of the active components (live or not).

        Returns
        -------
        vertex_ids : ndarray of int64
            Every vertex of the active components, ascending.
        probs : ndarray of float64
            Their posterior (every vertex outside the active set has posterior 0).
        sink_prob : float

        Notes
        -----
        O(n log n) for the n vertices of the active components; for tests and diagnostics, not
        for the per-frame path.
        """
        vids: list[np.ndarray] = []
        probs: list[np.ndarray] = []
        for comp in self._active:
            vids.append(comp.graph.vertex_ids())
            probs.append(comp.x[comp.trans.vertex_slots()] * self._z)
        if not vids:
            return np.empty(0, dtype=np.int64), np.empty(0), self.sink_prob
        v = np.concatenate(vids)
        p = np.concatenate(probs)
        order = np.argsort(v, kind="stable")
        return v[order], p[order], self.sink_prob

    def set_novelty_dist(self, value: float | None) -> None:
        """Use ``value`` as the novelty distance from the next frame on (see
        ``HMMConfig.novelty_dist``; None: no absolute test). The smoother calibrates it per
        frame; a causal filter keeps its config's."""
        self._obs.novelty_dist = value
        self._sink_lik_const = self._obs.sink_lik_const

    def live_belief(self) -> tuple[list[tuple[ComponentTransition, np.ndarray, np.ndarray]],
                                   float]:
        """The belief held now: per active component its transition, the slots of its live
        windows that hold belief (ascending) and their posterior; and the sink's posterior.

        Notes
        -----
        O(live): what the smoother (:mod:`sprint_map.hmm.smoother`) keeps of each frame
        (:meth:`laid_belief`, each component's share a view of it).
        """
        transitions, slots, values, starts, sink = self.laid_belief()
        return [(trans, slots[starts[i]:starts[i + 1]], values[starts[i]:starts[i + 1]])
                for i, trans in enumerate(transitions)], sink

    def laid_belief(self) -> tuple[list[ComponentTransition], np.ndarray, np.ndarray,
                                   list[int], float]:
        """:meth:`live_belief` laid end to end: the active components' transitions, the
        slots holding belief (each component's ascending, one component after another),
        their posterior, where each component's slots start (and their total, last), and the
        sink's posterior.

        Notes
        -----
        O(live), about 8 numpy calls plus 2 per active component.
        """
        z = self._z
        comps = list(self._active)
        if not comps:
            return [], _NO_SLOTS, _NO_VALUES, [0], self._sink * z
        live = [comp.live_slots() for comp in comps]
        slots = np.concatenate(live) if len(live) > 1 else live[0]
        values = (np.concatenate([comp.x[idx] for comp, idx in zip(comps, live, strict=True)])
                  if len(live) > 1 else comps[0].x[live[0]])
        held = (values > 0.0).nonzero()[0]
        ends = list(accumulate(idx.size for idx in live))
        starts = [0, *held.searchsorted(ends).tolist()]
        values = values[held]
        values *= z
        return [comp.trans for comp in comps], slots[held], values, starts, self._sink * z

    # ------------------------------------------------------------------ per frame
    def step(self, hit_ids: np.ndarray, hit_dists: np.ndarray,
             weights: np.ndarray | None = None, sink_weight: float = 1.0) -> Decision:
        """Filter one query frame and decide where it is: :meth:`update` then :meth:`decide`
        (the class notes give the cost).

        Parameters
        ----------
        hit_ids : ndarray of int64, shape (k,) or (1, k)
            Retrieved global vertex ids over the whole map; ``-1`` pads.
        hit_dists : ndarray of float, same shape
            Their squared-L2 distances.
        weights, sink_weight : optional
            Another cue's likelihood ratios of the hits and of the sink (GNSS:
            :mod:`sprint_map.localize.gnss`; :meth:`ObservationModel.evaluate`).

        Returns
        -------
        Decision

        Raises
        ------
        ValueError
            On malformed hits or a hit the graph source does not know.
        """
        self.update(hit_ids, hit_dists, weights, sink_weight)
        return self.decide()

    def update(self, hit_ids: np.ndarray, hit_dists: np.ndarray,
               weights: np.ndarray | None = None, sink_weight: float = 1.0) -> None:
        """Propagate the belief one frame and fold in the frame's hits (no decision).

        This is the HMM inference step proper (what the paper and ``tools/bench_fig4.py`` time).
        Same parameters and errors as :meth:`step`.
        """
        # This is the hot path of the whole system (and of tools/bench_fig4.py). A frame with
        # one plain hit after the first frame (k = 1: a vehicle's best match) takes the path
        # below: the same arithmetic as the general path (_update_any), in the same order (the
        # same floats: tests/hmm/test_hmm_fast_path.py checks it), without its loops over the
        # hits. Per-call overhead is the whole cost of a step at this size, so the common case
        # (one active component, the hit in or just ahead of its single window: a vehicle on
        # one mapped road, or in a lifelong map whose drives merged into one giant component)
        # is inline, and only a frame that prunes, trims or opens a window runs _finish.
        plain = weights is None and sink_weight == 1.0
        vid = self._obs.single_hit(hit_ids, hit_dists) if self._started and plain else -1
        if vid < 0:
            vids, _, liks, sink_lik, _ = self._obs.evaluate(hit_ids, hit_dists, weights,
                                                            sink_weight)
            self._update_any(vids, liks, sink_lik)
            return
        comps = self._active.comps
        comp: ActiveComponent | None = None
        if len(comps) == 1:
            (comp,) = comps.values()
            slot = vid + comp.shift  # (valid only inside the window's sequence)
            if comp.n_windows != 1 or not comp.a <= slot < comp.end:
                comp = None
        if comp is None:
            # Locate (and activate) before touching the belief: a bad hit leaves it intact.
            comp, slot = self._locate([vid])[0]
        single = len(comps) == 1
        scale = self._scale
        zinv = 1.0 / self._z
        flush_below = FLUSH_BELOW * zinv if self.frames % FLUSH_EVERY == 0 else 0.0
        sink = scale * self._sink + self._nu * zinv
        if single and comp.n_windows:
            sink += comp.propagate(flush_below, scale)
            self._n_propagated = comp.n_propagated
        else:
            n_prop = 0
            for c in comps.values():
                if c.n_windows:  # (a just-activated component holds no belief yet)
                    sink += c.propagate(flush_below, scale)
                    n_prop += c.n_propagated
            self._n_propagated = n_prop
        x = comp.x
        old = x.item(slot)
        new = (old + self._eps * zinv) * self._one_hit_lik
        x[slot] = new
        comp.mass = mass = comp.mass + (new - old)
        sink *= self._sink_lik_const
        if comp.n_windows != 1 or not comp.a <= slot < comp.b:
            comp.pending.append(slot)  # a new hypothesis: it opens a window
            self._finish(sink)
        elif (not single or mass < self._prune * (sink + mass)
              or not 0.0 < sink + mass < math.inf or self.frames % TRIM_EVERY == TRIM_EVERY - 1):
            self._finish(sink)
        else:  # what _finish does for one component when there is nothing to prune or trim
            self.last_pruned_mass = self.last_trimmed_mass = 0.0
            self._sink = sink
            self._z = z = 1.0 / (sink + mass)
            if not 1.0 / RESCALE_AT < z < RESCALE_AT:
                self._rescale()
        self.frames += 1

    def update_observed(self, vids: list[int], liks: list[float], sink_lik: float) -> None:
        """:meth:`update` for a frame already evaluated by an
        :class:`~sprint_map.hmm.observation.ObservationModel` of this config that has seen the
        same frames (its distinct valid hits, their likelihood ratios and the sink's): the
        smoothers evaluate each frame once, for the filter and for themselves. The same
        floats as :meth:`update` (its one-hit path is the same arithmetic); raises as it does
        for a hit the source does not know, before the belief is touched."""
        self._update_any(vids, liks, sink_lik)

    def _update_any(self, vids: list[int], liks: list[float], sink_lik: float) -> None:
        """:meth:`update` for any frame: the general path (the one-hit path is inline there)."""
        n_hits = len(vids)
        # Locate (and load what to activate) before touching the belief: a bad hit leaves the
        # state intact.
        groups = self._active.locate_many(np.asarray(vids)) if n_hits >= MANY_HITS else None
        located: list[tuple[ActiveComponent, int] | None] = []
        fresh: list[tuple[ComponentTransition, list[int], list[int] | None]] = []
        if n_hits and groups is None:
            located, fresh = self._locate_known(vids)
        comps = self._active.comps
        n_prop = 0
        if self._started:
            # Everything below is in raw units (posterior = raw * z): the mass a step adds
            # (nu, eps) is divided by z instead of multiplying every slot by the normaliser.
            scale = self._scale
            zinv = 1.0 / self._z
            sink = scale * self._sink + self._nu * zinv
            flush_below = FLUSH_BELOW * zinv if self.frames % FLUSH_EVERY == 0 else 0.0
            for comp in comps.values():
                if comp.n_windows:  # (a just-activated component holds no belief yet)
                    sink += comp.propagate(flush_below, scale)
                    n_prop += comp.n_propagated
            if n_hits:
                inject = self._eps * zinv / n_hits
            else:
                sink += self._eps * zinv
                inject = 0.0
        else:
            # Initialisation from the first frame's hits, not uniform over the map.
            self._started = True
            self._z = 1.0
            if n_hits:
                sink = self._nu
                inject = (1.0 - self._nu) / n_hits
            else:
                sink = 1.0
                inject = 0.0
        self._n_propagated = n_prop
        if groups is not None:
            inject_many(groups, np.asarray(liks, dtype=np.float64), inject)
        else:
            for found, lik in zip(located, liks, strict=True):
                if found is None:
                    continue  # (a hit of a component activated below)
                comp, slot = found
                x = comp.x
                old = x.item(slot)
                new = (old + inject) * lik
                x[slot] = new
                comp.mass += new - old
                # A hit outside the live windows opens one (a new hypothesis from the
                # restart mass).
                if comp.n_windows != 1 or not comp.a <= slot < comp.b:
                    comp.pending.append(slot)
        entries = self._activate_fresh(fresh, vids, liks, inject) if fresh else None
        self._finish(sink * sink_lik, entries)
        self.frames += 1

    def _locate_known(self, vids: list[int]) -> tuple[
            list[tuple[ActiveComponent, int] | None],
            list[tuple[ComponentTransition, list[int], list[int] | None]]]:
        """(component, slot) of every hit an active component holds (None for the others),
        and the components of the others to activate: their transitions (loaded now), the
        positions of their hits (in hit order) and the slots of those hits (None for a
        component of one sequence: the hits' offsets in it), in the order :meth:`_locate`
        activates them. Raises before anything changes for a hit the source does not know or
        does not place where it says."""
        active = self._active
        found = (active.locate_each(np.asarray(vids, dtype=np.int64)) if len(vids) >= MANY_HITS
                 else [active.locate(v) for v in vids])
        if None not in found:
            return found, []
        at = [i for i, f in enumerate(found) if f is None]
        comp_ids = np.asarray(self.source.components_of(np.asarray([vids[i] for i in at],
                                                                   dtype=np.int64)))
        if comp_ids.shape != (len(at),):
            raise ValueError("graph source returned a wrong number of component ids")
        hits: dict[int, list[int]] = {}
        for i, cid in zip(at, comp_ids.tolist(), strict=True):
            hits.setdefault(cid, []).append(i)
        for cid, mine in hits.items():  # (in order of first appearance: the first such hit)
            if cid in active:
                raise ValueError(f"vertex {vids[mine[0]]} is not in the component the source "
                                 "named")
        fresh: list[tuple[ComponentTransition, list[int], list[int] | None]] = []
        transition = self._transition
        for cid, mine in hits.items():
            trans = transition(cid)
            ids = [vids[i] for i in mine]
            slots: list[int] | None
            if len(trans.ranges) == 1:
                first, length, _ = trans.ranges[0]
                if min(ids) < first or max(ids) >= first + length:
                    raise ValueError(f"a vertex of {ids} is not in the component the source "
                                     "named")
                slots = None  # (``id - first``, made if the component is activated)
            else:
                held, found_slots = trans.held_slots(np.asarray(ids, dtype=np.int64))
                if held.size != len(ids):
                    raise ValueError(f"a vertex of {ids} is not in the component the source "
                                     "named")
                slots = found_slots.tolist()
            fresh.append((trans, mine, slots))
        return found, fresh

    def _activate_fresh(self,
                        fresh: list[tuple[ComponentTransition, list[int], list[int] | None]],
                        vids: list[int], liks: list[float], inject: float
                        ) -> list[ActiveComponent | _Beamed] | None:
        """Activate the components of :meth:`_locate_known` and inject their hits, as if they
        had been active with no belief, except those the beam would drop at the end of this
        step anyway (at least ``max_active_components`` others hold more mass): only their
        masses are kept (``_Beamed``). Returns the step's components and those masses in
        the order :meth:`_finish` sums them, or None when none was left out."""
        masses = []
        for _, mine, _ in fresh:
            mass = 0.0  # (a fresh component's hit becomes (0 + inject) * lik; in hit order)
            for i in mine:
                mass += inject * liks[i]
            masses.append(mass)
        cap = self._max_active
        comps = self._active.comps
        if cap and BEAM_AHEAD and len(comps) + len(fresh) > cap:
            ranked = sorted([c.mass for c in comps.values()] + masses)
            drop = [len(ranked) - bisect_right(ranked, m) >= cap for m in masses]
        else:
            drop = [False] * len(fresh)
        entries: list[ActiveComponent | _Beamed] = list(comps.values())
        for (trans, mine, slots), mass, dropped in zip(fresh, masses, drop, strict=True):
            if dropped:
                entries.append(_Beamed(mass))
                continue
            comp = self._active.add(trans)
            x = comp.x
            if slots is None:
                first = trans.ranges[0][0]
                slots = [vids[i] - first for i in mine]
            for slot, i in zip(slots, mine, strict=True):  # (the loop of _update_any)
                old = x.item(slot)
                new = (old + inject) * liks[i]
                x[slot] = new
                comp.mass += new - old
                comp.pending.append(slot)  # (it has no window yet)
            entries.append(comp)
        return entries if any(drop) else None

    def _activate(self, missing: np.ndarray) -> list[int]:
        """Activate the components of the ``missing`` vertices, in the order they first appear
        there; the ids activated (none if it raises)."""
        active = self._active
        comp_ids = np.asarray(self.source.components_of(missing))
        if comp_ids.shape != (len(missing),):
            raise ValueError("graph source returned a wrong number of component ids")
        added: list[int] = []
        try:
            for cid in dict.fromkeys(comp_ids.tolist()):
                if cid not in active:
                    active.add(self._transition(int(cid)))
                    added.append(int(cid))
        except BaseException:
            for cid in added:
                active.remove(cid)
            raise
        return added

    def _locate(self, vids: list[int]) -> list[tuple[ActiveComponent, int]]:
        """(component, slot) of every hit, activating the components not yet active (the
        one-hit path of :meth:`update`; the general path is :meth:`_locate_known`)."""
        active = self._active
        found = [active.locate(v) for v in vids]
        if None not in found:
            return found  # type: ignore[return-value]
        at = [i for i, f in enumerate(found) if f is None]
        missing = [vids[i] for i in at]
        added = self._activate(np.asarray(missing, dtype=np.int64))
        try:
            for i, v in zip(at, missing, strict=True):
                f = active.locate(v)
                if f is None:
                    raise ValueError(f"vertex {v} is not in the component the source named")
                found[i] = f
        except BaseException:
            for cid in added:  # a failed frame leaves the active set as it was
                active.remove(cid)
            raise
        return found  # type: ignore[return-value]

    def transition(self, component_id: int) -> ComponentTransition:
        """The transition of a component, as the filter propagates it (through the cache; its
        set-up memoised per graph): what the fixed-lag smoother re-maps waiting frames onto."""
        return self._transition(component_id)

    def _transition(self, component_id: int) -> ComponentTransition:
        """The transition of a component (through the cache; set-up memoised per graph)."""
        graph = self.cache.get(component_id, self.source.load_component)
        memo = self._transitions
        trans = memo.get(component_id)
        if trans is not None and trans.graph is graph:
            memo.move_to_end(component_id)
            return trans
        trans = memo[component_id] = ComponentTransition(graph, self.config)
        if len(memo) > TRANSITION_MEMO:
            memo.popitem(last=False)
        return trans

    def _finish(self, sink: float, entries: list[ActiveComponent | _Beamed] | None = None
                ) -> None:
        """Prune components, trim windows, normalise (raw belief in, lazy normaliser out).

        Components below ``prune_threshold`` of the total are dropped first; then (every
        ``TRIM_EVERY`` frames) slots below ``support_threshold`` of what is left are trimmed
        from the windows. The normaliser ``z`` becomes one over what remains. Both dropped
        masses are recorded as shares of the step's total. ``entries``: the step's components
        in activation order with the masses of those never activated in their places
        (:meth:`_activate_fresh`), which the beam drops; None: the active ones.
        """
        active = self._active
        comps = active.comps
        # (the step's components in the order they were activated, those left out included)
        ring: list[ActiveComponent | _Beamed] | ValuesView[ActiveComponent] = \
            comps.values() if entries is None else entries
        total = sink
        low = math.inf
        for comp in ring:
            mass = comp.mass
            total += mass
            if mass < low:
                low = mass
        if not 0.0 < total < math.inf:
            # Numerical breakdown (all likelihoods underflowed): fall back to "off the map";
            # the restart mass brings the belief back on the next frames.
            active.clear()
            self._sink = self._z = 1.0
            return
        pruned = 0.0
        if low < self._prune * total:
            limit = self._prune * total
            for comp in [c for c in ring if c.mass < limit]:
                pruned += comp.mass
                if isinstance(comp, ActiveComponent):
                    active.remove(comp.component_id)
            if entries is not None:
                ring = [c for c in entries if not c.mass < limit]
            total = sink + sum(c.mass for c in ring)
        cap = self._max_active
        if cap and len(ring) > cap:
            # A beam over components: only the ``cap`` most massive stay active, so a frame
            # costs O(cap) components whatever the number of drives whose hits it meets (many
            # unmerged drives of the same streets would otherwise each keep a window alive).
            order = sorted(ring, key=_mass, reverse=True)
            for comp in order[cap:]:
                pruned += comp.mass
                if isinstance(comp, ActiveComponent):
                    active.remove(comp.component_id)
            total = sink + sum(c.mass for c in comps.values())
        # Trimming is relative to the belief left after pruning (sink included). Several
        # windows are trimmed every frame (merging new slots alone saves nothing measurable,
        # and untrimmed windows let belief leak further over edges); a lone window every
        # TRIM_EVERY frames (its growth costs next to nothing).
        trimmed = 0.0
        limit = self._support * total
        lone = self.frames % TRIM_EVERY == TRIM_EVERY - 1
        empty: list[int] = []
        for cid, comp in comps.items():
            if comp.pending or comp.n_windows > 1 or (lone and comp.n_windows):
                trimmed += comp.settle(limit, lone)
                if not comp.n_windows:
                    empty.append(cid)
        for cid in empty:  # all its belief was negligible: it holds nothing any more
            active.remove(cid)
        if pruned or trimmed:
            step_total = total + pruned
            self.last_pruned_mass = pruned / step_total
            self.pruned_mass += self.last_pruned_mass
            self.last_trimmed_mass = trimmed / step_total
            self.trimmed_mass += self.last_trimmed_mass
            total -= trimmed
        else:
            self.last_pruned_mass = self.last_trimmed_mass = 0.0
        self._sink = sink
        self._z = z = 1.0 / total
        if not 1.0 / RESCALE_AT < z < RESCALE_AT:
            self._rescale()

    def _rescale(self) -> None:
        """Make the raw belief the posterior (``z = 1``); O(live)."""
        z = self._z
        for comp in self._active:
            comp.rescale(z)
        self._sink *= z
        self._z = 1.0

    def decide(self) -> Decision:
        """The decision for the current belief (see :mod:`sprint_map.hmm.decision`).

        Notes
        -----
        O(live) for the candidate search (a max, a comparison and a ``nonzero`` over the live
        slots of each active component) plus O(m (r + h d log d)) for the place masses of the m
        candidates.
        """
        cfg = self.config
        z = self._z
        views = [c.view(z) for c in self._active]
        candidates = top_candidates(views, cfg.decision_candidates)
        return decide(views, candidates, self._sink * z, cfg.place_radius, cfg.place_hops,
                      cfg.min_confidence, len(self._active), self._n_propagated)

    # ------------------------------------------------------------------ map changes
    def invalidate(self, component_ids: Iterable[int] | None = None) -> None:
        """Re-read components after the map changed (sequences added, components merged).

        Drops ``component_ids`` (all if None) from the cache, then re-maps the belief of every
        active component onto the source's current components by vertex id (vertex ids are
        stable, component ids may change on a merge). The belief is preserved exactly.

        Notes
        -----
        O(live) plus the loads of the affected components.
        """
        if component_ids is None:
            self.cache.clear()
            self._transitions.clear()
        else:
            ids = [int(cid) for cid in component_ids]
            self.cache.invalidate(ids)
            for cid in ids:
                self._transitions.pop(cid, None)
        self._rescale()
        comps = list(self._active)
        if not comps:
            return
        vid_parts: list[np.ndarray] = []
        prob_parts: list[np.ndarray] = []
        for c in comps:
            slots = c.live_slots()
            vals = c.x[slots]
            held = vals > 0.0
            vid_parts.append(c.trans.vertex_of_slots(slots[held]))
            prob_parts.append(vals[held])
        vids = np.concatenate(vid_parts)
        probs = np.concatenate(prob_parts)
        self._active.clear()
        if not vids.size:
            return
        comp_ids = np.asarray(self.source.components_of(vids))
        for cid in np.unique(comp_ids).tolist():
            comp = self._active.add(self._transition(int(cid)))
            sel = comp_ids == cid
            slots = comp.trans.slots_of(vids[sel])
            order = np.argsort(slots, kind="stable")
            slots = slots[order]
            comp.x[slots] = probs[sel][order]
            lo, hi, _, _ = runs(slots, comp.trans.gap)
            comp.set_windows(lo, hi)
            comp.mass = float(probs[sel].sum())


def inject_many(groups: list[tuple[ActiveComponent, np.ndarray, np.ndarray]], liks: np.ndarray,
                inject: float) -> None:
    """Step 4 for the hits of ``groups`` (:meth:`ActiveSet.locate_many`): each hit's raw belief
    becomes ``(x + inject) * lik``, its component's mass follows, and a hit outside the windows
    is queued to open one. The same floats as the hit-by-hit loop (the mass adds the changes
    one by one, in hit order; that loop also queues the hits inside a component's several
    windows, which change nothing when the windows are rebuilt). O(hits), a few numpy calls
    per component."""
    for comp, slots, at in groups:
        x = comp.x
        old = x[slots]
        new = (old + inject) * liks[at]
        x[slots] = new
        mass = comp.mass
        for change in (new - old).tolist():
            mass += change
        comp.mass = mass
        if comp.n_windows == 1:
            outside = (slots < comp.a) | (slots >= comp.b)
        elif comp.n_windows:
            lo, hi = comp.lo, comp.hi
            w = lo.searchsorted(slots, "right") - 1
            outside = (w < 0) | (slots >= hi[np.maximum(w, 0)])
        else:
            comp.pending.extend(slots.tolist())
            continue
        if outside.any():
            comp.pending.extend(slots[outside].tolist())
