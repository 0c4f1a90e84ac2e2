"""The demo behind the README's first command: a map from embedded data, evaluated end to end.

No download: the default is the synthetic city rendered by :mod:`sprint_map.synth` (the HoG path
runs on real rendered images). When the Nordland summer/winter set is present on the machine
(``$SPRINT_MAP_NORDLAND``, or ``../shared/data/nordland`` next to the working directory or the
checkout) ``auto`` evaluates on it instead, in both directions, with the paper's protocol.
``city-novel`` is the harder generated world (:data:`sprint_map.synth.city.PRESETS`): later
drives spend most of their frames on streets no earlier drive saw, or saw the other way, and
some streets are copies of others, so "no match" and false merges are exercised, not only
recall.
``latent`` is a world of another family (:mod:`sprint_map.synth.latent`): descriptor-level
drives over latent places, no rendering, evaluated on its precomputed descriptors.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from sprint_map import Dataset
from sprint_map.config import MapConfig
from sprint_map.errors import ConfigError, InputError
from sprint_map.evaluation.report import write_report
from sprint_map.evaluation.runner import EvalOptions, Log, config_for, run_evaluation

__all__ = ["CITY_FRAMES", "CITY_TRAVERSALS", "DATASETS", "LATENT_FRAMES", "LATENT_TRAVERSALS",
           "NORDLAND_ENV", "find_nordland", "run_demo"]

NORDLAND_ENV = "SPRINT_MAP_NORDLAND"
#: Demo city: small enough to render, map and evaluate well within the two-minute budget.
CITY_TRAVERSALS = 6
CITY_FRAMES = 300
#: ``run_demo``'s choices (``sprint-map demo --dataset``).
DATASETS = ("auto", "city", "city-novel", "latent", "nordland")
#: Demo latent world (:mod:`sprint_map.synth.latent`): descriptors only, so cheap to generate.
LATENT_TRAVERSALS = 10
LATENT_FRAMES = 300


def find_nordland() -> Path | None:
    """The Nordland data set folder if present (summer/ and winter/ inside), else None."""
    candidates = []
    if os.environ.get(NORDLAND_ENV):
        candidates.append(Path(os.environ[NORDLAND_ENV]))
    checkout = Path(__file__).resolve().parents[2]
    for base in (Path.cwd(), checkout):
        candidates.append(base.parent / "shared" / "data" / "nordland")
    for path in candidates:
        if (path / "summer").is_dir() and (path / "winter").is_dir():
            return path
    return None


def run_demo(out_dir: Path, which: str = "auto", log: Log = lambda _: None,
             gnss_sigma: float = 0.0) -> tuple[dict[str, Any], dict[str, Path]]:
    """Evaluate on Nordland (if ``which`` allows and it is present) or a generated city.

    ``which`` is one of :data:`DATASETS`; ``auto`` and ``city`` render ``city``, and each
    generated world is written once into ``out_dir/<name>`` and reused by later runs.
    ``gnss_sigma`` > 0 adds the GNSS-aided run (:class:`~sprint_map.evaluation.runner.
    EvalOptions`).
    """
    if which not in DATASETS:
        raise ConfigError(f"dataset must be one of {', '.join(DATASETS)}")
    EvalOptions(gnss_sigma=gnss_sigma)  # a bad sigma is refused before any work
    nordland = find_nordland() if which in ("auto", "nordland") else None
    if which == "nordland" and nordland is None:
        raise InputError(f"Nordland not found; set ${NORDLAND_ENV} to its folder")
    config = MapConfig.for_descriptor("hog")
    if nordland is not None:
        log(f"Nordland found at {nordland}: summer <-> winter, tolerance +/- 1 frame")
        dataset = Dataset.open(nordland, {"alignment": "frame", "tolerance_frames": 1})
        options = EvalOptions(protocol="pairs", database="summer", query="winter",
                              both_directions=True, gnss_sigma=gnss_sigma)
    elif which == "latent":
        from sprint_map.synth.latent import LATENT_PRESETS, generate_latent

        world = out_dir / "latent"
        if not (world / "dataset.json").is_file():
            log(f"generating the latent world into {world}")
            generate_latent(world, n_traversals=LATENT_TRAVERSALS,
                            frames_per_traversal=LATENT_FRAMES, seed=0,
                            config=LATENT_PRESETS["latent"])
        dataset = Dataset.open(world)
        config = config_for(dataset)
        options = EvalOptions(protocol="lifelong", gnss_sigma=gnss_sigma)
    else:
        from sprint_map.synth.city import PRESETS, generate_city

        name = which if which in PRESETS else "city"
        city = out_dir / name
        if not (city / "dataset.json").is_file():
            log(f"rendering the synthetic city into {city}")
            generate_city(city, n_traversals=CITY_TRAVERSALS, frames_per_traversal=CITY_FRAMES,
                          seed=0, config=PRESETS[name])
        dataset = Dataset.open(city)
        options = EvalOptions(protocol="lifelong", gnss_sigma=gnss_sigma)
    results = run_evaluation(dataset, out_dir / "maps", config, options, log=log)
    return results, write_report(results, out_dir)
