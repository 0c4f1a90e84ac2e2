"""The ``sprint-map`` command line: a thin layer over :class:`sprint_map.SprintMap`.

Every command is a few lines over the library plus help text with an example. Errors raised on
purpose by the library (:class:`SprintMapError`) print one ``Error: ...`` line on stderr and exit
with the error's own code; there is never a traceback for bad input (:mod:`sprint_map.cli.common`).
This module holds the group's entry point and the commands that make and localise drives
(``init``, ``ingest``, ``localize``); :mod:`sprint_map.cli.maintenance` and
:mod:`sprint_map.cli.runs` add the others to the same group.
"""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path
from typing import Any, NoReturn

import click

from sprint_map import DescriptorSpec, Drive, IngestResult
from sprint_map.cli.common import (
    bag_options,
    emit,
    hmm_overrides,
    main,
    model_options,
    read_json_config,
    trace_option,
)
from sprint_map.config import MapConfig
from sprint_map.errors import InputError, SprintMapError
from sprint_map.fleet.runtime import RAY_HELP
from sprint_map.map import SprintMap
from sprint_map.util import dataclass_dict


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--dim", type=int, help="Descriptor dimension (for precomputed .npy descriptors).")
@click.option("--descriptor", type=click.Choice(["precomputed", "hog", "patchnorm", "onnx"]),
              default=None, help="Descriptor kind; hog/patchnorm/onnx set the dimension "
              "themselves.")
@click.option("--model", type=click.Path(dir_okay=False), help="onnx: the ONNX model file "
              "(one descriptor per image; pip install \"sprint-map[onnx]\"). The SHA-256 of it "
              "and of each weights file it loads is stored: a different file there later is "
              "refused.")
@click.option("--model-card", type=click.Path(dir_okay=False), help="onnx: JSON card "
              "{input_size, channels, mean, std, normalize} (default: MODEL's .card.json "
              "beside it, else its fixed input size, RGB, ImageNet mean/std, l2).")
@click.option("--config", "config_json", type=click.Path(exists=True, dir_okay=False),
              help="JSON file of further MapConfig fields, e.g. {\"index_type\": \"flat\", "
              "\"hmm\": {\"k\": 20}} (docs/hmm.md, \"HMMConfig\").")
@click.option("--admission", type=click.Choice(["all", "novel"]), default=None,
              help="Which frames of an ingested drive the map stores: all (default: recall "
              "parity) or only those it does not already hold (novel: a lifelong map that "
              "stays smaller, at a measured cost of 0.7-0.9 points of later recall@1 on the "
              "hard rendered city, 16-26 % fewer vertices; docs/benchmarks.md, \"Bounded "
              "map\").")
@click.option("--centring", type=click.Choice(["none", "drive"]), default=None,
              help="How descriptors enter the map: as described (none, default) or centred "
              "on each drive's running mean (drive: answers by place, not by condition; on "
              "Nordland +1.1 / +6.7 points causal, +0.6 / +2.5 smoothed, merge precision "
              "-0.8 / -0.5; docs/benchmarks.md, \"Conditions\").")
def init(map_path: str, dim: int | None, descriptor: str | None, model: str | None,
         model_card: str | None, config_json: str | None, admission: str | None,
         centring: str | None) -> None:
    """Create an empty map in MAP (which must be absent or empty).

    \b
    Examples:
      sprint-map init city.map --descriptor hog      # images and video, the paper's HoG
      sprint-map init city.map --dim 256             # precomputed .npy descriptors
      sprint-map init city.map --descriptor onnx --model eigenplaces.onnx
      sprint-map init fleet.map --dim 256 --admission novel
      sprint-map init seasons.map --descriptor hog --centring drive
    """
    options = read_json_config(config_json)
    if centring is not None:
        options["centring"] = {**options.get("centring", {}), "mode": centring}
    if admission is not None:
        options["admission"] = {**options.get("admission", {}), "mode": admission}
    kind = descriptor or options.pop("descriptor", None) or (
        "onnx" if model is not None else "precomputed" if dim is not None else "hog")
    if (model is not None or model_card is not None) != (kind == "onnx"):
        raise InputError("--descriptor onnx needs --model FILE" if kind == "onnx"
                         else "--model and --model-card are for --descriptor onnx")
    if kind == "onnx":
        from sprint_map import onnx_params

        params = onnx_params(str(model), model_card)
        if dim is not None and dim != params["dim"]:
            raise InputError(f"{model}: the model gives {params['dim']} dimensions, not {dim}")
        config = MapConfig.from_dict({**options, "descriptor": kind, "descriptor_params": params,
                                      "dim": params["dim"]})
    elif kind == "precomputed":
        if dim is None:
            raise InputError("--dim is required for precomputed descriptors")
        config = MapConfig.from_dict({**options, "dim": dim, "descriptor": kind})
    else:
        params = options.pop("descriptor_params", {})
        config = MapConfig.from_dict({**options, "descriptor": kind, "descriptor_params": params,
                                      "dim": DescriptorSpec(kind, params).dim})
        if dim is not None and dim != config.dim:
            raise InputError(f"{kind} descriptors have {config.dim} dimensions, not {dim}")
    with SprintMap.create(map_path, config) as m:
        click.echo(f"created {m.path} ({config.descriptor}, dim {config.dim})")



@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.argument("sources", metavar="SOURCE...", nargs=-1, required=True, type=click.Path())
@click.option("--name", help="Sequence name, unique in the map (default: SOURCE's name; one "
              "SOURCE only).")
@click.option("--positions", type=click.Path(dir_okay=False),
              help="CSV frame,x,y[,heading_deg][,sigma_m] or frame,lat,lon[,...] with a header "
              "row (one SOURCE only; default: the drive folder's own positions.csv, or a "
              "bag's GNSS): stored with the drive, and its GNSS fixes where the map has "
              "positions (a frame without a row: no fix).")
@click.option("--no-merge", is_flag=True, help="Append the sequence as it is, without localising it.")
@click.option("--thumbnails", is_flag=True, help="Keep a small JPEG of each frame in the map "
              "(images and video; about 2 KiB a frame), for viewers and to verify merges on "
              "the images against the map's own thumbnails.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON (several "
              "SOURCEs: a list, one object per drive).")
@click.option("--ray", "ray_spec", metavar="local|auto|ADDRESS", help=RAY_HELP + " (drives "
              "described and localised in parallel as Ray tasks, committed in order here).")
@trace_option
@bag_options
@model_options
def ingest(map_path: str, sources: tuple[str, ...], name: str | None, positions: str | None,
           no_merge: bool, thumbnails: bool, as_json: bool, ray_spec: str | None,
           trace: str | None, image_topic: str | None, gnss_topic: str | None,
           every_m: float | None, stride: int, quiet: bool, k: int | None, window: str | None,
           hmm_pairs: tuple[str, ...]) -> None:
    """Localise each drive SOURCE against MAP, then merge it with its decisions as edges.

    SOURCE is a folder of images, a video file, a .npy of N x D descriptors, or a ROS bag
    (.bag, .mcap, a ROS 2 bag folder; pip install "sprint-map[ros]"). The first drive of an
    empty map is added as it is. Several SOURCEs are ingested in the order given, each its own
    sequence (named after its source, or after its folder where two sources share a name)
    localised against the map holding the earlier ones, as separate commands would, and
    committed in groups. A failure stops there: the drives before it stay committed. Each
    drive's positions: --positions, else a bag's GNSS, else its folder's positions.csv. A map
    made with `init --admission novel` stores only the frames it lacks (--json:
    frames_stored, frames_skipped, each decision's stored_as).

    \b
    Examples:
      sprint-map ingest city.map drives/monday/ --positions drives/monday/positions.csv
      sprint-map ingest city.map monday.npy --name monday --json
      sprint-map ingest city.map tuesday.mp4 --stride 5 --no-merge
      sprint-map ingest city.map wednesday.npy --trace wednesday.trace.npz
      sprint-map ingest city.map drives/friday/ --thumbnails
      sprint-map ingest city.map mon.npy tue.npy wed.npy   # three drives, in this order
      sprint-map ingest city.map drives/*/ --ray auto      # on the Ray cluster joined here
      sprint-map ingest city.map drive.bag --image-topic /cam/image --every-m 2
      sprint-map ingest city.map drives/*/descriptors.npy  # each with its positions.csv
    """
    # The front end's sources and the trace load here, not at start-up: `info` and the other
    # commands never need them (tests/test_startup.py).
    from sprint_map import (
        BagOptions,
        TraceRecorder,
        drive_names,
        drive_positions,
        gnss_fixes,
        own_positions,
    )
    from sprint_map.cli.progress import progress_display
    from sprint_map.util.output import Output

    bag = BagOptions(image_topic, gnss_topic, every_m)
    single = {"--name": name, "--positions": positions, "--trace": trace}
    for option, value in single.items():
        if value is not None and len(sources) > 1:
            raise InputError(f"{option} is for one SOURCE; {len(sources)} given (each drive is "
                             "named after its source)")
    if ray_spec is not None:
        given = {"--positions": positions is not None, "--trace": trace is not None,
                 "--thumbnails": thumbnails, "--image-topic/--gnss-topic/--every-m":
                 bag != BagOptions()}
        for option in (option for option, on in given.items() if on):
            raise InputError(f"{option} is not available with --ray")
        for source in sources:  # the farm stores no positions: never drop them silently
            own = own_positions(source)
            if own is not None:
                raise InputError(f"{source}: its positions ({own}) are not carried by --ray; "
                                 "ingest it without --ray to keep them")
    overrides = hmm_overrides(k, window, hmm_pairs)
    done: list[dict[str, Any]] = []

    bars: list[Any] = []  # each drive's progress display (None without one)

    def report(results: list[IngestResult]) -> None:
        for result in results:
            if len(done) < len(bars) and bars[len(done)] is not None:
                bars[len(done)].close()  # its smoothing and merge are over
            done.append(result.to_dict())
            if not as_json:
                click.echo(_ingest_line(done[-1]))

    if ray_spec is not None:  # the ingest farm: Ray is imported from here on only
        from sprint_map.fleet.farm import farm_ingest
        from sprint_map.fleet.runtime import connect

        connect(ray_spec)
    with SprintMap.open(map_path) as m, contextlib.ExitStack() as stack:
        hmm = dataclass_dict.replace(m.config.hmm, **overrides) if overrides else None
        if ray_spec is not None:
            try:
                farm_ingest(m, sources, names=[name], stride=stride, merge=not no_merge,
                            hmm=hmm, on_commit=lambda r: report([r.result]))
            except SprintMapError as exc:
                _stop_after(exc, sources, done, as_json)
        opened = []
        for source in sources if ray_spec is None else ():  # each opened (and checked) first
            label = "ingesting" if len(sources) == 1 else f"ingesting {source}"
            bars.append(stack.enter_context(progress_display(
                label, quiet, after="smoothing and merging" if not no_merge else "committing")))
            src = m.open_source(source, stride=stride, thumbnails=thumbnails, bag=bag,
                                progress=bars[-1])
            opened.append((src, drive_positions(src, source, positions, stride)))
        names = (drive_names([Path(s) for s in sources], [src.name for src, _ in opened])
                 if opened and name is None else [name] * len(opened))
        # Streamed: each batch is described, localised and written (uncommitted) in turn.
        # An empty --name is refused by the name rules, not replaced by the source's name.
        # one frame (lat/lon or x/y) for every drive and the map, checked before any is stored
        placed = list(zip([src for src, _ in opened],
                          m.metric_positions_of([table for _, table in opened]), strict=True))
        drives = [Drive(src.iter_batches(), label, rows, str(source), src.thumbnails,
                        None if rows is None else gnss_fixes(rows))
                  for (src, rows), label, source in zip(placed, names, sources, strict=False)]
        # The trace's file is made now: a path that cannot be written is refused before the
        # drive is localised and committed (after the commit, a failure is only a warning).
        trace_out = stack.enter_context(Output(trace, "trace", forbidden=[m.path])) \
            if trace else None
        recorder = TraceRecorder(m) if trace else None
        try:
            results = m.ingest_drives(drives, merge=not no_merge, hmm=hmm, on_committed=report,
                                      observe=recorder.attach if recorder else None)
        except SprintMapError as exc:
            _stop_after(exc, sources, done, as_json)
        if recorder is not None and trace_out is not None:
            result = results[0]
            try:
                recorder.save(trace_out, final=result.decisions, merged=result.merged,
                              meta={"command": "ingest", "source": str(sources[0]),
                                    "smoothed": True,
                                    "seq_id": result.to_dict()["seq_id"]})
            except (SprintMapError, OSError) as exc:
                m.warnings.append(f"the drive is committed, but its trace was not written: "
                                  f"{exc}")
    for warning in [w for src, _ in opened for w in src.warnings] + m.warnings:
        click.echo(f"Warning: {warning}", err=True)
    if as_json:
        click.echo(json.dumps(done[0] if len(sources) == 1 else done, indent=2))


def _stop_after(exc: SprintMapError, sources: tuple[str, ...], done: list[dict[str, Any]],
                as_json: bool) -> NoReturn:
    """A drive of several failed: report the ones committed, then which one failed; exit."""
    if not done:
        raise exc
    if as_json:  # the drives that are in the map, then which one failed
        click.echo(json.dumps(done, indent=2))
    click.echo(f"Error: {sources[len(done)]}: {exc} ({len(done)} earlier drive(s) "
               "committed)", err=True)
    sys.exit(exc.exit_code)


def _ingest_line(out: dict[str, Any]) -> str:
    """One drive's ingest, in one line of text."""
    if out["already_committed"]:  # a retry: the drive is in the map already, nothing added
        return (f"sequence {out['seq_id']} ({out['name']}) was already committed with these "
                f"{out['frames']} frames: nothing added")
    matched = sum(d["seq_id"] is not None for d in out["decisions"])
    if out["seq_id"] is None:  # admission stored nothing: the drive's sightings only
        return (f"stored nothing of {out['name']}: {out['frames']} frames, {matched} matched, "
                f"{out['sightings']} places seen again")
    stored = ("" if out["frames_stored"] == out["frames"]
              else f" ({out['frames_stored']} stored, {out['sightings']} places seen again)")
    return (f"added sequence {out['seq_id']} ({out['name']}): {out['frames']} frames{stored}, "
            f"{matched} matched, {out['edges_added']} edges, component {out['component']}")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.argument("source", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the decisions as JSON.")
@click.option("--out", type=click.Path(dir_okay=False), help="Also write the JSON to this file.")
@click.option("--smooth", is_flag=True,
              help="Decide each frame from the smoothed posterior (the whole drive, as ingest "
                   "merges); default: causal, as a vehicle gets the answers.")
@click.option("--thumbnails", is_flag=True,
              help="With --smooth: verify on the images, against the map's thumbnails, the "
                   "runs the merge rule's lookalike tests refuse, as ingest --thumbnails does "
                   "(images and video).")
@click.option("--positions", type=click.Path(dir_okay=False),
              help="CSV frame,x,y[,heading_deg][,sigma_m]: the drive's GNSS fixes, weighed "
              "against the map's positions (each decision's gnss_dist_m).")
@click.option("--lag", type=int, default=0, show_default=True, metavar="L",
              help="Answer each frame once L more frames were seen (fixed-lag smoothing, "
                   "0..10000; 0: causal); one answer per frame, in frame order.")
@trace_option
@bag_options
@model_options
def localize(map_path: str, source: str, as_json: bool, out: str | None, smooth: bool,
             thumbnails: bool, lag: int, positions: str | None, trace: str | None,
             image_topic: str | None, gnss_topic: str | None, every_m: float | None,
             stride: int, quiet: bool, k: int | None, window: str | None,
             hmm_pairs: tuple[str, ...]) -> None:
    """Localise the drive SOURCE against MAP without changing the map.

    \b
    Examples:
      sprint-map localize city.map drives/friday/ --json
      sprint-map localize city.map friday.npy --smooth --json
      sprint-map localize city.map friday.npy --lag 10 --json      # each answer 10 frames late
      sprint-map localize city.map drives/friday/ --smooth --thumbnails --json
      sprint-map localize city.map friday.npy --k 20 --out friday.json
      sprint-map localize city.map friday.npy --trace friday.trace.npz   # sprint-map view
      sprint-map localize city.map friday.npy --smooth --positions friday.csv --json  # GNSS
      sprint-map localize city.map friday.mcap --image-topic /cam/compressed --json
    """
    # Loaded here, not at start-up (as in ingest).
    from sprint_map import BagOptions, TraceRecorder, drive_positions, gnss_fixes
    from sprint_map.cli.progress import progress_display
    from sprint_map.util.output import Output

    if thumbnails and not smooth:
        raise InputError("--thumbnails verifies smoothed decisions: add --smooth")
    if lag:
        from sprint_map import validate_lag

        validate_lag(lag, whole_drive=bool(smooth or trace), fixes=bool(positions), flags=True)
    overrides = hmm_overrides(k, window, hmm_pairs)
    with SprintMap.open(map_path, readonly=True) as m, contextlib.ExitStack() as outputs, \
            progress_display("localising", quiet, after="smoothing" if smooth else None
                             ) as progress:
        # Outputs are made first: an unwritable path (or one inside the map) is refused early.
        trace_out = outputs.enter_context(Output(trace, "trace", forbidden=[m.path])) \
            if trace else None
        json_out = outputs.enter_context(Output(out, "JSON", forbidden=[m.path])) \
            if out else None
        src = m.open_source(source, stride=stride, progress=progress, thumbnails=thumbnails,
                            bag=BagOptions(image_topic, gnss_topic, every_m))
        rows = (m.metric_positions(drive_positions(src, source, positions, stride))
                if positions else None)
        recorder = TraceRecorder(m) if trace else None
        decisions, timing = m.localize(  # streamed, searches batched
            src.iter_batches(), smooth=smooth, lag=lag,
            observe=recorder.attach if recorder else None,
            thumbnails=src.thumbnails if thumbnails else None,
            fixes=None if rows is None else gnss_fixes(rows), **overrides)
        if recorder is not None and trace_out is not None:
            recorder.save(trace_out, final=decisions, meta={
                "command": "localize", "smoothed": smooth, "source": str(source)})
        t = timing.to_dict()
        data = {"decisions": [d.to_dict() for d in decisions], "timing": t}
        if json_out is not None:
            json_out.stream.write(json.dumps(data, indent=1).encode())
            json_out.commit()
    for warning in src.warnings:
        click.echo(f"Warning: {warning}", err=True)
    matched = sum(d.is_match for d in decisions)
    emit(data, as_json, "\n".join(
        [f"{d.frame:>6}  " + (f"seq {d.seq_id} image {d.image_id}" if d.is_match else "no match")
         + f"  p={d.prob:.3f} novel={d.novel_prob:.3f}" for d in decisions]
        + [f"{matched}/{len(decisions)} frames matched; per frame: retrieval "
           f"{t['retrieval_ms_per_frame']} ms, HMM {t['hmm_ms_per_frame']} ms"]))
    for warning in m.warnings:  # on stderr: a --json answer on stdout stays JSON
        click.echo(f"Warning: {warning}", err=True)

# The other commands register on the same group when their modules are imported.
from sprint_map.cli.join import join  # noqa: E402
from sprint_map.cli.maintenance import (  # noqa: E402
    check,
    compact,
    components,
    edges,
    export,
    index,
    info,
    remove,
    sequences,
    unmerge,
)
from sprint_map.cli.runs import demo, eval_, serve, view  # noqa: E402

__all__ = ["check", "compact", "components", "demo", "edges", "eval_", "export", "index", "info",
           "ingest", "init", "join", "localize", "main", "remove", "sequences", "serve", "unmerge", "view"]
