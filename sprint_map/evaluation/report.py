"""Writing evaluation results: JSON, a markdown table and PNG plots (matplotlib, no display)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.storage.atomic import publish

COLUMNS = (
    ("query", "query"),
    ("frames", "frames"),
    ("frames_with_match", "with match"),
    ("knn_recall@1", "k-NN@1"),
    ("knn_recall@5", "k-NN@5"),
    ("knn_recall@10", "k-NN@10"),
    ("sprint_recall@1", "SPRINT@1"),
    ("pr_auc", "PR AUC"),
    ("recall@100%precision", "R@P=1"),
    ("no_match_on_novel", "novel->no match"),
    ("active_vertices_mean", "active verts"),
)


def markdown_table(results: dict[str, Any]) -> str:
    """The results as a markdown table: one row per query traversal plus the overall row."""
    rows = list(results["queries"])
    if len(rows) > 1:
        rows.append(results["overall"])
    head = "| " + " | ".join(title for _, title in COLUMNS) + " |"
    rule = "| " + " | ".join("---" for _ in COLUMNS) + " |"
    lines = [head, rule]
    for row in rows:
        cells = []
        for key, _ in COLUMNS:
            value = row.get(key, "")
            if isinstance(value, float) and key not in ("active_vertices_mean",):
                cells.append(f"{100 * value:.1f} %")
            else:
                cells.append(str(value))
        lines.append("| " + " | ".join(cells) + " |")
    o = results["overall"]
    lines += [
        "",
        f"Per-frame latency (ms), retrieval p50/p99: {o['retrieval_ms']['p50']} / "
        f"{o['retrieval_ms']['p99']}; HMM p50/p99: {o['hmm_ms']['p50']} / {o['hmm_ms']['p99']}.",
        f"Protocol {results['protocol']}, ground truth {results['ground_truth']}, "
        f"{results['seconds']} s in all.",
    ]
    return "\n".join(lines) + "\n"


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
    publish(paths["json"], lambda p: p.write_text(json.dumps(public, indent=2)))
    publish(paths["markdown"], lambda p: p.write_text(markdown_table(results)))
    _plots(results, paths)
    return paths


def _plots(results: dict[str, Any], paths: dict[str, Path]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for name, curve in results["_curves"].items():
        ax.plot(curve.recall, curve.precision, label=f"{name} (AUC {curve.auc:.2f})")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1.02),
           title="SPRINT precision-recall (threshold on place probability)")
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

    fig, ax = plt.subplots(figsize=(6, 4))
    lat = results["_latency"]
    for key in ("retrieval_ms", "hmm_ms"):
        values = np.asarray(lat[key]) if lat[key] else np.zeros(1)
        ax.hist(np.maximum(values, 1e-4), bins=list(np.logspace(-4, 3, 60)), alpha=0.6, label=key)
    ax.set(xscale="log", xlabel="ms per frame", ylabel="frames",
           title="Per-frame latency, retrieval and HMM apart")
    ax.legend()
    fig.tight_layout()
    fig.savefig(paths["latency"], dpi=110)
    plt.close(fig)
