"""Writing evaluation results: JSON, a markdown table and PNG plots (matplotlib, no display)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.util.atomic import publish

__all__ = ["COLUMNS", "latency_bins", "latency_figure", "markdown_table", "write_report"]

#: The table's columns: (key of a results row, title). ``edges (wrong)`` joins two keys.
COLUMNS = (
    ("query", "query"),
    ("frames", "frames"),
    ("frames_with_match", "with match"),
    ("knn_recall@1", "k-NN@1"),
    ("knn_recall@10", "k-NN@10"),
    ("sprint_recall@1", "SPRINT@1"),
    ("smoothed_recall@1", "smoothed@1"),
    ("pr_auc", "PR AUC"),
    ("recall@100%precision", "R@P=1"),
    ("no_match_on_novel", "novel->no match"),
    ("merge_precision", "merge P"),
    ("merge_recall", "merge R"),
    ("edges_added", "edges (wrong)"),
    ("novel_merged", "novel merged"),
)


def _cell(row: dict[str, Any], key: str) -> str:
    value = row.get(key, "")
    if key == "edges_added" and value != "":
        return f"{value} ({row.get('edges_wrong', '?')})"
    if isinstance(value, float):
        return f"{100 * value:.1f} %"
    return str(value)


def markdown_table(results: dict[str, Any]) -> str:
    """The results as a markdown table: one row per query traversal plus the overall row,
    then latency, the merge rule's parameters and the protocol."""
    rows = list(results["queries"])
    if len(rows) > 1:
        rows.append(results["overall"])
    head = "| " + " | ".join(title for _, title in COLUMNS) + " |"
    rule = "| " + " | ".join("---" for _ in COLUMNS) + " |"
    lines = [head, rule]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row, key) for key, _ in COLUMNS) + " |")
    o = results["overall"]
    merge_rule = results.get("merge_rule", {})
    params = ", ".join(f"{k.removeprefix('merge_')} {v}" for k, v in merge_rule.items())
    committed = ("committed by each query's ingest" if results["protocol"] == "lifelong"
                 else "that merging the query would add (pairs: nothing is merged)")
    lines += [
        "",
        "SPRINT@1: the causal (streamed) decisions; smoothed@1: the forward-backward smoothed "
        "decisions the merge rule reads. Merge P/R: precision of the decisions the rule merges, "
        f"and their correct ones over frames with a match; edges (wrong): the edges {committed}; "
        "novel merged: frames without a true match whose decision was merged.",
        f"Merge rule: {params}." if params else "Merge rule: not reported.",
        f"Per-frame latency (ms), retrieval p50/p99: {o['retrieval_ms']['p50']} / "
        f"{o['retrieval_ms']['p99']}; HMM p50/p99: {o['hmm_ms']['p50']} / {o['hmm_ms']['p99']}; "
        f"active vertices mean {o['active_vertices_mean']}, max {o['active_vertices_max']}.",
        f"Protocol {results['protocol']}, ground truth {results['ground_truth']}, "
        f"{results['seconds']} s in all.",
    ]
    if "gnss" in results:
        lines += ["", *_gnss_table(results)]
    return "\n".join(lines) + "\n"


#: The side-by-side table of an evaluation with ``--gnss-sigma``.
GNSS_COLUMNS = (("sprint_recall@1", "SPRINT@1"), ("smoothed_recall@1", "smoothed@1"),
                ("merge_precision", "merge P"), ("merge_recall", "merge R"),
                ("edges_added", "edges (wrong)"), ("novel_merged", "novel merged"))


def _gnss_table(results: dict[str, Any]) -> list[str]:
    """Image only beside GNSS-aided, per query and overall (``results["gnss"]``)."""
    gnss = results["gnss"]
    lines = [f"GNSS-aided beside image only (fixes simulated at sigma {gnss['sigma_m']} m, "
             "seed {}):".format(gnss["seed"]), "",
             "| query | run | " + " | ".join(t for _, t in GNSS_COLUMNS) + " |",
             "| --- | --- | " + " | ".join("---" for _ in GNSS_COLUMNS) + " |"]
    pairs = list(zip(results["queries"], gnss["queries"], strict=True))
    if len(pairs) > 1:
        pairs.append((results["overall"], gnss["overall"]))
    for plain, aided in pairs:
        for run, row in (("image only", plain), ("GNSS-aided", aided)):
            lines.append(f"| {row['query']} | {run} | "
                         + " | ".join(_cell(row, k) for k, _ in GNSS_COLUMNS) + " |")
    return lines


def write_report(results: dict[str, Any], out_dir: Path) -> dict[str, Path]:
    """Write ``results.json``, ``results.md`` and the plots into ``out_dir``; return the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    public = {k: v for k, v in results.items() if not k.startswith("_")}
    paths = {
        "json": out_dir / "results.json",
        "markdown": out_dir / "results.md",
        "pr_curve": out_dir / "pr_curve.png",
        "recall": out_dir / "recall.png",
        "latency": out_dir / "latency.png",
    }
    if results["protocol"] == "lifelong" and results.get("recall_by_traversal"):
        paths["recall_by_traversal"] = out_dir / "recall_by_traversal.png"
    publish(paths["json"], lambda p: p.write_text(json.dumps(public, indent=2)))
    publish(paths["markdown"], lambda p: p.write_text(markdown_table(results)))
    _plots(results, paths)
    return paths


def _plots(results: dict[str, Any], paths: dict[str, Path]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    rows = {q["query"]: q for q in results["queries"]}
    for name, curve in results["_curves"].items():
        (line,) = ax.plot(curve.recall, curve.precision, label=f"{name} (AUC {curve.auc:.2f})")
        if "merge_precision" in rows.get(name, {}):
            ax.plot(rows[name]["merge_recall"], rows[name]["merge_precision"], "o",
                    color=line.get_color(), markeredgecolor="black")
    overall = results["overall"]
    if "merge_precision" in overall:
        ax.plot(overall["merge_recall"], overall["merge_precision"], "*", color="black",
                markersize=12, label="merge rule, overall (dots: per query)")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1.02),
           title="SPRINT precision-recall (causal, threshold on place probability)\n"
                 "and the merge rule's operating point (smoothed decisions)")
    ax.title.set_fontsize(9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(paths["pr_curve"], dpi=110)
    plt.close(fig)

    queries = results["queries"]
    keys = [k for k in ("knn_recall@1", "knn_recall@5", "knn_recall@10", "sprint_recall@1")
            if k in queries[0]] if queries else []
    fig, ax = plt.subplots(figsize=(max(5.0, 1.2 * len(queries) + 2), 4))
    width = 0.8 / max(len(keys), 1)
    x = np.arange(len(queries))
    for j, key in enumerate(keys):
        ax.bar(x + j * width, [100 * q[key] for q in queries], width, label=key)
    ax.set_xticks(x + width * (len(keys) - 1) / 2, [q["query"] for q in queries], fontsize=7,
                  rotation=20)
    ax.set(ylabel="recall (%)", ylim=(0, 100), title="k-NN versus SPRINT")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(paths["recall"], dpi=110)
    plt.close(fig)

    if "recall_by_traversal" in paths:
        _recall_by_traversal(results["recall_by_traversal"], paths["recall_by_traversal"], plt)

    fig = latency_figure(results["_latency"], plt)
    fig.savefig(paths["latency"], dpi=110)
    plt.close(fig)


def latency_bins(series: list[Any], bins: int = 60) -> np.ndarray:
    """Log-spaced histogram bin edges (ms) spanning the positive values of ``series`` (a
    little beyond its smallest and largest), so the plot's axis is the data's range, not a
    fixed 1e-4 to 1e3 ms; a zero (a frame with nothing to search) sits in the first bin.
    O(values)."""
    positive = np.concatenate([np.asarray(v, dtype=np.float64).ravel() for v in series]
                              + [np.empty(0)])
    positive = positive[np.isfinite(positive) & (positive > 0)]
    lo, hi = (float(positive.min()), float(positive.max())) if positive.size else (1e-3, 1.0)
    lo, hi = lo / 1.25, max(hi * 1.25, lo * 10)
    return np.logspace(np.log10(lo), np.log10(hi), bins)


def latency_figure(lat: dict[str, Any], plt: Any) -> Any:
    """The per-frame latency histogram (retrieval and HMM apart) on a log axis spanning the
    data (:func:`latency_bins`); returns the matplotlib figure."""
    fig, ax = plt.subplots(figsize=(6, 4))
    keys = ("retrieval_ms", "hmm_ms")
    edges = latency_bins([lat[key] for key in keys])
    for key in keys:
        values = np.asarray(lat[key], dtype=np.float64) if lat[key] else np.zeros(0)
        ax.hist(np.clip(values, edges[0], edges[-1]), bins=list(edges), alpha=0.6, label=key)
    ax.set(xscale="log", xlim=(edges[0], edges[-1]), xlabel="ms per frame", ylabel="frames",
           title="Per-frame latency, retrieval and HMM apart")
    ax.legend()
    fig.tight_layout()
    return fig


def _recall_by_traversal(rows: list[dict[str, Any]], path: Path, plt: Any) -> None:
    """Recall@1 of each traversal in the order it was localised: does the map degrade as it
    grows?"""
    fig, ax = plt.subplots(figsize=(max(5.0, 0.5 * len(rows) + 3), 4))
    x = [r["traversal"] for r in rows]
    for key, style in (("knn_recall@1", "s:"), ("sprint_recall@1", "o-"),
                       ("smoothed_recall@1", "^--")):
        if all(key in r for r in rows):
            ax.plot(x, [100 * r[key] for r in rows], style, label=key)
    ax.set_xticks(x, [f"{r['traversal']}\n{r['query']}" for r in rows], fontsize=7)
    ax.set(xlabel="traversal (in the order merged)", ylabel="recall@1 (%)", ylim=(0, 100),
           title="Recall@1 per traversal as the map grows")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
