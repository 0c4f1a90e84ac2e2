"""A drive against the drives it matched: similarity matrices, decision paths, precision/recall.

The matrix between drive ``S`` (rows) and drive ``T`` (columns) is computed from the stored
descriptors: ``S`` and ``T`` are sampled to at most ``size`` evenly spaced frames each and
every sampled pair's squared-L2 distance is computed exactly, then mapped to a similarity byte
(255: the closest pair of the matrix). The decisions are the map's edges between the two
drives, each a point ``(frame of S, image of T)``: those ``S`` added when it was merged, and
those ``T`` added (drawn transposed). When both drives have positions, ground truth is a
distance of at most ``radius_m`` between the two frames (as the data sets' position
alignment, :class:`sprint_map.frontend.groundtruth.GroundTruthSpec`): precision is the share
of decisions that are right, recall the share of ``S``'s frames with a true match in ``T``
that have a right decision.
"""

from __future__ import annotations

import base64
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.viewer.overview import MapOverview

if TYPE_CHECKING:
    from sprint_map import EdgeInfo

__all__ = ["MATRIX_SIZE", "RADIUS_M", "drive_detail", "match_matrix", "pair_decisions"]

#: Sampled frames per side of a matrix (at most).
MATRIX_SIZE = 320
#: Ground truth: frames at most this far apart (metres) are the same place.
RADIUS_M = 10.0


def pair_decisions(edges: list[EdgeInfo], seq: int, other: int) -> np.ndarray:
    """The edges between ``seq`` and ``other`` as rows ``(frame of seq, image of other, prob,
    added by seq)``, one per distinct frame pair (an edge and its reverse count once)."""
    rows: dict[tuple[int, int], tuple[float, bool]] = {}
    for e in edges:
        if e.src_seq == seq and e.dst_seq == other:
            ij = (e.src_image, e.dst_image)
        elif e.src_seq == other and e.dst_seq == seq:
            ij = (e.dst_image, e.src_image)
        else:
            continue
        rows[ij] = (max(e.prob, rows.get(ij, (0.0, False))[0]), e.added_by == seq)
    out = np.array([(i, j, p, float(mine)) for (i, j), (p, mine) in sorted(rows.items())],
                   np.float64)
    return out.reshape(-1, 4)


def _precision_recall(dec: np.ndarray, ps: np.ndarray, pt: np.ndarray) -> dict[str, Any]:
    from scipy.spatial import cKDTree

    i, j = dec[:, 0].astype(int), dec[:, 1].astype(int)
    right = np.linalg.norm(ps[i] - pt[j], axis=1) <= RADIUS_M
    near, _ = cKDTree(pt).query(ps, k=1)
    has_match = near <= RADIUS_M
    right_frames = np.unique(i[right])
    return {"radius_m": RADIUS_M, "decisions": len(dec), "correct": int(right.sum()),
            "precision": round(float(right.mean()), 4) if len(dec) else None,
            "frames_with_match": int(has_match.sum()),
            "recall": round(len(right_frames) / int(has_match.sum()), 4)
            if has_match.any() else None}


def drive_detail(summary: MapOverview, seq_id: int) -> dict[str, Any] | None:
    """A drive's page header: its record, the drives it shares edges with (most first) and,
    when positions allow, its precision/recall against all of them. None: no such drive.

    Notes
    -----
    O(log E + edges touching the drive) plus a KD-tree per matched drive with positions.
    """
    st = summary.state()
    seq = st.sequence(seq_id)
    if seq is None:
        return None
    edges = summary.read(lambda: summary.map.edges(seq_id))
    others: dict[int, int] = {}
    for e in edges:
        o = e.dst_seq if e.src_seq == seq_id else e.src_seq
        others[o] = others.get(o, 0) + 1
    matched = []
    ps = st.positions(seq_id)
    total = {"decisions": 0, "correct": 0}
    for o, n in sorted(others.items(), key=lambda kv: -kv[1]):
        other = st.sequence(o)
        row: dict[str, Any] = {"seq_id": o, "name": other.name if other else str(o),
                               "edges": n}
        pt = st.positions(o)
        if ps is not None and pt is not None:
            dec = pair_decisions(edges, seq_id, o)
            row["pr"] = _precision_recall(dec, ps, pt)
            total["decisions"] += row["pr"]["decisions"]
            total["correct"] += row["pr"]["correct"]
        matched.append(row)
    return {
        "seq_id": seq.seq_id, "name": seq.name, "frames": seq.length,
        "component": st.component(seq_id), "source": seq.source,
        "has_positions": ps is not None, "edges": len(edges), "matched": matched,
        "precision": round(total["correct"] / total["decisions"], 4)
        if total["decisions"] else None,
    }


def match_matrix(summary: MapOverview, seq_id: int, other: int, size: int = MATRIX_SIZE
                 ) -> dict[str, Any]:
    """The similarity matrix of ``seq_id`` (rows) against ``other`` (columns) with the
    decisions between them (see the module notes).

    Notes
    -----
    O(size^2 * dim) for the distances, plus reading the two drives' sampled descriptors and
    the edges touching ``seq_id``.
    """
    st = summary.state()
    s_len = st.sequence(seq_id)
    o_len = st.sequence(other)
    if s_len is None or o_len is None:
        raise KeyError(seq_id if s_len is None else other)
    rows = np.unique(np.linspace(0, s_len.length - 1, min(size, s_len.length)).astype(int))
    cols = np.unique(np.linspace(0, o_len.length - 1, min(size, o_len.length)).astype(int))
    a = summary.read(lambda: np.asarray(summary.map.descriptors(seq_id)[rows], np.float64))
    b = summary.read(lambda: np.asarray(summary.map.descriptors(other)[cols], np.float64))
    d = np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T, 0.0)
    lo, hi = float(d.min()), float(np.percentile(d, 95))
    sim = np.clip(1.0 - (d - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    pixels = np.rint(sim * 255).astype(np.uint8)
    edges = summary.read(lambda: summary.map.edges(seq_id))
    dec = pair_decisions(edges, seq_id, other)
    ps, pt = st.positions(seq_id), st.positions(other)
    return {
        "seq_id": seq_id, "other": other, "rows": rows.tolist(), "cols": cols.tolist(),
        "frames": [s_len.length, o_len.length],
        "pixels": base64.b64encode(pixels.tobytes()).decode("ascii"),
        "dist_range": [round(lo, 6), round(hi, 6)],
        "decisions": {"frame": dec[:, 0].astype(int).tolist(),
                      "image": dec[:, 1].astype(int).tolist(),
                      "prob": np.round(dec[:, 2], 3).tolist(),
                      "by_self": dec[:, 3].astype(bool).tolist()},
        "pr": _precision_recall(dec, ps, pt) if ps is not None and pt is not None else None,
    }
