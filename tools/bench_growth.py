"""Fig. 7 of the SPRINT paper: per-frame inference time as the map grows, drive after drive.

A synthetic city of streets (descriptor level: each place has an appearance vector; a drive sees
it through a condition-dependent distortion plus noise) is driven by ``--sequences`` drives of
random routes over its streets at varying speed. Each drive is localised against the map of all
earlier drives and merged into it with its decisions as edges, exactly as ``sprint-map ingest``
does (``SprintMap.ingest``). We record the mean per-frame HMM, smoothing (the merge's
forward-backward pass) and retrieval time of each drive.

    python tools/bench_growth.py --json growth.json --png growth.png
    python tools/bench_growth.py --quick            # 20 drives, for a smoke run
    python tools/bench_growth.py --quick --gnss 10  # with GNSS fixes (sigma 10 m) on every drive
    python tools/bench_growth.py --quick --lag 10   # also each drive localised 10 frames late

With ``--lag L`` every drive is also localised read-only before its ingest, causally and with
answers ``L`` frames late (``SprintMap.localize(lag=L)``), ``--repeat`` times each way
(alternating; the fastest of each is kept), and both per-frame HMM times are recorded
(``causal_ms``, ``lag_ms``; with retrieval ``causal_total_ms``, ``lag_total_ms``): the lag's
cost against the causal step's in the same run, and whether it stays flat as the map grows.

Goal: flat; the last 10 drives no slower than 1.5x the first 10 that had a map to match. With
``--gnss M`` the streets lie on a plane (a grid of straight streets, 5 m between places), every
drive carries fixes simulated from its true positions (:mod:`sprint_map.frontend.gnss`) which
the map stores, and the GNSS step of each frame (:meth:`GnssAid.cue`: the KD-tree look-up and
the weights, O(log n)) is timed apart and held to the same goal.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sprint_map import MapConfig
from sprint_map.map import SprintMap


def make_city(rng: np.random.Generator, n_streets: int, street_len: int, dim: int
              ) -> np.ndarray:
    """Appearance of every place: (n_streets, street_len, dim), smooth along each street."""
    raw = rng.normal(size=(n_streets, street_len + 8, dim)).astype(np.float32)
    kernel = np.ones(8, dtype=np.float32) / 8  # neighbouring places look alike
    smooth = np.apply_along_axis(lambda v: np.convolve(v, kernel, "valid"), 1, raw)
    return smooth[:, :street_len]


def street_xy(street: int, place: np.ndarray, street_len: int) -> np.ndarray:
    """True positions of places along a street: streets are straight, 5 m between places, side
    by side 60 m apart on a grid of 8 columns, alternately east-west and north-south."""
    row, col = divmod(street, 8)
    origin = np.array([col * (street_len * 5.0 + 60.0), row * (street_len * 5.0 + 60.0)])
    step = np.array([5.0, 0.0]) if street % 2 == 0 else np.array([0.0, 5.0])
    return origin + place[:, None] * step


def drive(rng: np.random.Generator, city: np.ndarray, frames: int, condition_std: float = 0.25,
          noise: float = 0.6, truth: list[np.ndarray] | None = None) -> np.ndarray:
    """One drive: a route of whole street stretches at varying speed under one condition.

    ``condition_std`` scales the drive's random appearance change, ``noise`` the per-frame
    noise (relative to the descriptors' spread). ``truth``, if given, receives the true
    positions of the frames (:func:`street_xy`)."""
    n_streets, street_len, dim = city.shape
    condition = np.eye(dim, dtype=np.float32) + rng.normal(
        0, condition_std, (dim, dim)).astype(np.float32)
    out = []
    while sum(len(o) for o in out) < frames:
        street = rng.integers(n_streets)
        start = rng.integers(0, street_len // 2)
        speed = rng.uniform(0.7, 1.4)
        pos = start + np.arange(int((street_len - start) / speed)) * speed
        out.append(city[street, pos.astype(int)])
        if truth is not None:
            truth.append(street_xy(int(street), pos.astype(int), street_len))
    seq = np.concatenate(out)[:frames] @ condition
    seq += rng.normal(0, noise * seq.std(), seq.shape).astype(np.float32)
    seq /= np.linalg.norm(seq, axis=1, keepdims=True)
    return seq.astype(np.float32)


def lag_timing(m: SprintMap, seq: np.ndarray, lag: int, repeat: int) -> dict[str, float]:
    """Per-frame HMM and retrieval + HMM times of ``seq`` localised causally and ``lag``
    frames late, each the fastest of ``repeat`` runs (the two ways alternate)."""
    best: dict[str, float] = {}
    for _ in range(max(repeat, 1)):
        for name, way in (("causal", 0), ("lag", lag)):
            t = m.localize(seq, lag=way)[1].to_dict()
            hmm = t["hmm_ms_per_frame"]
            total = hmm + t["retrieval_ms_per_frame"]
            best[f"{name}_ms"] = min(best.get(f"{name}_ms", np.inf), hmm)
            best[f"{name}_total_ms"] = min(best.get(f"{name}_total_ms", np.inf), total)
    return {key: round(value, 4) for key, value in best.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sequences", type=int, default=80)
    parser.add_argument("--frames", type=int, default=625, help="frames per drive (80 x 625 = 50k)")
    parser.add_argument("--dim", type=int, default=128)
    parser.add_argument("--streets", type=int, default=60)
    parser.add_argument("--street-len", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--condition", type=float, default=0.25,
                        help="std of each drive's appearance change (default 0.25)")
    parser.add_argument("--noise", type=float, default=0.6,
                        help="per-frame noise, relative to the descriptors' spread (default 0.6; "
                             "0.3 with --condition 0.1 is a world whose drives can be matched)")
    parser.add_argument("--quick", action="store_true", help="20 drives of 300 frames")
    parser.add_argument("--gnss", type=float, default=0.0, metavar="M",
                        help="drives carry simulated GNSS fixes of M metres (0: none)")
    parser.add_argument("--lag", type=int, default=0,
                        help="also localise each drive L frames late (and causally) first")
    parser.add_argument("--repeat", type=int, default=3,
                        help="with --lag: localise each drive this many times each way, "
                             "alternating, and keep the fastest of each (default 3)")
    parser.add_argument("--json", type=Path, help="write the rows here")
    parser.add_argument("--png", type=Path, help="plot here")
    args = parser.parse_args(argv)
    if args.quick:
        args.sequences, args.frames = 20, 300
    rng = np.random.default_rng(args.seed)
    city = make_city(rng, args.streets, args.street_len, args.dim)
    rows = []
    gnss_s = [0.0, 0]  # seconds in the GNSS step, frames it ran on (this drive)
    if args.gnss:
        from sprint_map.frontend.gnss import GnssModel, simulate_fixes
        from sprint_map.localize.gnss import GnssAid

        cue = GnssAid.cue

        def timed_cue(self: GnssAid, frame: int, ids: np.ndarray, dists: np.ndarray) -> object:
            start = time.perf_counter()
            out = cue(self, frame, ids, dists)
            gnss_s[0] += time.perf_counter() - start
            gnss_s[1] += 1
            return out

        GnssAid.cue = timed_cue  # type: ignore[assignment,method-assign]
    with (
        tempfile.TemporaryDirectory() as tmp,
        SprintMap.create(Path(tmp) / "growth.map", MapConfig(dim=args.dim)) as m,
    ):
        print(f"{'seq':>4} {'frames':>6} {'map_vertices':>12} {'hmm_ms':>8} {'retr_ms':>8} "
              f"{'smooth_ms':>9} {'active':>8} {'edges':>6} {'comps':>5} {'gnss_ms':>8}")
        for i in range(args.sequences):
            truth: list[np.ndarray] = []
            seq = drive(rng, city, args.frames, args.condition, args.noise, truth)
            fixes = (simulate_fixes(np.concatenate(truth)[:len(seq)], GnssModel(args.gnss),
                                    np.random.SeedSequence([args.seed, i]))
                     if args.gnss else None)
            before = m.stats()["vertices"]
            lagged = {}
            if args.lag and i:
                lagged = lag_timing(m, seq, args.lag, args.repeat)
            gnss_s[:] = [0.0, 0]
            start = time.perf_counter()
            result = m.ingest(seq, name=f"drive-{i:03d}", fixes=fixes,
                              positions=None if fixes is None else fixes[:, :2])
            t = result.timing.to_dict()
            row = {
                "sequence": i,
                "frames": len(seq),
                "map_vertices": before,
                "hmm_ms_per_frame": t["hmm_ms_per_frame"] if i else None,
                "smooth_ms_per_frame": t["smooth_ms_per_frame"] if i else None,
                "retrieval_ms_per_frame": t["retrieval_ms_per_frame"] if i else None,
                "active_vertices_mean": t["active_vertices_mean"] if i else None,
                "edges_added": result.edges_added,
                "components": m.stats()["components"],
                "ingest_s": round(time.perf_counter() - start, 3),
                # the GNSS step, per frame it ran on (causal and smoothing passes alike)
                "gnss_ms_per_frame": (round(gnss_s[0] * 1e3 / gnss_s[1], 5)
                                      if gnss_s[1] else None),
                **lagged,
            }
            rows.append(row)
            print(f"{i:>4} {len(seq):>6} {before:>12} {row['hmm_ms_per_frame'] or 0:>8.4f} "
                  f"{row['retrieval_ms_per_frame'] or 0:>8.4f} "
                  f"{row['smooth_ms_per_frame'] or 0:>9.4f} "
                  f"{row['active_vertices_mean'] or 0:>8.0f} {row['edges_added']:>6} "
                  f"{row['components']:>5} {row['gnss_ms_per_frame'] or 0:>8.4f}"
                  + (f"  causal {lagged['causal_ms']:.4f} lag {lagged['lag_ms']:.4f} ms"
                     if lagged else ""), flush=True)
    timed = [r for r in rows if r["hmm_ms_per_frame"] is not None]
    first = float(np.mean([r["hmm_ms_per_frame"] for r in timed[:10]]))
    last = float(np.mean([r["hmm_ms_per_frame"] for r in timed[-10:]]))
    ratio = last / first
    s_first = float(np.mean([r["smooth_ms_per_frame"] for r in timed[:10]]))
    s_last = float(np.mean([r["smooth_ms_per_frame"] for r in timed[-10:]]))
    s_ratio = s_last / s_first
    print(f"\nHMM ms/frame: first 10 drives with a map {first:.4f}, last 10 {last:.4f}, "
          f"ratio {ratio:.2f} (goal <= 1.5)")
    print(f"smoothed merge ms/frame: first 10 {s_first:.4f}, last 10 {s_last:.4f}, "
          f"ratio {s_ratio:.2f} (goal <= 1.5)")
    if args.lag:
        lag_rows = [r for r in timed if "lag_ms" in r]
        l_first = float(np.mean([r["lag_ms"] for r in lag_rows[:10]]))
        l_last = float(np.mean([r["lag_ms"] for r in lag_rows[-10:]]))
        vs_causal = float(np.mean([r["lag_ms"] / r["causal_ms"] for r in lag_rows]))
        vs_total = float(np.mean([r["lag_total_ms"] / r["causal_total_ms"] for r in lag_rows]))
        print(f"lag {args.lag} HMM ms/frame: first 10 {l_first:.4f}, last 10 {l_last:.4f}, "
              f"ratio {l_last / l_first:.2f}; vs the causal step of the same drive: HMM "
              f"{vs_causal:.2f}x, with retrieval {vs_total:.2f}x")
    out = {"rows": rows, "first10_hmm_ms": first, "last10_hmm_ms": last, "ratio": ratio,
           "first10_smooth_ms": s_first, "last10_smooth_ms": s_last, "smooth_ratio": s_ratio,
           "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    if args.lag:
        out.update(lag_first10_ms=l_first, lag_last10_ms=l_last, lag_vs_causal=vs_causal,
                   lag_vs_causal_total=vs_total)
    g_ratio = 0.0
    if args.gnss:
        g_first = float(np.mean([r["gnss_ms_per_frame"] for r in timed[:10]]))
        g_last = float(np.mean([r["gnss_ms_per_frame"] for r in timed[-10:]]))
        g_ratio = g_last / g_first
        print(f"GNSS step ms/frame: first 10 {g_first:.4f}, last 10 {g_last:.4f}, "
              f"ratio {g_ratio:.2f} (goal <= 1.5)")
        out.update(first10_gnss_ms=g_first, last10_gnss_ms=g_last, gnss_ratio=g_ratio)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot([r["sequence"] for r in timed], [r["hmm_ms_per_frame"] for r in timed], "o-",
                label="HMM (SPRINT)")
        ax.plot([r["sequence"] for r in timed], [r["smooth_ms_per_frame"] for r in timed], "^-",
                label="smoothed merge (forward-backward)")
        ax.plot([r["sequence"] for r in timed], [r["retrieval_ms_per_frame"] for r in timed],
                "s-", label="retrieval (exact k-NN, batched)")
        ax.set(xlabel="sequence number", ylabel="mean time per frame (ms)",
               title="Per-frame inference time as the map grows (paper Fig. 7)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.png, dpi=110)
    return 0 if ratio <= 1.5 and s_ratio <= 1.5 and g_ratio <= 1.5 else 1


if __name__ == "__main__":
    sys.exit(main())
