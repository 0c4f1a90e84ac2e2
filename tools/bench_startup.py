"""Start-up benchmark: ``sprint-map info --json`` on a large map against bare interpreters.

Times, as fresh processes, interleaved round by round so that drift on a shared machine hits
every command alike:

* ``python -c pass``: the interpreter alone (the floor of any command);
* ``python -c "import numpy, lmdb, click"``: what ``info`` cannot avoid importing;
* ``sprint-map --version``;
* ``sprint-map info MAP --json`` on a map of ``--vertices`` (default 1,000,000) vertices.

and prints each one's median and best wall time, its median CPU time (user + system: what the
process costs, less sensitive than wall time to other jobs on the machine) and the ratio of its
median wall time to the two baselines, plus the heavy modules ``info`` loaded (it should load no
FAISS, SciPy, OpenCV, matplotlib, networkx, nor the HMM: it only reads LMDB). The target: ``info
--json`` within ``TARGET_RATIO`` (1.6x) of the import floor's median. Every command runs with
bytecode caching on (``PYTHONDONTWRITEBYTECODE`` removed from its environment), so the warm-up
round writes ``__pycache__`` and the rounds compare loading cached modules, as installed
packages such as numpy always do. With
``--before DIR`` (a checkout of an older commit, e.g. ``git worktree add --detach DIR REV``)
the same ``info --json`` is also timed with that code (``PYTHONPATH=DIR``), in the same rounds.
The map is built once from precomputed random descriptors with ``tools/bench_scale.py``'s
lifelong builder (drives of 1,000 frames, an edge every 10 frames;
``--dim`` 128) and cached under ``--cache`` (default ``/tmp/sprint-map-bench-startup``), so later
runs only measure::

    python tools/bench_startup.py --json startup.json             # builds the 1M map once (~1 min)
    python tools/bench_startup.py --vertices 20000 --repeat 5     # smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

#: Modules ``info`` must not import (it reads LMDB only).
HEAVY = ("faiss", "scipy", "cv2", "matplotlib", "networkx", "sprint_map.hmm", "rich", "fastapi",
         "uvicorn", "ray")
TARGET_S = 0.25
#: ``info --json``'s median wall time over the ``import numpy, lmdb, click`` floor's.
TARGET_RATIO = 1.6
CLI = "import sys; from sprint_map.cli.main import main; sys.argv[0] = 'sprint-map'; main()"
LOADED = ("import sys, atexit\n"
          "atexit.register(lambda: print(' '.join(sorted(sys.modules)), file=sys.stderr))\n"
          + CLI)


def map_path(cache: Path, vertices: int, dim: int) -> Path:
    """The cached map of ``vertices`` x ``dim``, built on first use (atomically: a map built
    under a temporary name, then renamed)."""
    final = cache / f"v{vertices}-d{dim}" / "startup.map"
    if final.is_dir():
        return final
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_scale  # tools/bench_scale.py: the lifelong map builder

    staging = cache / f"v{vertices}-d{dim}.partial-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    args = argparse.Namespace(seq_len=1000, street_len=500, revisits=5, edge_every=10, dim=dim,
                              seed=0, spectrum=0.0, condition=0.2, set=[], verbose=False)
    t0 = time.perf_counter()
    built = bench_scale.build(staging / "startup.map", vertices, args)
    print(f"built {built['vertices']:,} vertices, {built['sequences']:,} drives in "
          f"{time.perf_counter() - t0:.0f} s under {cache}", flush=True)
    final.parent.parent.mkdir(parents=True, exist_ok=True)
    os.replace(staging, final.parent)
    return final


def commands(path: Path, before: Path | None) -> dict[str, tuple[list[str], Path | None]]:
    """Each timed command's argv and the PYTHONPATH it runs with (None: inherited)."""
    py = sys.executable
    cmds: dict[str, tuple[list[str], Path | None]] = {
        "python -c pass": ([py, "-c", "pass"], None),
        "python -c 'import numpy, lmdb, click'": ([py, "-c", "import numpy, lmdb, click"], None),
        "sprint-map --version": ([py, "-c", CLI, "--version"], None),
        "sprint-map info --json": ([py, "-c", CLI, "info", str(path), "--json"], None),
    }
    if before is not None:
        cmds[f"sprint-map info --json ({before.name})"] = (
            [py, "-c", CLI, "info", str(path), "--json"], before)
    return cmds


def time_once(argv: list[str], pythonpath: Path | None = None) -> tuple[float, float]:
    """Wall time and CPU time (user + system) of one run of ``argv``. CPU time is what the
    process itself costs; on a loaded machine wall time also counts waiting for a core."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    env = child_env(pythonpath)
    # From a neutral directory: ``python -c`` puts the working directory first on sys.path,
    # which would shadow PYTHONPATH from inside a checkout.
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, env=env, cwd=Path.home())
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def child_env(pythonpath: Path | None = None) -> dict[str, str]:
    """The environment of a timed command: this one, with bytecode caching on (without it every
    run of ``sprint-map`` would compile its modules from source, while numpy's are cached)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return env


def heavy_modules_loaded(path: Path) -> list[str]:
    """The heavy modules a real ``info --json`` imports."""
    out = subprocess.run([sys.executable, "-c", LOADED, "info", str(path), "--json"],
                         check=True, capture_output=True, text=True, cwd=Path.home(),
                         env=child_env())
    loaded = out.stderr.split()
    # The HMM's configuration is part of a map's (MapConfig.hmm); its machinery is not.
    return [h for h in HEAVY if any(
        m == h or m.startswith(h + ".") for m in loaded
        if not (h == "sprint_map.hmm" and m in ("sprint_map.hmm", "sprint_map.hmm.config")))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vertices", type=int, default=1_000_000)
    parser.add_argument("--dim", type=int, default=128)
    parser.add_argument("--repeat", type=int, default=15, help="rounds (each times every command)")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/sprint-map-bench-startup"))
    parser.add_argument("--before", type=Path, help="also time info --json with this checkout")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)

    path = map_path(args.cache, args.vertices, args.dim).resolve()
    cmds = commands(path, args.before)
    for argv_, pythonpath in cmds.values():  # warm the page cache and the bytecode caches
        time_once(argv_, pythonpath)
    times: dict[str, list[float]] = {name: [] for name in cmds}
    cpu: dict[str, list[float]] = {name: [] for name in cmds}
    for _ in range(args.repeat):
        for name, (argv_, pythonpath) in cmds.items():
            wall, used = time_once(argv_, pythonpath)
            times[name].append(wall)
            cpu[name].append(used)

    median = {name: statistics.median(t) for name, t in times.items()}
    base, imports = median["python -c pass"], median["python -c 'import numpy, lmdb, click'"]
    rows: list[dict[str, Any]] = [
        {"command": name, "median_s": median[name], "best_s": min(t),
         "cpu_median_s": statistics.median(cpu[name]),
         "ratio_to_python": median[name] / base, "ratio_to_imports": median[name] / imports}
        for name, t in times.items()]
    heavy = heavy_modules_loaded(path)
    info_s = median["sprint-map info --json"]
    ratio = info_s / imports

    print(f"{'command':<40} {'median s':>9} {'best s':>8} {'cpu s':>7} {'/ pass':>7} "
          f"{'/ imports':>9}")
    for r in rows:
        print(f"{r['command']:<40} {r['median_s']:>9.3f} {r['best_s']:>8.3f} "
              f"{r['cpu_median_s']:>7.3f} {r['ratio_to_python']:>7.2f} "
              f"{r['ratio_to_imports']:>9.2f}")
    print(f"map: {args.vertices:,} vertices x {args.dim}; {args.repeat} rounds; load average "
          f"{os.getloadavg()[0]:.1f}; "
          f"info --json {'within' if info_s < TARGET_S else 'ABOVE'} the {TARGET_S} s target, "
          f"{ratio:.2f}x the import floor ({'within' if ratio <= TARGET_RATIO else 'ABOVE'} "
          f"{TARGET_RATIO}x); "
          f"heavy modules info loaded: {', '.join(heavy) or 'none'}")
    if args.json:
        args.json.write_text(json.dumps({
            "rows": rows, "heavy_modules_loaded": heavy, "target_s": TARGET_S,
            "info_over_imports": ratio, "target_ratio": TARGET_RATIO,
            "vertices": args.vertices, "dim": args.dim, "repeat": args.repeat,
            "load_average": os.getloadavg()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
