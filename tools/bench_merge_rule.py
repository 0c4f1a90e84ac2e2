"""Merge rule on several world families and seeds: does one configuration hold everywhere?

For each ``--family`` (``city``, ``city-novel``: rendered images described by HoG, as ``sprint-map
demo`` does; ``latent``: descriptor-level drives over latent places, :mod:`sprint_map.synth.latent`)
and each ``--seeds`` seed, a world is generated (once: cached under ``--cache``, keyed by family,
seed, traversals, frames, generator config and the generator's source) and the lifelong protocol of ``sprint-map eval`` is
run on it (:func:`sprint_map.evaluation.runner.run_evaluation`, the same code, the same default
config: HoG for the city, the world's precomputed descriptors for latent). Descriptors and
thumbnails of the city worlds are cached too (the HoG and the JPEG thumbnails are what ``eval``
computes from the images; the cache only skips recomputing them).

Per family and seed: merge precision (also without the merges of frames on identical twins, the
image-only figure) and recall, share of frames without a true match that were
merged (``novel merged``), the worst query's merge precision (over queries that merged anything),
smoothed SPRINT@1, exact k-NN@1 / @10, merged decisions, frames on identical twins (and their
merges) where the world declares twins, and seconds; then the mean over seeds per family.

``--set KEY=VALUE`` (repeatable, JSON values) overrides a ``MapConfig`` field (``merge_*``, ...)
or an ``HMMConfig`` field (``k``, ``hmm.k``) of every run; the default configuration then runs
too as the baseline (skip it with ``--no-baseline``), and the table shows both.

``--gnss-sigma M`` also runs every evaluation GNSS-aided (``eval --gnss-sigma``: fixes simulated
from the ground truth with M metres of drift, dropouts and jumps); its figures are the rows
``<config>+gnss`` beside the image-only ones.

    python tools/bench_merge_rule.py --family city city-novel latent --seeds 0 1 2 --json m.json
    python tools/bench_merge_rule.py --family latent --seeds 0 --set merge_max_contrast=0.9
    python tools/bench_merge_rule.py --family latent --quick     # 5 traversals x 120 frames
    python tools/bench_merge_rule.py --family latent city-novel --gnss-sigma 10

Cost: a latent world generates in ~2 s; a city renders in ~10-20 s (once, then cached); each
evaluation is ~30 s (latent, 10 x 300) or ~20-40 s (city, 6 x 300) on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import HMMConfig, MapConfig
from sprint_map.errors import ConfigError
from sprint_map.evaluation.runner import (
    EvalOptions,
    config_for,
    describe_with_thumbnails,
    run_evaluation,
)
from sprint_map.frontend.dataset import Dataset, Traversal
from sprint_map.map import SprintMap

FAMILIES = ("city", "city-novel", "latent")
#: As ``sprint-map demo``: city worlds 6 x 300 frames, the latent world 10 x 300.
DEFAULT_SIZE = {"city": (6, 300), "city-novel": (6, 300), "latent": (10, 300)}
METRICS = ("merge_precision", "merge_precision_no_twins", "merge_recall", "novel_merged", "worst_query_precision",
           "smoothed_recall@1", "knn_recall@1", "knn_recall@10", "merged_decisions")


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/sprint-map/worlds`` (``~/.cache/...`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "sprint-map" / "worlds"


def generator_config(family: str) -> dict[str, Any]:
    """The generator config of a family, as a dict (part of the cache key)."""
    if family == "latent":
        from sprint_map.synth.latent import LATENT_PRESETS

        return LATENT_PRESETS["latent"].to_dict()
    from sprint_map.synth.city import PRESETS

    return PRESETS[family].to_dict()


def generator_source(family: str) -> str:
    """Digest of the generator's source files: a changed generator is a new cache entry."""
    import sprint_map.synth as synth

    folder = Path(synth.__file__).parent
    names = ["latent.py"] if family == "latent" else sorted(
        p.name for p in folder.glob("*.py") if p.name != "latent.py")
    digest = hashlib.sha256()
    for name in names:
        digest.update((folder / name).read_bytes())
    return digest.hexdigest()


def world(cache: Path, family: str, seed: int, traversals: int, frames: int) -> Path:
    """The cached data set of ``family``/``seed`` (generated on first use), keyed by family,
    seed, size, generator config and generator source."""
    config = generator_config(family)
    key = hashlib.sha256(json.dumps([family, seed, traversals, frames, config,
                                     generator_source(family)],
                                    sort_keys=True).encode()).hexdigest()[:12]
    path = cache / f"{family}-s{seed}-{traversals}x{frames}-{key}"
    if (path / "dataset.json").is_file():
        return path
    cache.mkdir(parents=True, exist_ok=True)
    if family == "latent":
        from sprint_map.synth.latent import LATENT_PRESETS, generate_latent

        generate_latent(path, traversals, frames, seed, LATENT_PRESETS["latent"])
    else:
        from sprint_map.synth.city import PRESETS, generate_city

        generate_city(path, traversals, frames, seed, PRESETS[family])
    return path


class CachedDescribe:
    """``describe_with_thumbnails`` with its result kept next to the world (``.describe/``),
    keyed by traversal, stride and descriptor spec. Precomputed (``.npy``) traversals are read
    as they are."""

    def __init__(self, root: Path) -> None:
        self.root = root / ".describe"

    def __call__(self, m: SprintMap, traversal: Traversal, stride: int
                 ) -> tuple[np.ndarray, list[bytes] | None]:
        if traversal.kind == "npy":
            return describe_with_thumbnails(m, traversal, stride)
        spec = json.dumps([m.config.descriptor, m.config.descriptor_params, stride],
                          sort_keys=True)
        key = hashlib.sha256(spec.encode()).hexdigest()[:12]
        path = self.root / f"{traversal.name}-{key}.npz"
        if path.is_file():
            with np.load(path, allow_pickle=False) as data:
                rows = data["rows"]
                blob, ends = data["thumbs"].tobytes(), data["ends"]
            starts = np.concatenate([[0], ends[:-1]])
            return rows, [blob[a:b] for a, b in zip(starts, ends, strict=True)]
        rows, thumbs = describe_with_thumbnails(m, traversal, stride)
        if thumbs is not None:
            self.root.mkdir(exist_ok=True)
            partial = path.with_suffix(".partial.npz")
            np.savez(partial, rows=rows, thumbs=np.frombuffer(b"".join(thumbs), dtype=np.uint8),
                     ends=np.cumsum([len(t) for t in thumbs]))
            os.replace(partial, path)
        return rows, thumbs


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs -> changes of the MapConfig record; values are JSON (else text).
    ``part.field`` (``merge.max_contrast``, ``hmm.k``, ``store.index_type``) or the flat names
    MapConfig reads (``merge_max_contrast``, ``index_type``); a bare HMMConfig field goes to
    the HMM."""
    hmm_fields = {f.name for f in dataclasses.fields(HMMConfig)}
    changes: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep:
            raise ConfigError(f"--set {pair}: expected KEY=VALUE")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        part, dot, name = key.partition(".")
        if not dot and key in hmm_fields:
            part, name = "hmm", key
        if dot or part == "hmm":
            changes.setdefault(part, {})[name] = value
        else:
            changes[key] = value
    configured(MapConfig(dim=8), changes)  # an unknown field or a bad value: ConfigError now
    return changes


def configured(base: MapConfig, changes: dict[str, Any]) -> MapConfig:
    """``base`` with the overrides (validated as the map validates them)."""
    record = base.to_dict()
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(record.get(key), dict):
            record[key] = {**record[key], **value}
        else:
            record[key] = value
    return MapConfig.from_dict(record)


def figures(results: dict[str, Any]) -> dict[str, Any]:
    """The table's figures of one evaluation's results."""
    overall = results["overall"]
    merged = [q for q in results["queries"] if q["merged_decisions"] > 0]
    out: dict[str, Any] = {key: overall[key] for key in METRICS if key in overall}
    out["worst_query_precision"] = min((q["merge_precision"] for q in merged), default=None)
    out["worst_query"] = (min(merged, key=lambda q: q["merge_precision"])["query"]
                          if merged else None)
    for key in ("twin_frames", "twin_merged", "twin_merged_wrong"):
        if key in overall:
            out[key] = overall[key]
    if "twin_merged" in overall:  # the image-only figure: identical twins left out
        wrong = round(overall["merged_decisions"] * (1 - overall["merge_precision"]))
        kept = overall["merged_decisions"] - overall["twin_merged"]
        out["merge_precision_no_twins"] = (
            round(1 - (wrong - overall["twin_merged_wrong"]) / kept, 4) if kept else 1.0)
    out["seconds"] = results["seconds"]
    return out


def run_one(path: Path, family: str, changes: dict[str, Any], gnss_sigma: float = 0.0
            ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Evaluate one cached world; returns (figures, full results without private keys)."""
    dataset = Dataset.open(path)
    base = config_for(dataset) if family == "latent" else MapConfig.for_descriptor("hog")
    config = configured(base, changes)
    options = EvalOptions(protocol="lifelong", gnss_sigma=gnss_sigma)
    with tempfile.TemporaryDirectory(prefix="bench-merge-") as tmp:
        results = run_evaluation(dataset, Path(tmp), config, options,
                                 describe=CachedDescribe(path))
    clean = {k: v for k, v in results.items() if not k.startswith("_")}
    return figures(results), clean


def mean_row(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean over seeds of each figure (worst query: the minimum)."""
    out: dict[str, Any] = {}
    for key in (*METRICS, "twin_frames", "twin_merged", "twin_merged_wrong", "seconds"):
        values = [r[key] for r in rows if r.get(key) is not None]
        if not values:
            continue
        out[key] = (min(values) if key == "worst_query_precision"
                    else round(float(np.mean(values)), 4))
    return out


def pct(value: float | None) -> str:
    return "    -" if value is None else f"{100 * value:5.1f}"


def print_table(family: str, rows: list[tuple[str, str, dict[str, Any]]]) -> None:
    print(f"\n{family}")
    print(f"{'seed':>5} {'config':>12} | {'mergeP':>6} {'P-twin':>6} {'mergeR':>6} {'novelM':>6} "
          f"{'worstQ':>6} {'smooth':>6} | {'kNN@1':>6} {'kNN@10':>6} | {'merged':>6} "
          f"{'twins':>11} | {'s':>5}")
    for seed, arm, r in rows:
        twins = ("/".join(f"{r[k]:.0f}" for k in ("twin_merged_wrong", "twin_merged",
                                                   "twin_frames"))
                 if "twin_frames" in r else "-")
        print(f"{seed:>5} {arm:>12} | {pct(r.get('merge_precision')):>6} "
              f"{pct(r.get('merge_precision_no_twins')):>6} "
              f"{pct(r.get('merge_recall')):>6} {pct(r.get('novel_merged')):>6} "
              f"{pct(r.get('worst_query_precision')):>6} {pct(r.get('smoothed_recall@1')):>6} | "
              f"{pct(r.get('knn_recall@1')):>6} {pct(r.get('knn_recall@10')):>6} | "
              f"{r.get('merged_decisions', 0):>6.0f} {twins:>11} | {r['seconds']:5.0f}",
              flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--family", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--traversals", type=int, help="per world (default: as the demo)")
    parser.add_argument("--frames", type=int, help="per traversal (default: 300)")
    parser.add_argument("--quick", action="store_true", help="5 traversals x 120 frames")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="MapConfig / HMMConfig override (JSON value)")
    parser.add_argument("--no-baseline", action="store_true",
                        help="with --set: do not also run the default configuration")
    parser.add_argument("--cache", type=Path, default=default_cache(),
                        help="where generated worlds and descriptors are kept")
    parser.add_argument("--gnss-sigma", type=float, default=0.0, metavar="M",
                        help="also run GNSS-aided with fixes of M metres (rows '<config>+gnss')")
    parser.add_argument("--json", type=Path, help="write every figure (and full results) here")
    args = parser.parse_args(argv)
    if not args.gnss_sigma >= 0:
        parser.error("--gnss-sigma must be >= 0 metres")
    try:
        changes = parse_overrides(args.overrides)
        configured(MapConfig(dim=8), changes)  # fail before any work
    except ConfigError as exc:
        parser.error(str(exc))
    arms: list[tuple[str, dict[str, Any]]] = [("tuned", changes)] if args.overrides else []
    if not args.overrides or not args.no_baseline:
        arms.insert(0, ("default", {}))
    started = time.perf_counter()
    out: dict[str, Any] = {"args": {k: str(v) if isinstance(v, Path) else v
                                    for k, v in vars(args).items()},
                           "overrides": changes,
                           "families": {}}
    for family in args.family:
        traversals, frames = DEFAULT_SIZE[family]
        if args.quick:
            traversals, frames = 5, 120
        traversals, frames = args.traversals or traversals, args.frames or frames
        table: list[tuple[str, str, dict[str, Any]]] = []
        runs: list[dict[str, Any]] = []
        for seed in args.seeds:
            t0 = time.perf_counter()
            path = world(args.cache, family, seed, traversals, frames)
            made = time.perf_counter() - t0
            for arm, arm_changes in arms:
                row, results = run_one(path, family, arm_changes, args.gnss_sigma)
                table.append((str(seed), arm, row))
                runs.append({"seed": seed, "arm": arm, "world": str(path),
                             "world_seconds": round(made, 1), "figures": row,
                             "results": results})
                if "gnss" in results:
                    aided = figures({**results["gnss"], "seconds": results["seconds"]})
                    table.append((str(seed), f"{arm}+gnss", aided))
                    runs.append({"seed": seed, "arm": f"{arm}+gnss", "world": str(path),
                                 "figures": aided})
                made = 0.0
        names = [arm for arm, _ in arms] + (
            [f"{arm}+gnss" for arm, _ in arms] if args.gnss_sigma else [])
        for arm in names:
            table.append(("mean", arm, mean_row([r for _, a, r in table if a == arm])))
        print_table(f"{family} ({traversals} x {frames} frames per seed)", table)
        out["families"][family] = {
            "traversals": traversals, "frames": frames, "runs": runs,
            "mean": {arm: mean_row([r["figures"] for r in runs if r["arm"] == arm])
                     for arm in names}}
    seconds = time.perf_counter() - started
    out["seconds"] = round(seconds, 1)
    print(f"\n{seconds:.0f} s in all (merge P, merge P without the identical twins' merges, merge "
          "R, novel merged, worst query precision, smoothed SPRINT@1, exact k-NN; twins: "
          "wrong/merged/frames on identical twins)")
    if args.json:
        partial = args.json.with_name(args.json.name + ".partial")
        partial.write_text(json.dumps(out, indent=2) + "\n")
        os.replace(partial, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
