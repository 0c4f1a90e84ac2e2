"""Evaluating on a VPR-layout data set (``eval DATA --layout vpr``): recall@1/5/10/20.

The database folder becomes one map sequence (with its positions); the query folder is
localised against it, each query frame answered two ways:

- ``knn``: the exact k-NN list (the map's flat search) of the frame's descriptor;
- ``sprint``: SPRINT streamed over the queries as one drive (in timestamp order when the names
  carry timestamps, else file-name order): its most probable place first, then the k-NN list
  without that place (the HMM decides one place; the list behind it is retrieval's).

A database image is a positive of a query when their UTM positions are at most ``radius_m``
apart (25 m by default, the benchmarks' rule); recall@N is the share of the queries with at
least one positive whose first N answers hold one (queries without a positive are counted
apart, as the benchmarks' splits have none). Cost: one exact search per query (O(Q * D * dim))
plus SPRINT's per-frame step; positives by a KD-tree, O(Q log D).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sprint_map import HMMConfig, VprDataset
from sprint_map.config import MapConfig
from sprint_map.errors import ConfigError, InputError
from sprint_map.map import SprintMap
from sprint_map.util.atomic import publish_bytes

__all__ = ["RECALL_NS", "markdown_recall", "recall_at_n", "run_vpr_evaluation"]

RECALL_NS = (1, 5, 10, 20)


def recall_at_n(answers: np.ndarray, positives: list[set[int]], ns: tuple[int, ...] = RECALL_NS
                ) -> dict[str, float]:
    """``{"recall@N": share}`` over the queries with a positive; ``answers`` is ``(Q, K)``
    database indices by rank (-1: none). O(Q * K)."""
    has = [i for i, p in enumerate(positives) if p]
    out = {}
    for n in ns:
        hit = sum(any(int(a) in positives[i] for a in answers[i, :n] if a >= 0) for i in has)
        out[f"recall@{n}"] = round(hit / max(len(has), 1), 4)
    return out


def _sprint_lists(best: list[int | None], knn: np.ndarray) -> np.ndarray:
    """SPRINT's place first, then the k-NN list without it (same width). O(Q * K)."""
    out = np.full(knn.shape, -1, dtype=np.int64)
    for i, place in enumerate(best):
        row = ([place] if place is not None else []) + [int(a) for a in knn[i]
                                                        if a >= 0 and a != place]
        out[i, : min(len(row), knn.shape[1])] = row[: knn.shape[1]]
    return out


def run_vpr_evaluation(data: VprDataset, out_dir: Path, config: MapConfig,
                       hmm: HMMConfig | None = None, radius_m: float = 25.0,
                       log: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """Map the database, answer the queries, write ``out_dir/results.json``; return it.

    The map is built in ``out_dir/map-vpr`` (replaced if there). See the module docstring.

    Raises
    ------
    ConfigError
        ``radius_m`` not a positive finite number of metres (before any work).
    InputError
        The map's frames not in the data set's order (the one VPR rule,
        :func:`~sprint_map.frontend.vpr.is_vpr_folder`, makes them so).
    """
    if (isinstance(radius_m, bool) or not isinstance(radius_m, int | float)
            or not math.isfinite(radius_m) or radius_m <= 0):
        raise ConfigError(f"--radius must be a positive number of metres, got {radius_m!r}")
    started = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    map_dir = out_dir / "map-vpr"
    if map_dir.exists():
        shutil.rmtree(map_dir)
    tree = cKDTree(data.database_utm)
    positives = [set(map(int, tree.query_ball_point(q, radius_m))) for q in data.queries_utm]
    k = max(RECALL_NS)
    with SprintMap.create(map_dir, config) as m:
        log(f"mapping {len(data.database)} database images")
        db = m.open_source(data.database[0].parent)
        query_source = m.open_source(data.queries[0].parent)
        for source, listed in ((db, data.database), (query_source, data.queries)):
            if getattr(source, "files", None) != listed:  # vertex id = index in the data set
                raise InputError(f"{listed[0].parent}: the map's frame order is not the data "
                                 "set's")
        m.add_sequence(db.read_all(), name="database",
                       positions=m.metric_positions(db.positions))
        log(f"localising {len(data.queries)} queries")
        queries = query_source.read_all()
        # k-NN in the map's space: the queries as one drive, centred (SPRINT's localizer
        # centres them itself as it steps them, in this order)
        _, ids = m.search(m.service.drive_centring().apply(queries), min(k, len(data.database)))
        knn = np.full((len(queries), k), -1, dtype=np.int64)
        knn[:, : ids.shape[1]] = ids  # one sequence from vertex 0: vertex id = database index
        localizer = m.localizer(hmm)
        decisions = [localizer.step(row) for row in queries]
        best = [None if d.best is None else int(d.best[1]) for d in decisions]
    results = {
        "layout": "vpr",
        "dataset": str(data.path),
        "radius_m": radius_m,
        "order": {"database": data.database_order, "queries": data.queries_order},
        "database": len(data.database),
        "queries": len(data.queries),
        "queries_with_positives": sum(1 for p in positives if p),
        "utm_zone": f"{data.zone}{'S' if data.south else 'N'}",
        "descriptor": config.descriptor,
        "dim": config.dim,
        "methods": {"knn": recall_at_n(knn, positives),
                    "sprint": recall_at_n(_sprint_lists(best, knn), positives)},
        "seconds": round(time.perf_counter() - started, 2),
    }
    publish_bytes(out_dir / "results.json", (json.dumps(results, indent=2) + "\n").encode())
    return results


def markdown_recall(results: dict[str, Any]) -> str:
    """The recall table of :func:`run_vpr_evaluation`'s results, in markdown."""
    header = "| method | " + " | ".join(f"R@{n}" for n in RECALL_NS) + " |"
    rows = [header, "|---" * (len(RECALL_NS) + 1) + "|"]
    for method, recall in results["methods"].items():
        rows.append(f"| {method} | " + " | ".join(f"{recall[f'recall@{n}']:.4f}"
                                                  for n in RECALL_NS) + " |")
    return "\n".join(rows + [f"frame order: database by {results['order']['database']}, "
                             f"queries by {results['order']['queries']}"])
