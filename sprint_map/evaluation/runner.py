"""Running the evaluation protocols on a data set.

``pairs`` (the paper's Table I): one database traversal is mapped, one query traversal is
localised against it. ``lifelong`` (the paper's Mapillary protocol): traversals are taken in
order; each is localised against the map of all earlier ones and then merged into it with
:meth:`SprintMap.ingest <sprint_map.map.SprintMap.ingest>`.

Every query frame is answered three ways over the same map: by exact k-NN (FAISS flat search,
the baseline); by SPRINT, streamed frame by frame as a vehicle would (``sprint_recall@1``, and
the latencies reported are per-frame latencies, not batch averages); and by SPRINT's smoothed
decisions, made once the whole drive has been seen (``smoothed_recall@1``), which the merge
rule (:mod:`sprint_map.merge.rule`) turns into edges. The merge metrics
(:func:`sprint_map.evaluation.metrics.merge_metrics`: ``merge_precision``, ``merge_recall``,
``edges_added``, ``edges_wrong``, ``novel_merged``) score those edges:

- ``lifelong``: the decisions and the mask of the ingest that committed the drive;
  ``edges_added`` is the commit's count.
- ``pairs``: the query is not merged; the merge rule is applied to its smoothed decisions
  (:meth:`MapService.select_merges <sprint_map.facade.service.MapService.select_merges>`), and
  ``edges_added``/``edges_wrong`` count the edges that merging it *would* add (2 per merged
  decision when ``config.merge.both_ways``).

A decision is correct when its place is a true match of its frame by the data set's ground
truth; a merged decision on a frame without a true match is wrong.

With ``gnss_sigma`` > 0 the protocol runs a second time, GNSS-aided: every traversal gets fixes
simulated from its ground-truth positions (:func:`sprint_map.frontend.gnss.simulate_fixes`:
drift, dropouts, multipath), which the maps store as its positions and its localisation and
merge use (:mod:`sprint_map.localize.gnss`). The results gain ``"gnss"``: ``sigma_m``, the
receiver ``model``, its ``seed``, and ``queries`` / ``overall`` rows with the same keys as the
image-only ones (``results["gnss"]["overall"]["merge_precision"]``, ...).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import (
    Dataset,
    FrameDecision,
    GnssModel,
    GroundTruth,
    HMMConfig,
    Traversal,
    simulate_fixes,
)
from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.evaluation.metrics import merge_metrics, percentiles, pr_curve, recall_at_k
from sprint_map.map import SprintMap
from sprint_map.util import dataclass_dict
from sprint_map.util.arrays import Descriptors

__all__ = ["Describe", "EvalOptions", "Log", "PROTOCOLS", "QueryResult", "config_for", "describe",
           "describe_with_thumbnails", "evaluate_query", "run_evaluation"]

PROTOCOLS = ("lifelong", "pairs")
Log = Callable[[str], None]


@dataclass(frozen=True)
class EvalOptions:
    """What to evaluate.

    Parameters
    ----------
    protocol : {"lifelong", "pairs"}
    database, query : str, optional
        ``pairs``: traversal names (default the first and second traversal).
    both_directions : bool
        ``pairs``: also evaluate with database and query swapped.
    stride : int
        Keep every ``stride``-th frame of every traversal.
    ks : tuple of int
        k of the k-NN recall baselines.
    gnss_sigma : float
        Metres (per axis) of the simulated GNSS fixes of the aided run; 0: no aided run.
    gnss_seed : int
        Seed of the simulated fixes (traversal ``i`` draws from ``(gnss_seed, i)``).
    """

    protocol: str = "lifelong"
    database: str | None = None
    query: str | None = None
    both_directions: bool = False
    stride: int = 1
    ks: tuple[int, ...] = (1, 5, 10)
    gnss_sigma: float = 0.0
    gnss_seed: int = 0

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise InputError(f"protocol must be one of {', '.join(PROTOCOLS)}")
        if not (np.isfinite(self.gnss_sigma) and self.gnss_sigma >= 0):
            raise InputError(f"--gnss-sigma must be a finite number >= 0 metres (0: off), got "
                             f"{self.gnss_sigma}")


@dataclass
class QueryResult:
    """Per-frame answers of one query traversal against one map state."""

    query: str
    database: list[str]
    knn_correct: np.ndarray  # (Q, K) bool, ranked hits
    has_match: np.ndarray  # (Q,) bool
    best_correct: np.ndarray  # (Q,) bool: SPRINT's most probable place is a true match
    accepted: np.ndarray  # (Q,) bool: SPRINT answered "match" (not "no match")
    prob: np.ndarray  # (Q,) float: SPRINT's place probability
    retrieval_ms: list[float]
    hmm_ms: list[float]
    active_vertices: list[int]
    map_vertices: int
    #: Edges the query's commit added (lifelong); None when it was not merged (pairs).
    edges_added: int | None = None
    #: (Q,) bool: the smoothed decision's most probable place is a true match.
    smoothed_best_correct: np.ndarray | None = None
    #: (Q,) bool: the merge rule selects the smoothed decision (it becomes, or would become,
    #: edges).
    merged: np.ndarray | None = None
    #: (Q,) bool: the smoothed decision's place (``seq_id``, ``image_id``) is a true match.
    merged_correct: np.ndarray | None = None
    #: Edges one merged decision makes: 2 with ``merge_both_ways``, else 1.
    edges_per_decision: int = 2
    #: (Q,) bool: frames on an identical twin (a place pixel- or latent-identical to another,
    #: declared by the data set, :meth:`Dataset.twin_frames`); None when it declares none.
    twin: np.ndarray | None = None

    def score_merge(self, decisions: list[FrameDecision], merged: np.ndarray, gt: GroundTruth,
                    names: dict[int, str], edges_per_decision: int) -> None:
        """Record the smoothed ``decisions`` of this query and the merge rule's verdict on them.

        Parameters
        ----------
        decisions : list of FrameDecision
            One per query frame, in order (``IngestResult.decisions`` or
            ``SprintMap.localize(..., smooth=True)``).
        merged : (Q,) bool
            Which of them the merge rule selects.
        gt : GroundTruth
        names : dict
            Sequence id -> traversal name, of the map the decisions were made against.
        edges_per_decision : int
            Edges one merged decision makes.
        """
        n = len(self.has_match)
        if len(decisions) != n or len(merged) != n:
            raise ValueError(f"{self.query}: {len(decisions)} decisions and {len(merged)} merge "
                             f"verdicts for {n} frames")
        self.smoothed_best_correct = _correct(self.query, [d.best for d in decisions], gt, names)
        self.merged_correct = _correct(
            self.query, [None if d.seq_id is None or d.image_id is None else (d.seq_id, d.image_id)
                         for d in decisions], gt, names)
        self.merged = np.asarray(merged, dtype=bool).copy()
        self.edges_per_decision = edges_per_decision

    def row(self, ks: tuple[int, ...]) -> dict[str, Any]:
        """The JSON row of this query (see the module docstring for the merge metrics)."""
        knn = recall_at_k(self.knn_correct, self.has_match, ks)
        denom = max(int(self.has_match.sum()), 1)
        curve = pr_curve(self.prob, self.best_correct, self.has_match)
        accepted_tp = self.accepted & self.best_correct & self.has_match
        unscored = np.zeros(len(self.has_match), dtype=bool)
        smoothed = (self.smoothed_best_correct if self.smoothed_best_correct is not None
                    else unscored)
        merge = merge_metrics(self.merged if self.merged is not None else unscored,
                              self.merged_correct if self.merged_correct is not None else unscored,
                              self.has_match, self.edges_per_decision)
        return {
            "query": self.query,
            "database": self.database,
            "frames": int(len(self.has_match)),
            "frames_with_match": int(self.has_match.sum()),
            "map_vertices": self.map_vertices,
            **{f"knn_recall@{k}": round(v, 4) for k, v in knn.items()},
            "sprint_recall@1": round(float((self.best_correct & self.has_match).sum()) / denom, 4),
            "decision_precision": round(
                float(accepted_tp.sum()) / max(int(self.accepted.sum()), 1), 4),
            "decision_recall": round(float(accepted_tp.sum()) / denom, 4),
            "no_match_on_novel": round(float((~self.accepted & ~self.has_match).sum())
                                       / max(int((~self.has_match).sum()), 1), 4),
            "pr_auc": round(curve.auc, 4),
            "recall@100%precision": round(curve.recall_at_full_precision, 4),
            "retrieval_ms": percentiles(self.retrieval_ms),
            "hmm_ms": percentiles(self.hmm_ms),
            "active_vertices_mean": round(float(np.mean(self.active_vertices or [0])), 1),
            "active_vertices_max": int(np.max(self.active_vertices or [0])),
            "smoothed_recall@1": round(float((smoothed & self.has_match).sum()) / denom, 4),
            "merge_precision": round(merge.precision, 4),
            "merge_recall": round(merge.recall, 4),
            "merged_decisions": merge.merged,
            "edges_added": merge.edges_added if self.edges_added is None else self.edges_added,
            "edges_wrong": merge.edges_wrong,
            "novel_merged": round(merge.novel_merged, 4),
            **self._twin_counts(),
        }

    def _twin_counts(self) -> dict[str, int]:
        """``twin_frames``, and of them ``twin_merged`` and ``twin_merged_wrong``; nothing
        when the data set declares no twins."""
        if self.twin is None:
            return {}
        merged = self.merged if self.merged is not None else np.zeros(len(self.twin), bool)
        right = (self.merged_correct if self.merged_correct is not None
                 else np.zeros(len(self.twin), bool))
        on_twin = self.twin & merged
        return {"twin_frames": int(self.twin.sum()), "twin_merged": int(on_twin.sum()),
                "twin_merged_wrong": int((on_twin & ~(right & self.has_match)).sum())}


def config_for(dataset: Dataset, descriptor: str = "auto") -> MapConfig:
    """Map config for evaluating ``dataset``: ``auto`` takes the data set's own descriptors
    (``descriptors.npy`` traversals: precomputed, of their dimension), else HoG from images."""
    first = dataset.traversals[0]
    if descriptor == "auto":
        descriptor = "precomputed" if first.kind == "npy" else "hog"
    if descriptor == "precomputed":
        return MapConfig(dim=first.open().dim)
    return MapConfig.for_descriptor(descriptor)


def describe(m: SprintMap, traversal: Traversal, stride: int) -> Descriptors:
    """Descriptors of a traversal, in the map's descriptor kind."""
    return describe_with_thumbnails(m, traversal, stride, thumbnails=False)[0]


def describe_with_thumbnails(m: SprintMap, traversal: Traversal, stride: int,
                             thumbnails: bool = True) -> tuple[Descriptors, list[bytes] | None]:
    """Descriptors of a traversal, in the map's descriptor kind, and its thumbnails (one JPEG
    per frame, as ``ingest --thumbnails`` keeps them) when it holds images or video and
    ``thumbnails`` is set; else None. The thumbnails never change a descriptor."""
    spec = m.config.descriptor_spec()
    thumbnails = thumbnails and spec is not None and traversal.kind != "npy"
    source = traversal.open(spec, stride=stride, thumbnails=thumbnails)
    rows = source.read_all()
    if rows.shape[1] != m.config.dim:
        raise InputError(f"{traversal.folder}: descriptors of dim {rows.shape[1]}, map has "
                         f"{m.config.dim}")
    return rows, (list(source.thumbnails) if source.thumbnails is not None else None)


def evaluate_query(m: SprintMap, query: str, rows: Descriptors, gt: GroundTruth,
                   ks: tuple[int, ...], hmm: HMMConfig | None, *, smooth: bool = False,
                   thumbnails: Sequence[bytes] | None = None, fixes: np.ndarray | None = None
                   ) -> tuple[QueryResult, list[FrameDecision]]:
    """Answer every frame of ``rows`` by exact k-NN and by streamed SPRINT, and score both.

    With ``smooth`` the query is also localised with the smoothed posterior over the same map
    (what :meth:`SprintMap.localize` with ``smooth=True`` gives, from the hits of the streamed
    pass) and the map's merge rule is scored on it (:meth:`QueryResult.score_merge`): what
    merging the query would add, its runs verified on ``thumbnails`` as ``ingest`` would).
    The returned decisions are the streamed (causal) ones. ``fixes``: the query's GNSS fixes
    (:meth:`SprintMap.ingest`), for SPRINT's answers (k-NN is image only).
    """
    names = {s.seq_id: s.name for s in m.sequences()}
    db_names = list(names.values())
    frames = np.arange(len(rows))
    kmax = max(ks)
    _, ids = m.search(m.service.drive_centring().apply(rows), kmax)  # in the map's space
    located = m.locate(ids[ids >= 0].ravel())
    seq = np.full(ids.shape, -1)
    img = np.full(ids.shape, -1)
    seq[ids >= 0] = [s for s, _ in located]
    img[ids >= 0] = [i for _, i in located]
    knn_correct = np.zeros(ids.shape, dtype=bool)
    for seq_id, name in names.items():
        mask = seq == seq_id
        if mask.any():
            qf = np.broadcast_to(frames[:, None], ids.shape)[mask]
            knn_correct[mask] = gt.correct(query, qf, name, img[mask])
    has_match = gt.has_match(query, frames, db_names)

    # stepped frame by frame (a vehicle's per-frame cost); hits kept for the smoothed decisions
    localizer = m.localizer(hmm, record=smooth, fixes=fixes)
    decisions = [localizer.step(row) for row in rows]
    best_correct = _correct(query, [d.best for d in decisions], gt, names)
    result = QueryResult(
        query=query,
        database=db_names,
        knn_correct=knn_correct,
        has_match=has_match,
        best_correct=best_correct,
        accepted=np.array([d.is_match for d in decisions], dtype=bool),
        prob=np.array([d.prob for d in decisions]),
        retrieval_ms=localizer.timing.retrieval_ms,
        hmm_ms=localizer.timing.hmm_ms,
        active_vertices=localizer.timing.active_vertices,
        map_vertices=m.stats()["vertices"],
    )
    if smooth:
        smoothed = m.smoothed(localizer, thumbnails=thumbnails)
        result.score_merge(smoothed, m.service.select_merges(smoothed), gt, names,
                           _edges_per_decision(m.config))
    return result, decisions


def _correct(query: str, places: list[tuple[int, int] | None], gt: GroundTruth,
             names: dict[int, str]) -> np.ndarray:
    """Whether each frame's place (``(seq_id, image_id)``, or None) is a true match of it."""
    out = np.zeros(len(places), dtype=bool)
    for frame, place in enumerate(places):
        if place is not None:
            seq_id, image_id = place
            out[frame] = bool(gt.correct(query, frame, names[seq_id], image_id))
    return out


def _edges_per_decision(config: MapConfig) -> int:
    """Edges one merged decision makes (:func:`sprint_map.merge.commit.merge_edges`)."""
    return 2 if config.merge.both_ways else 1


#: How a traversal becomes rows (and thumbnails): :func:`describe_with_thumbnails` by default.
Describe = Callable[[SprintMap, Traversal, int], tuple[Descriptors, list[bytes] | None]]


def run_evaluation(dataset: Dataset, work_dir: Path, config: MapConfig, options: EvalOptions,
                   hmm: HMMConfig | None = None, log: Log = lambda _: None,
                   describe: Describe | None = None) -> dict[str, Any]:
    """Run ``options.protocol`` on ``dataset``, building maps under ``work_dir``.

    ``describe(map, traversal, stride)`` gives a traversal's descriptors and thumbnails
    (default :func:`describe_with_thumbnails`; a benchmark passes a cached one). Returns the
    results as a JSON-ready dict: one row per query traversal plus an ``overall`` row over all
    query frames.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    gt = dataset.ground_truth(options.stride)
    started = time.perf_counter()
    described: dict[str, tuple[Descriptors, list[bytes] | None]] = {}

    def describe_once(m: SprintMap, traversal: Traversal, stride: int
                      ) -> tuple[Descriptors, list[bytes] | None]:
        if traversal.name not in described:  # the aided run reads the same rows
            described[traversal.name] = (describe or describe_with_thumbnails)(m, traversal,
                                                                               stride)
        return described[traversal.name]

    results = _run_protocol(dataset, work_dir, config, options, hmm, log, describe_once, gt,
                            None)
    aided: list[QueryResult] = []
    model = GnssModel(sigma=options.gnss_sigma) if options.gnss_sigma > 0 else None
    if model is not None:
        index = {name: i for i, name in enumerate(dataset.names)}

        def fixes_of(traversal: Traversal) -> np.ndarray:
            truth = traversal.positions(options.stride, dataset.geo_frame())
            if truth is None:
                raise InputError(f"{traversal.folder}: --gnss-sigma simulates fixes from "
                                 "positions, and this traversal has none")
            seed = np.random.SeedSequence([options.gnss_seed, index[traversal.name]])
            return simulate_fixes(truth[:, 1:3], model, seed)

        log(f"GNSS-aided run: fixes simulated at sigma {options.gnss_sigma} m")
        aided = _run_protocol(dataset, work_dir, config, options, hmm, log, describe_once, gt,
                              fixes_of)
    rows_out = [r.row(options.ks) for r in results]
    overall = _overall(results, options.ks)
    out = {
        "dataset": str(dataset.path),
        "protocol": options.protocol,
        "stride": options.stride,
        "ground_truth": gt.spec.to_dict(),
        "config": config.to_dict(),
        "hmm": (hmm or config.hmm).to_dict(),
        "merge_rule": config.merge.reported(),
        "queries": rows_out,
        "overall": overall,
        "recall_by_traversal": [
            {"traversal": i, "query": row["query"], "map_vertices": row["map_vertices"],
             **{k: row[k] for k in ("knn_recall@1", "sprint_recall@1", "smoothed_recall@1")
                if k in row}}
            for i, row in enumerate(rows_out, start=1 if options.protocol == "lifelong" else 0)],
        "seconds": round(time.perf_counter() - started, 2),
        "_curves": {r.query: pr_curve(r.prob, r.best_correct, r.has_match) for r in results},
        "_latency": {"retrieval_ms": sum((r.retrieval_ms for r in results), []),
                     "hmm_ms": sum((r.hmm_ms for r in results), [])},
    }
    if model is not None:
        out["gnss"] = {"sigma_m": options.gnss_sigma, "seed": options.gnss_seed,
                       "model": model.to_dict(), "config": dataclass_dict.to_dict(config.gnss),
                       "queries": [r.row(options.ks) for r in aided],
                       "overall": _overall(aided, options.ks)}
    return out


FixesOf = Callable[[Traversal], np.ndarray]


def _run_protocol(dataset: Dataset, work_dir: Path, config: MapConfig, options: EvalOptions,
                  hmm: HMMConfig | None, log: Log, describe_fn: Describe, gt: GroundTruth,
                  fixes_of: FixesOf | None) -> list[QueryResult]:
    """One run of ``options.protocol``: image only (``fixes_of`` None; the maps store the
    ground-truth positions), or GNSS-aided (each traversal's fixes ``fixes_of(traversal)`` are
    what its sequence stores and what its localisation reads; maps in ``*-gnss`` folders)."""
    suffix = "" if fixes_of is None else "-gnss"
    results: list[QueryResult] = []

    def placed(traversal: Traversal) -> tuple[np.ndarray | None, np.ndarray | None]:
        if fixes_of is None:
            return _xy(traversal.positions(options.stride, dataset.geo_frame())), None
        fixes = fixes_of(traversal)
        return fixes[:, :2], fixes

    if options.protocol == "pairs":
        names = dataset.names
        if len(names) < 2 and not (options.database and options.query):
            raise InputError(f"{dataset.path}: the pairs protocol needs two traversals")
        db = options.database or names[0]
        query = options.query or next(n for n in names if n != db)
        pairs = [(db, query)] + ([(query, db)] if options.both_directions else [])
        for db_name, q_name in pairs:
            map_dir = _fresh(work_dir / f"map-{db_name}{suffix}")
            with SprintMap.create(map_dir, config) as m:
                log(f"mapping {db_name}")
                db_rows, db_thumbs = describe_fn(m, dataset[db_name], options.stride)
                m.add_sequence(db_rows, name=db_name, thumbnails=db_thumbs,
                               positions=placed(dataset[db_name])[0])
                log(f"localising {q_name} against {db_name}")
                rows, thumbs = describe_fn(m, dataset[q_name], options.stride)
                results.append(evaluate_query(m, q_name, rows, gt, options.ks, hmm,
                                              smooth=True, thumbnails=thumbs,
                                              fixes=placed(dataset[q_name])[1])[0])
                results[-1].twin = dataset.twin_frames(q_name, options.stride)
    else:
        map_dir = _fresh(work_dir / f"map-lifelong{suffix}")
        with SprintMap.create(map_dir, config) as m:
            for i, traversal in enumerate(dataset):
                rows, thumbs = describe_fn(m, traversal, options.stride)
                positions, fixes = placed(traversal)
                if i == 0:
                    log(f"mapping {traversal.name} (first traversal)")
                    m.add_sequence(rows, name=traversal.name, positions=positions,
                                   thumbnails=thumbs)
                    continue
                log(f"localising {traversal.name} against {i} earlier traversal(s), then merging")
                seq_names = {s.seq_id: s.name for s in m.sequences()}
                result, _ = evaluate_query(m, traversal.name, rows, gt, options.ks, hmm,
                                           fixes=fixes)
                ingested = m.ingest(rows, name=traversal.name, positions=positions, hmm=hmm,
                                    thumbnails=thumbs, fixes=fixes)
                result.score_merge(ingested.decisions, ingested.merged, gt, seq_names,
                                   _edges_per_decision(m.config))
                result.edges_added = ingested.edges_added
                result.twin = dataset.twin_frames(traversal.name, options.stride)
                results.append(result)
    return results


def _overall(results: list[QueryResult], ks: tuple[int, ...]) -> dict[str, Any]:
    if not results:
        return {}
    joined = QueryResult(
        query="overall",
        database=sorted({n for r in results for n in r.database}),
        knn_correct=np.concatenate([r.knn_correct for r in results]),
        has_match=np.concatenate([r.has_match for r in results]),
        best_correct=np.concatenate([r.best_correct for r in results]),
        accepted=np.concatenate([r.accepted for r in results]),
        prob=np.concatenate([r.prob for r in results]),
        retrieval_ms=sum((r.retrieval_ms for r in results), []),
        hmm_ms=sum((r.hmm_ms for r in results), []),
        active_vertices=sum((r.active_vertices for r in results), []),
        map_vertices=max(r.map_vertices for r in results),
        edges_added=(None if any(r.edges_added is None for r in results)
                     else sum(r.edges_added or 0 for r in results)),
        smoothed_best_correct=_joined(results, "smoothed_best_correct"),
        merged=_joined(results, "merged"),
        merged_correct=_joined(results, "merged_correct"),
        edges_per_decision=results[0].edges_per_decision,
        twin=(None if all(r.twin is None for r in results) else _joined(results, "twin")),
    )
    return joined.row(ks)


def _joined(results: list[QueryResult], field: str) -> np.ndarray:
    """A per-frame field of every query, end to end (all False for a query that lacks it)."""
    parts = []
    for r in results:
        value = getattr(r, field)
        parts.append(value if value is not None else np.zeros(len(r.has_match), dtype=bool))
    return np.concatenate(parts)


def _xy(positions: np.ndarray | None) -> np.ndarray | None:
    """Positions as the map stores them: drop the leading frame-number column."""
    return None if positions is None else positions[:, 1:]


def _fresh(path: Path) -> Path:
    """The evaluation owns its work directory: a map left by an earlier run is replaced."""
    if path.exists():
        shutil.rmtree(path)
    return path
