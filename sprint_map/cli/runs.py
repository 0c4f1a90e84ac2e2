"""``sprint-map`` commands that run something beside a map: ``eval``, ``demo``, ``serve`` and
``view`` (registered on the group of :mod:`sprint_map.cli.common`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import click

from sprint_map.cli.common import (
    gnss_option,
    hmm_overrides,
    key_values,
    log_to_stderr,
    main,
    model_options,
    read_json_config,
)
from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.fleet.runtime import RAY_HELP
from sprint_map.util import dataclass_dict

__all__ = ["demo", "eval_", "serve", "view"]


@main.command(name="eval")
@click.argument("dataset", type=click.Path(exists=True, file_okay=False))
@click.option("--layout", type=click.Choice(["traversals", "vpr"]), default="traversals",
              show_default=True, help="traversals: one folder per traversal; vpr: database/ "
              "and queries/ folders of @UTM-named images (recall@1/5/10/20 of k-NN and SPRINT "
              "in results.json; --radius default 25 m).")
@click.option("--protocol", type=click.Choice(["lifelong", "pairs"]), default="lifelong",
              show_default=True, help="lifelong: each traversal localised against all earlier "
              "ones, then merged; pairs: one database, one query traversal.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Where results, plots and maps go (default: ./eval-<dataset name>).")
@click.option("--database", help="pairs: database traversal (default: the first).")
@click.option("--query", help="pairs: query traversal (default: the second).")
@click.option("--both-directions", is_flag=True, help="pairs: also swap database and query.")
@click.option("--descriptor", type=click.Choice(["auto", "hog", "patchnorm", "precomputed"]),
              default="auto", show_default=True,
              help="auto: the traversals' descriptors.npy if they have them, else HoG of images.")
@click.option("--model", type=click.Path(dir_okay=False), help="vpr layout: describe the "
              "images with this ONNX model (as init --descriptor onnx --model).")
@click.option("--model-card", type=click.Path(dir_okay=False), help="vpr layout: the "
              "model's card (default: beside it, or the model's own input size).")
@click.option("--alignment", type=click.Choice(["frame", "position"]),
              help="Ground truth, if the data set has no dataset.json (Nordland: frame).")
@click.option("--tolerance", type=int, help="Frame alignment: +/- frames counted correct.")
@click.option("--radius", type=float, help="Position alignment: metres counted correct.")
@click.option("--map-config", "map_pairs", multiple=True, metavar="KEY=VALUE",
              help="Override a MapConfig field of the evaluation maps (repeatable, JSON "
              "values), e.g. index_type=ivf-pq.")
@gnss_option
@click.option("--learn-every", type=click.IntRange(min=1), default=None, metavar="EDGES",
              help="lifelong: also run it with the maps learning their descriptor from their "
              "merges after every EDGES new edges (learn_every), reported beside the run "
              "without learning (in OUT/learned).")
@model_options
def eval_(dataset: str, layout: str, protocol: str, out_dir: str | None, database: str | None,
          query: str | None, both_directions: bool, descriptor: str, model: str | None,
          model_card: str | None, alignment: str | None,
          tolerance: int | None, radius: float | None, map_pairs: tuple[str, ...],
          gnss_sigma: float, learn_every: int | None, stride: int, quiet: bool, k: int | None,
          window: str | None, hmm_pairs: tuple[str, ...]) -> None:
    """Evaluate k-NN and SPRINT on DATASET (one folder per traversal); write JSON, markdown, PNGs.

    \b
    Examples:
      sprint-map eval data/city --out eval-city
      sprint-map eval ../shared/data/nordland --protocol pairs --database summer \\
          --query winter --both-directions --alignment frame --tolerance 1
      sprint-map eval ../shared/data/nordland --protocol pairs --database summer \\
          --query winter --alignment frame --tolerance 1 --map-config index_type=ivf-pq \\
          --map-config index_nlist=64 --map-config index_segment_rows=256
      sprint-map eval data/city --gnss-sigma 10   # also GNSS-aided, side by side
      sprint-map eval datasets/pitts30k --layout vpr --radius 25 --out eval-pitts
      sprint-map eval datasets/pitts30k --layout vpr --model eigenplaces.onnx
      sprint-map eval data/city --learn-every 2000   # with and without learning
    """
    if radius is not None and not (math.isfinite(radius)
                                   and (radius > 0 if layout == "vpr" else radius >= 0)):
        raise InputError(f"--radius must be a finite number of metres "
                         f"{'above 0' if layout == 'vpr' else '(0 or more)'}, got {radius:g}")
    if layout == "vpr":
        _eval_vpr(dataset, out_dir, descriptor, (model, model_card), radius, map_pairs, k,
                  window, hmm_pairs, quiet)
        return
    if model is not None or model_card is not None:
        raise InputError("--model is for --layout vpr (a traversal data set's map: init "
                         "--descriptor onnx, then ingest)")
    from sprint_map import Dataset
    from sprint_map.evaluation.report import markdown_table, write_report
    from sprint_map.evaluation.runner import EvalOptions, config_for, run_evaluation

    gt: dict[str, Any] = {}
    for key, value in (("alignment", alignment), ("tolerance_frames", tolerance),
                       ("radius_m", radius)):
        if value is not None:
            gt[key] = value
    data = Dataset.open(dataset, gt or None)
    config = config_for(data, descriptor)
    if map_pairs:
        config = config.replace(**key_values(map_pairs, "--map-config"))
    overrides = hmm_overrides(k, window, hmm_pairs)
    hmm = dataclass_dict.replace(config.hmm, **overrides) if overrides else None
    options = EvalOptions(protocol=protocol, database=database, query=query,
                          both_directions=both_directions, stride=stride, gnss_sigma=gnss_sigma)
    out = Path(out_dir or f"eval-{data.path.resolve().name}")
    runs = [(out, config, "")]
    if learn_every:
        runs.append((out / "learned", config.replace(learn_every=learn_every),
                     f"\nwith learning (learn_every={learn_every}):"))
    for where, cfg, title in runs:
        results = run_evaluation(data, where / "maps", cfg, options, hmm, log=log_to_stderr(quiet))
        paths = write_report(results, where)
        click.echo(f"{title}\n{markdown_table(results)}" if title else markdown_table(results))
        click.echo("\n".join(f"{kind}: {path}" for kind, path in paths.items()))


def _eval_vpr(dataset: str, out_dir: str | None, descriptor: str,
              model: tuple[str | None, str | None], radius: float | None,
              map_pairs: tuple[str, ...], k: int | None, window: str | None,
              hmm_pairs: tuple[str, ...], quiet: bool) -> None:
    """``eval --layout vpr``: recall@1/5/10/20 of k-NN and SPRINT into results.json."""
    from sprint_map import VprDataset
    from sprint_map.evaluation.vpr import markdown_recall, run_vpr_evaluation

    if descriptor == "precomputed":
        raise InputError("--layout vpr describes the images: --descriptor auto, hog or patchnorm")
    data = VprDataset.open(dataset)
    if model[0] is not None:
        from sprint_map import onnx_params

        params = onnx_params(model[0], model[1])
        config = MapConfig(dim=params["dim"], descriptor="onnx", descriptor_params=params)
    elif model[1] is not None:
        raise InputError("--model-card needs --model FILE")
    else:
        config = MapConfig.for_descriptor("hog" if descriptor == "auto" else descriptor)
    if map_pairs:  # the same keys as the traversal layout's (flat or nested)
        config = config.replace(**key_values(map_pairs, "--map-config"))
    overrides = hmm_overrides(k, window, hmm_pairs)
    hmm = dataclass_dict.replace(config.hmm, **overrides) if overrides else None
    out = Path(out_dir or f"eval-{data.path.resolve().name}")
    results = run_vpr_evaluation(data, out, config, hmm, 25.0 if radius is None else radius,
                                 log=log_to_stderr(quiet))
    click.echo(markdown_recall(results))
    click.echo(f"results: {out / 'results.json'}")


@main.command()
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="sprint-demo",
              show_default=True, help="Where the data, maps, results and plots go.")
@click.option("--dataset", "which",
              type=click.Choice(["auto", "city", "city-novel", "latent", "nordland"]),
              default="auto", show_default=True,
              help="auto: Nordland when it is present on this machine, else the generated city; "
              "city-novel: a harder city (mostly novel streets, some driven the other way, "
              "aliased streets); latent: descriptor-level drives over latent places (another "
              "world family, no rendering).")
@gnss_option
@click.option("--quiet", "-q", is_flag=True, help="No progress messages.")
def demo(out_dir: str, which: str, gnss_sigma: float, quiet: bool) -> None:
    """Build a map from the embedded default data, evaluate it, print the table and plots.

    With no data to download: the generated city (rendered images, several drives with
    condition changes, aliasing and novel streets), or the Nordland summer/winter set when
    present (found through $SPRINT_MAP_NORDLAND or ../shared/data/nordland).

    \b
    Examples:
      sprint-map demo --out sprint-demo
      sprint-map demo --dataset city-novel --out sprint-demo-novel
      sprint-map demo --dataset latent --out sprint-demo-latent
      sprint-map demo --dataset city --gnss-sigma 10   # image only and GNSS-aided
    """
    from sprint_map.evaluation.demo import run_demo
    from sprint_map.evaluation.report import markdown_table

    results, paths = run_demo(Path(out_dir), which, log=log_to_stderr(quiet), gnss_sigma=gnss_sigma)
    click.echo(markdown_table(results))
    click.echo("\n".join(f"{kind}: {path}" for kind, path in paths.items()))


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--host", help="Address to listen on (default 127.0.0.1); beyond loopback a "
              "bearer token is required.")
@click.option("--port", type=click.IntRange(0, 65535),
              help="TCP port (default 8000; 0: a free one, printed at start).")
@click.option("--token-file", type=click.Path(dir_okay=False),
              help="File holding the bearer token (default: $SPRINT_MAP_TOKEN, if set).")
@click.option("--config", "config_json", type=click.Path(exists=True, dir_okay=False),
              help="JSON file of ServerConfig limits (docs/service.md, \"Threads and "
              "queues\").")
@click.option("--ray", "ray_spec", metavar="local|auto|ADDRESS", help=RAY_HELP + " (the "
              "sessions' localisers in Ray actors; commits here; the API is the same).")
@click.option("--replicas", type=click.IntRange(min=1), default=2, show_default=True,
              help="Localiser replicas with --ray (spread over the cluster's nodes).")
def serve(map_path: str, host: str | None, port: int | None, token_file: str | None,
          config_json: str | None, ray_spec: str | None, replicas: int) -> None:
    """Serve MAP over HTTP: vehicles stream frames, get places, and commit their drives.

    Stops gracefully on SIGTERM/Ctrl-C (open sessions discarded unless configured to commit).
    API: POST /v1/sessions, /v1/sessions/ID/frames, /v1/sessions/ID/commit; see /docs.

    \b
    Examples:
      sprint-map serve city.map --port 8000
      SPRINT_MAP_TOKEN=s3cret sprint-map serve city.map --host 0.0.0.0
      sprint-map serve city.map --ray auto --replicas 4
    """
    from sprint_map.server.config import ServerConfig
    from sprint_map.server.run import serve_map
    from sprint_map.viewer.app import mount_viewer

    options = read_json_config(config_json)
    given = {"host": host, "port": port, "token_file": token_file}
    options.update({key: value for key, value in given.items() if value is not None})
    serve_map(map_path, ServerConfig.from_dict(options), ray=ray_spec, replicas=replicas,
              extensions=[mount_viewer])


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--trace", type=click.Path(dir_okay=False), metavar="OUT",
              help="Also play back this trace (from localize/ingest --trace OUT).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; beyond loopback a bearer token is required.")
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="TCP port (0: a free one, printed at start).")
@click.option("--token-file", type=click.Path(dir_okay=False),
              help="File holding the bearer token (default: $SPRINT_MAP_TOKEN, if set).")
def view(map_path: str, trace: str | None, host: str, port: int, token_file: str | None) -> None:
    """Serve a page that shows MAP: drives, edges, match matrices, trace playback.

    Open the printed address in a browser (it works offline). The map is opened read-only.

    \b
    Examples:
      sprint-map view city.map
      sprint-map view city.map --trace friday.trace.npz --port 8081
    """
    from sprint_map.viewer.run import view_map

    view_map(map_path, trace=trace, host=host, port=port, token_file=token_file)
