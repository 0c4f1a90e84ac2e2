"""A trace as the viewer plays it back: a timeline of the whole drive, then frames in pages.

:func:`timeline` gives per-frame scalars for the whole trace (active set size, decision and
its probability, unmapped-place probability, merged or not): a few numbers per frame, so a
100k-frame trace is a few MB at most. :func:`frames` gives the full state of a page of frames
(hits, active components with their mass, the top belief states with their positions when the
map has them), at most ``PAGE`` frames per call.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sprint_map import Trace
from sprint_map.viewer.overview import MapOverview, MapState

__all__ = ["PAGE", "frames", "timeline"]

#: Frames per :func:`frames` call (at most).
PAGE = 500


def timeline(trace: Trace) -> dict[str, Any]:
    """The trace's meta and per-frame scalars. O(frames)."""
    ptr = trace["active_ptr"]
    return {
        "meta": trace.meta,
        "frames": trace.frames,
        "n_active_components": np.diff(ptr).tolist(),
        "n_active_vertices": trace["n_active_vertices"].tolist(),
        "dec_seq": trace["dec_seq"].tolist(),
        "dec_prob": np.round(trace["dec_prob"].astype(float), 4).tolist(),
        "novel_prob": np.round(trace["novel_prob"].astype(float), 4).tolist(),
        "final_seq": trace["final_seq"].tolist(),
        "final_prob": np.round(trace["final_prob"].astype(float), 4).tolist(),
        "merged": trace["merged"].astype(bool).tolist(),
    }


def frames(trace: Trace, summary: MapOverview | None, start: int, count: int
           ) -> list[dict[str, Any]]:
    """Frames ``start .. start + count - 1`` (clipped to the trace and to :data:`PAGE`).

    Notes
    -----
    O(count * (k + top_n + active components)).
    """
    start = max(0, start)
    stop = min(trace.frames, start + max(0, min(count, PAGE)))
    out = []
    st = summary.state() if summary is not None else None
    for t in range(start, stop):
        comps, mass = trace.active(t)
        top = trace["top_seq"][t] >= 0
        ts, ti = trace["top_seq"][t][top], trace["top_image"][t][top]
        hit = trace["hit_seq"][t] >= 0
        row: dict[str, Any] = {
            "frame": t,
            "active": {"component": comps.tolist(), "mass": np.round(mass.astype(float), 4).tolist()},
            "n_active_vertices": int(trace["n_active_vertices"][t]),
            "top": {"seq": ts.tolist(), "image": ti.tolist(),
                    "prob": np.round(trace["top_prob"][t][top].astype(float), 4).tolist()},
            "hits": {"seq": trace["hit_seq"][t][hit].tolist(),
                     "image": trace["hit_image"][t][hit].tolist(),
                     "dist": np.round(trace["hit_dist"][t][hit].astype(float), 4).tolist()},
            "decision": _decision(trace, "dec", t) | {
                "novel_prob": round(float(trace["novel_prob"][t]), 4)},
            "final": _decision(trace, "final", t) | {"merged": bool(trace["merged"][t])},
        }
        if st is not None:
            row["top"]["xy"] = _positions(st, ts, ti)
        out.append(row)
    return out


def _decision(trace: Trace, prefix: str, t: int) -> dict[str, Any]:
    seq = int(trace[f"{prefix}_seq"][t])
    return {"seq": None if seq < 0 else seq,
            "image": None if seq < 0 else int(trace[f"{prefix}_image"][t]),
            "prob": round(float(trace[f"{prefix}_prob"][t]), 4)}


def _positions(st: MapState, seqs: np.ndarray, images: np.ndarray
               ) -> list[list[float] | None]:
    out: list[list[float] | None] = []
    for s, i in zip(seqs.tolist(), images.tolist(), strict=True):
        pos = st.positions(s)
        out.append(None if pos is None or i >= len(pos) else
                   [round(float(pos[i, 0]), 2), round(float(pos[i, 1]), 2)])
    return out
