"""Front-end measurements (not collected by pytest: the file name does not start with ``test_``).

Usage::

    python tools/bench_frontend.py ingest DIR [--repeat 3]
        HoG ingest frames/s from an image directory: 1 worker, 2 threads, 2 processes.
    python tools/bench_frontend.py make-jpegs DIR [--frames 400]
        Write 640x480 JPEGs of the synthetic city to DIR (input for ``ingest``).
    python tools/bench_frontend.py synth [--seeds 0,1,2,3] [--traversals 6] [--frames 300]
        Generation time and HoG k-NN@1/5/10 on the synthetic city.
    python tools/bench_frontend.py nordland [PATH]
        Summer -> winter HoG k-NN@1/5/10 at +/- 1 frame (README: 41.4 / 58.0 / 64.4 %).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from sprint_map.frontend import Dataset, DescriptorSpec, GroundTruth, open_source
from sprint_map.synth import CityConfig, generate_city


def knn_hits(
    query: np.ndarray,
    db: dict[str, np.ndarray],
    query_name: str,
    gt: GroundTruth,
    ks: tuple[int, ...] = (1, 5, 10),
) -> tuple[int, dict[int, int]]:
    """Exact L2 k-NN of each query frame over the union of ``db`` traversals.

    Returns the number of query frames that have a correct match in ``db`` and, per k, how many
    of those have one among their k nearest neighbours.
    """
    names = list(db)
    stacked = np.concatenate([db[n] for n in names])
    owner = np.concatenate([np.full(len(db[n]), i) for i, n in enumerate(names)])
    index = np.concatenate([np.arange(len(db[n])) for n in names])
    dist = (query * query).sum(1)[:, None] - 2 * query @ stacked.T + (stacked * stacked).sum(1)
    order = np.argsort(dist, axis=1, kind="stable")[:, : max(ks)]
    frames = np.arange(len(query))[:, None]
    correct = np.zeros(order.shape, dtype=bool)
    for i, name in enumerate(names):
        correct |= (owner[order] == i) & gt.correct(query_name, frames, name, index[order])
    has = gt.has_match(query_name, np.arange(len(query)), names)
    return int(has.sum()), {k: int(correct[has, :k].any(axis=1).sum()) for k in ks}


def cmd_make_jpegs(args: argparse.Namespace) -> None:
    config = CityConfig(width=640, height=480)
    with tempfile.TemporaryDirectory() as tmp:
        out = generate_city(
            Path(tmp) / "set", 1, args.frames, seed=3, config=config, image_format="jpg"
        )
        target = Path(args.dir)
        target.mkdir(parents=True)
        for path in sorted((out / "t00-day").glob("*.jpg")):
            path.rename(target / path.name)
    print(f"wrote {args.frames} 640x480 JPEGs to {target}")


def cmd_ingest(args: argparse.Namespace) -> None:
    spec = DescriptorSpec("hog")
    open_source(args.dir, spec, workers=1).read_all()  # warm the page cache
    configs = ((1, "thread"), (2, "thread"), (2, "process"))
    rates: dict[tuple[int, str], list[float]] = {c: [] for c in configs}
    cpu: dict[tuple[int, str], list[float]] = {c: [] for c in configs}
    n = 0
    # Round-robin over the configurations, so that a burst of load from other processes on the
    # machine does not penalise one configuration only; report median and best.
    for _ in range(args.repeat):
        for workers, executor in configs:
            source = open_source(args.dir, spec, workers=workers, executor=executor)
            before, start = os.times(), time.perf_counter()
            n = len(source.read_all())
            elapsed, after = time.perf_counter() - start, os.times()
            used = sum(after[:4]) - sum(before[:4])  # user + sys, self + joined children
            rates[(workers, executor)].append(n / elapsed)
            cpu[(workers, executor)].append(1000 * used / n)
    print(f"load average before: {os.getloadavg()[0]:.2f}; {n} frames, {args.repeat} rounds")
    for (workers, executor), values in rates.items():
        print(
            f"workers={workers} {executor:7s}: median {statistics.median(values):5.0f}  "
            f"best {max(values):5.0f} frames/s; "
            f"CPU {statistics.median(cpu[(workers, executor)]):.2f} ms/frame"
        )


def cmd_synth(args: argparse.Namespace) -> None:
    spec = DescriptorSpec("hog")
    # Two databases per query traversal: all earlier traversals (a growing map), traversal 0.
    matchable = {"all earlier": 0, "traversal 0": 0}
    hits = {label: dict.fromkeys((1, 5, 10), 0) for label in matchable}
    for seed in (int(s) for s in args.seeds.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            path = generate_city(Path(tmp) / "city", args.traversals, args.frames, seed=seed)
            took = time.perf_counter() - start
            dataset = Dataset.open(path)
            descriptors = {t.name: t.open(spec).read_all() for t in dataset}
            gt = dataset.ground_truth()
            names = dataset.names
            for i in range(1, len(names)):
                for label, db_names in (("all earlier", names[:i]), ("traversal 0", names[:1])):
                    db = {n: descriptors[n] for n in db_names}
                    n, found = knn_hits(descriptors[names[i]], db, names[i], gt)
                    matchable[label] += n
                    for k, v in found.items():
                        hits[label][k] += v
        print(f"seed {seed}: generated {args.traversals} x {args.frames} frames in {took:.1f} s")
    for label, n in matchable.items():
        scores = "  ".join(f"@{k} {100 * v / n:.1f} %" for k, v in hits[label].items())
        print(f"db = {label}: {n} matchable queries  {scores}")


def cmd_nordland(args: argparse.Namespace) -> None:
    dataset = Dataset.open(args.path, {"alignment": "frame", "tolerance_frames": 1})
    spec = DescriptorSpec("hog")
    start = time.perf_counter()
    summer = dataset["summer"].open(spec).read_all()
    winter = dataset["winter"].open(spec).read_all()
    print(f"described {len(summer) + len(winter)} frames in {time.perf_counter() - start:.1f} s")
    n, hits = knn_hits(winter, {"summer": summer}, "winter", dataset.ground_truth())
    print(
        "summer -> winter, all frames: "
        + "  ".join(f"@{k} {100 * v / n:.1f} %" for k, v in hits.items())
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(required=True)
    p = sub.add_parser("make-jpegs")
    p.add_argument("dir")
    p.add_argument("--frames", type=int, default=400)
    p.set_defaults(func=cmd_make_jpegs)
    p = sub.add_parser("ingest")
    p.add_argument("dir")
    p.add_argument("--repeat", type=int, default=3)
    p.set_defaults(func=cmd_ingest)
    p = sub.add_parser("synth")
    p.add_argument("--seeds", default="0,1,2,3")
    p.add_argument("--traversals", type=int, default=6)
    p.add_argument("--frames", type=int, default=300)
    p.set_defaults(func=cmd_synth)
    p = sub.add_parser("nordland")
    p.add_argument("path", nargs="?", default="/work/shared/data/nordland")
    p.set_defaults(func=cmd_nordland)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
