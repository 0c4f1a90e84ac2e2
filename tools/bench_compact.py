"""Forgetting and compaction on a realistic map: bytes on disk before and after.

Builds a synthetic lifelong map of ``--drives`` drives of ``--frames`` frames (``--dim``
float32 descriptors, positions, an edge every 10 frames both ways to an earlier drive of the
same place), removes every other drive (``--remove-every``), compacts, and reports the bytes of
each part (LMDB, shards, index) after building, after the removal and after the compaction,
plus the time of each step. The removal reclaims nothing on disk (ids stay, rows stay) and the
compaction should bring the map to the size of a map built from the kept drives alone, which is
built in the same run as the baseline.

    python tools/bench_compact.py --drives 20 --frames 1000 --dim 256 --json compact.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.storage.check import check_map
from sprint_map.storage.compaction import part_bytes
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore


def drive(rng: np.random.Generator, places: np.ndarray, i: int, frames: int
          ) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors and positions of drive ``i``: the places seen under its own noise."""
    noise = rng.standard_normal((frames, places.shape[1])).astype(np.float32)
    pos = np.stack([np.arange(frames) * 1.5, np.full(frames, 0.0), np.full(frames, 90.0)], 1)
    return places + 0.5 * noise, pos


def build(path: Path, args: argparse.Namespace, keep: list[int] | None = None) -> list[int]:
    """Build the map (only the drives in ``keep``, if given); return the drive indices added."""
    rng = np.random.default_rng(args.seed)
    places = rng.standard_normal((args.frames, args.dim)).astype(np.float32)
    config = MapConfig(dim=args.dim)
    added: list[int] = []
    seq_of: dict[int, int] = {}
    with MapStore.create(path, config) as store:
        for i in range(args.drives):
            desc, pos = drive(rng, places, i, args.frames)
            earlier = [j for j in added if keep is None or j in keep]
            if keep is not None and i not in keep:
                continue
            other = earlier[int(rng.integers(len(earlier)))] if earlier else None
            edges = []
            if other is not None:
                for f in range(0, args.frames, 10):
                    edges += [EdgeSpec((None, f), (seq_of[other], f), 0.9, f),
                              EdgeSpec((seq_of[other], f), (None, f), 0.9, f)]
            result = store.add_sequence(desc, name=f"drive-{i}", positions=pos, edges=edges)
            seq_of[i] = result.sequence.seq_id
            added.append(i)
        store.search(places[:1], 1)  # load the index: persisted at close
    return added


def measure(path: Path) -> dict[str, int]:
    with MapStore.open(path, readonly=True) as store:
        parts = part_bytes(store.data_path)
        parts["total"] = store.disk_bytes()
        report = check_map(store)
        assert report.ok, report.violations
        parts["vertices"] = store.stats()["vertices"]
        parts["removed_vertices"] = store.removed_vertices()
    return parts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=20)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--remove-every", type=int, default=2,
                        help="remove drives 0, N, 2N, ... (default: every other one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--dir", type=Path, help="work directory (default: a temporary one)")
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        removed = list(range(0, args.drives, args.remove_every))
        t = time.monotonic()
        build(root / "map", args)
        rows: dict[str, Any] = {"built": {**measure(root / "map"),
                                          "seconds": round(time.monotonic() - t, 2)}}
        t = time.monotonic()
        with MapStore.open(root / "map") as store:
            result = store.remove_sequences(removed)
        rows["removed"] = {**measure(root / "map"), "seconds": round(time.monotonic() - t, 2)}
        t = time.monotonic()
        with MapStore.open(root / "map") as store:
            report = store.compact()
        rows["compacted"] = {**measure(root / "map"), "seconds": round(time.monotonic() - t, 2)}
        keep = [i for i in range(args.drives) if i not in removed]
        t = time.monotonic()
        build(root / "baseline", args, keep)
        rows["baseline (kept drives only)"] = {**measure(root / "baseline"),
                                               "seconds": round(time.monotonic() - t, 2)}

    cols = ["total", "map.lmdb", "shards", "index", "vertices", "removed_vertices", "seconds"]
    print(f"{args.drives} drives x {args.frames} frames x {args.dim} dims; removed "
          f"{len(removed)} drives ({result.edges_removed} edges)")
    print(f"{'state':<28}" + "".join(f"{c:>17}" for c in cols))
    for name, row in rows.items():
        print(f"{name:<28}" + "".join(f"{row[c]:>17,}" if isinstance(row[c], int)
                                      else f"{row[c]:>17}" for c in cols))
    ratio = rows["compacted"]["total"] / rows["removed"]["total"]
    vs_base = rows["compacted"]["total"] / rows["baseline (kept drives only)"]["total"]
    print(f"compacted / before compaction: {ratio:.3f}; compacted / baseline: {vs_base:.3f}; "
          f"compaction report: {report.bytes_before:,} -> {report.bytes_after:,} bytes")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: v for k, v in vars(args).items()
                                                  if k not in ("json", "dir")},
                                         "rows": rows, "report": report.to_dict(),
                                         "ratio_compacted_to_removed": ratio,
                                         "ratio_compacted_to_baseline": vs_base}, indent=2,
                                        default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
