"""The ``sprint-map`` command line: a thin layer over :class:`sprint_map.SprintMap`.

Every command is a few lines over the library plus help text with an example. Errors raised on
purpose by the library (:class:`SprintMapError`) print one ``Error: ...`` line on stderr and exit
with the error's own code; there is never a traceback for bad input.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path
from typing import Any, NoReturn

import click

from sprint_map.cli.progress import progress_display
from sprint_map.config import MapConfig
from sprint_map.errors import InputError, SprintMapError
from sprint_map.fleet.runtime import RAY_HELP
from sprint_map.frontend.bags import BagOptions
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.positions import gnss_fixes
from sprint_map.frontend.sources import drive_names, drive_positions
from sprint_map.localize.trace import TraceRecorder
from sprint_map.map import SprintMap
from sprint_map.merge.commit import IngestResult
from sprint_map.merge.drives import Drive
from sprint_map.util import dataclass_dict
from sprint_map.util.output import Output
from sprint_map.util.validation import parse_seq_ref

__all__ = ["check", "compact", "components", "demo", "edges", "eval_", "export", "index", "info",
           "ingest", "init", "localize", "main", "remove", "sequences", "serve", "unmerge", "view"]


class _Group(click.Group):
    """Turns library errors into one line on stderr and a distinct exit code."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except SprintMapError as exc:
            click.echo(f"Error: {exc}", err=True)
            sys.exit(exc.exit_code)
        except OSError as exc:
            click.echo(f"Error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "),
                       err=True)
            sys.exit(1)
        except MemoryError:
            click.echo("Error: out of memory", err=True)
            sys.exit(1)


def _emit(data: Any, as_json: bool, text: str) -> None:
    click.echo(json.dumps(data, indent=2) if as_json else text)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="sprint-map")
def main() -> None:
    """sprint-map: a persistent, lifelong visual place-recognition map (SPRINT).

    \b
    Quick start:
      sprint-map init city.map --dim 256
      sprint-map ingest city.map monday.npy --name monday
      sprint-map info city.map
    """
    # OpenCV logs its own warning lines for a corrupt image; the one-line error says it all.
    # OpenCV is imported only by the commands that decode images: it reads the variable then.
    cv2 = sys.modules.get("cv2")
    if cv2 is None:
        os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    else:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--dim", type=int, help="Descriptor dimension (for precomputed .npy descriptors).")
@click.option("--descriptor", type=click.Choice(["precomputed", "hog", "patchnorm", "onnx"]),
              default=None, help="Descriptor kind; hog/patchnorm/onnx set the dimension "
              "themselves.")
@click.option("--model", type=click.Path(dir_okay=False), help="onnx: the ONNX model file "
              "(one descriptor per image; pip install \"sprint-map[onnx]\"). Its SHA-256 is "
              "stored: a different file there later is refused.")
@click.option("--model-card", type=click.Path(dir_okay=False), help="onnx: JSON card "
              "{input_size, channels, mean, std, normalize} (default: MODEL's .card.json "
              "beside it, else its fixed input size, RGB, ImageNet mean/std, l2).")
@click.option("--config", "config_json", type=click.Path(exists=True, dir_okay=False),
              help="JSON file of further MapConfig fields, e.g. {\"index_type\": \"flat\", "
              "\"hmm\": {\"k\": 20}} (docs/hmm.md, \"HMMConfig\").")
@click.option("--admission", type=click.Choice(["all", "novel"]), default=None,
              help="Which frames of an ingested drive the map stores: all (default) or only "
              "those it does not already hold (novel: a lifelong map that stays bounded).")
def init(map_path: str, dim: int | None, descriptor: str | None, model: str | None,
         model_card: str | None, config_json: str | None, admission: str | None) -> None:
    """Create an empty map in MAP (which must be absent or empty).

    \b
    Examples:
      sprint-map init city.map --descriptor hog      # images and video, the paper's HoG
      sprint-map init city.map --dim 256             # precomputed .npy descriptors
      sprint-map init city.map --descriptor onnx --model eigenplaces.onnx
      sprint-map init fleet.map --dim 256 --admission novel
    """
    options = _read_json_config(config_json)
    if admission is not None:
        options["admission"] = {**options.get("admission", {}), "mode": admission}
    kind = descriptor or options.pop("descriptor", None) or (
        "onnx" if model is not None else "precomputed" if dim is not None else "hog")
    if (model is not None or model_card is not None) != (kind == "onnx"):
        raise InputError("--descriptor onnx needs --model FILE" if kind == "onnx"
                         else "--model and --model-card are for --descriptor onnx")
    if kind == "onnx":
        from sprint_map.frontend.onnx_model import onnx_params

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


def _read_json_config(path: str | None) -> dict[str, Any]:
    """The options in the JSON file ``path`` (``{}`` without one); an unreadable file (or one
    that is not UTF-8 JSON) is an InputError."""
    if not path:
        return {}
    try:
        with open(path, encoding="utf-8") as fh:
            options = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read config {path}: {exc}") from exc
    if not isinstance(options, dict):
        raise InputError(f"config {path} must hold a JSON object")
    return options


def _hmm_overrides(k: int | None, window: str | None, pairs: tuple[str, ...]) -> dict[str, Any]:
    """Per-call model overrides from --k, --window and repeated --hmm key=value."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise InputError(f"--hmm expects key=value, got {pair!r}")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    if k is not None:
        out["k"] = k
    if window is not None:
        try:
            out["window"] = [float(x) for x in window.split(",")]
        except ValueError as exc:
            raise InputError(f"--window expects comma-separated numbers: {window}") from exc
    return out


def _key_values(pairs: tuple[str, ...], option: str) -> dict[str, Any]:
    """``KEY=VALUE`` pairs as a dict, each value parsed as JSON (else kept as a string)."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise InputError(f"{option} expects KEY=VALUE, got {pair!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _trace_option(f: Any) -> Any:
    return click.option("--trace", type=click.Path(dir_okay=False), metavar="OUT",
                        help="Record per frame the hits, active components and top belief "
                             "states to OUT (.npz) for `sprint-map view --trace OUT`.")(f)


def _bag_options(f: Any) -> Any:
    f = click.option("--every-m", type=float, metavar="M", help="ROS bags: keep a frame each "
                     "M metres travelled (by GNSS), after --stride.")(f)
    f = click.option("--gnss-topic", metavar="TOPIC", help="ROS bags: the NavSatFix topic of "
                     "the positions (default: the only one, if any).")(f)
    f = click.option("--image-topic", metavar="TOPIC", help="ROS bags: the Image or "
                     "CompressedImage topic (default: the only one).")(f)
    return f


def _model_options(f: Any) -> Any:
    f = click.option("--hmm", "hmm_pairs", multiple=True, metavar="KEY=VALUE",
                     help="Override any HMM parameter for this call (repeatable).")(f)
    f = click.option("--window", help="Forward transition window, e.g. 0.2,0.4,0.3,0.1.")(f)
    f = click.option("--k", type=int, help="Neighbours retrieved per frame.")(f)
    f = click.option("--stride", type=click.IntRange(min=1), default=1, show_default=True,
                     help="Keep every STRIDE-th frame (video and image folders).")(f)
    f = click.option("--quiet", "-q", is_flag=True,
                     help="No progress bar (none either when stderr is not a terminal).")(f)
    return f


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
@_trace_option
@_bag_options
@_model_options
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
    drive's positions: --positions, else a bag's GNSS, else its folder's positions.csv.

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
    overrides = _hmm_overrides(k, window, hmm_pairs)
    done: list[dict[str, Any]] = []

    def report(results: list[IngestResult]) -> None:
        for result in results:
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
            src = m.open_source(source, stride=stride, thumbnails=thumbnails, bag=bag,
                                progress=stack.enter_context(progress_display(label, quiet)))
            opened.append((src, drive_positions(src, source, positions, stride)))
        names = (drive_names([Path(s) for s in sources], [src.name for src, _ in opened])
                 if opened and name is None else [name] * len(opened))
        # Streamed: each batch is described, localised and written (uncommitted) in turn.
        # An empty --name is refused by the name rules, not replaced by the source's name.
        placed = [(src, m.metric_positions(table)) for src, table in opened]
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
    for warning in m.warnings:
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
@_trace_option
@_bag_options
@_model_options
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
    if thumbnails and not smooth:
        raise InputError("--thumbnails verifies smoothed decisions: add --smooth")
    if lag:
        from sprint_map.localize.lagged import validate_lag

        validate_lag(lag)
    if lag and (smooth or trace):
        raise InputError("--lag answers frames as the drive goes: it cannot be combined with "
                         "--smooth (the whole drive) or --trace")
    if lag and positions:
        raise InputError("--lag does not weigh GNSS fixes: drop --positions, or --lag")
    overrides = _hmm_overrides(k, window, hmm_pairs)
    with SprintMap.open(map_path, readonly=True) as m, contextlib.ExitStack() as outputs, \
            progress_display("localising", quiet) as progress:
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
    matched = sum(d.is_match for d in decisions)
    _emit(data, as_json, "\n".join(
        [f"{d.frame:>6}  " + (f"seq {d.seq_id} image {d.image_id}" if d.is_match else "no match")
         + f"  p={d.prob:.3f} novel={d.novel_prob:.3f}" for d in decisions]
        + [f"{matched}/{len(decisions)} frames matched; per frame: retrieval "
           f"{t['retrieval_ms_per_frame']} ms, HMM {t['hmm_ms_per_frame']} ms"]))


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
def info(map_path: str, as_json: bool) -> None:
    """Summarise MAP: counts, dimension, index and disk use.

    \b
    Example:
      sprint-map info city.map --json
    """
    with SprintMap.open(map_path, readonly=True) as m:
        data = m.info()
    text = "\n".join(
        f"{key}: {data[key]}"
        for key in ("path", "schema_version", "sequences", "vertices", "edges", "components",
                    "dim", "descriptor", "admission", "index", "disk_bytes")
    )
    _emit(data, as_json, text)


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
def sequences(map_path: str, as_json: bool) -> None:
    """List the sequences of MAP with their component.

    \b
    Example:
      sprint-map sequences city.map --json
    """
    with SprintMap.open(map_path, readonly=True) as m:
        rows = [
            {"seq_id": s.seq_id, "name": s.name, "frames": s.length,
             "component": m.component_of(s.seq_id)}
            for s in m.sequences()
        ]
    text = "\n".join(f"{r['seq_id']:>6}  {r['frames']:>7} frames  component {r['component']:>6}  "
                     f"{r['name']}" for r in rows)
    _emit(rows, as_json, text or "(no sequences)")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
def components(map_path: str, as_json: bool) -> None:
    """List the connected components of MAP (sequences joined by edges).

    \b
    Example:
      sprint-map components city.map
    """
    with SprintMap.open(map_path, readonly=True) as m:
        rows = [{"component": c.component, "sequences": c.sequences, "vertices": c.vertices}
                for c in m.components()]
    text = "\n".join(f"{r['component']:>6}  {r['vertices']:>8} vertices  sequences "
                     f"{r['sequences']}" for r in rows)
    _emit(rows, as_json, text or "(no components)")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--repair", is_flag=True, help="Rebuild what is derivable (shard tails, index, "
              "union-find, lookups, temp files), then check; takes the writer lock.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def check(map_path: str, repair: bool, as_json: bool) -> None:
    """Verify every invariant of MAP; exit 1 and list the violations if any.

    With --repair, first fix what the map's own data can rebuild and report what it cannot;
    exit 0 when the map is healthy afterwards.

    \b
    Examples:
      sprint-map check city.map
      sprint-map check city.map --repair
    """
    if repair:
        fixed = SprintMap.repair(map_path)
        report, data = fixed.after, fixed.to_dict()
        lines = [f"repaired: {r}" for r in fixed.repaired] + [f"skipped: {s}" for s in fixed.skipped]
    else:
        with SprintMap.open(map_path, readonly=True) as m:
            report = m.check()
        data, lines = report.to_dict(), []
    lines += [f"violation: {v}" for v in report.violations] + [f"note: {n}" for n in report.notes]
    done = f" ({len(fixed.repaired)} repaired)" if repair else ""
    left = f" left after repair ({', '.join(sorted(report.areas))})" if repair else ""
    lines.append(f"ok{done}" if report.ok else f"{len(report.violations)} violation(s){left}")
    _emit(data, as_json, "\n".join(lines))
    sys.exit(0 if report.ok else 1)


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.argument("seqs", metavar="SEQ...", nargs=-1, required=True)
@click.option("--by-name", is_flag=True, help="Read every SEQ as a name, even all digits.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def remove(map_path: str, seqs: tuple[str, ...], by_name: bool, as_json: bool) -> None:
    """Forget the given sequences of MAP (ids or names) in one atomic commit.

    Their edges go and components split where nothing else joins them; their space is
    reclaimed by `sprint-map compact`. A SEQ of ASCII digits (0-9) is a sequence id, anything
    else a name.

    \b
    Examples:
      sprint-map remove city.map 0 3            # sequences 0 and 3
      sprint-map remove city.map monday-2019    # by name
      sprint-map remove city.map 2024 --by-name # a sequence named "2024"
    """
    refs = [parse_seq_ref(s, by_name) for s in seqs]
    with SprintMap.open(map_path) as m:
        data = m.remove_sequences(refs).to_dict()
    names = ", ".join(f"{r['seq_id']} ({r['name']})" for r in data["removed"])
    _emit(data, as_json, f"removed {names}: {data['vertices_removed']} vertices, "
                         f"{data['edges_removed']} edges; components {data['components_affected']}"
                         f" -> {data['components_after']}; reclaim the space with compact")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--seq", help="Only edges touching this sequence (id or name), either end.")
@click.option("--added-by", help="Only edges this drive (id or name) added: what unmerge "
              "revokes.")
@click.option("--by-name", is_flag=True, help="Read --seq and --added-by as names, even digits.")
@click.option("--json", "as_json", is_flag=True, help="Print as JSON: a list of {src_seq, "
              "src_image, dst_seq, dst_image, prob, added_by}.")
def edges(map_path: str, seq: str | None, added_by: str | None, by_name: bool,
          as_json: bool) -> None:
    """List the edges of MAP with their provenance: the drive whose merge added each one.

    \b
    Examples:
      sprint-map edges city.map --seq monday        # edges from or to monday
      sprint-map edges city.map --added-by 3 --json # what `unmerge city.map 3` would revoke
    """
    with SprintMap.open(map_path, readonly=True) as m:
        found = m.edges(None if seq is None else parse_seq_ref(seq, by_name),
                        added_by=None if added_by is None else parse_seq_ref(added_by, by_name))
        names = {s.seq_id: s.name for s in m.sequences()} if not as_json else {}
    text = "\n".join(
        f"{f'{e.src_seq}:{e.src_image}':>11} -> {f'{e.dst_seq}:{e.dst_image}':<11} "
        f"p={e.prob:.3f}  added by "
        + ("-" if e.added_by is None else f"{e.added_by} ({names.get(e.added_by, 'removed')})")
        + ("" if e.frame is None else f", frame {e.frame}") for e in found)
    _emit([e.to_dict() for e in found], as_json, text or "(no edges)")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--graphml", type=click.Path(dir_okay=False), help="Write the graph as GraphML "
              "(networkx, Gephi): edges with probability and provenance.")
@click.option("--level", type=click.Choice(["vertex", "sequence"]), default=None,
              help="GraphML nodes: one per frame or one per drive (default: vertex up to "
                   "100,000 vertices, sequence beyond).")
@click.option("--csv", "csv_dir", type=click.Path(file_okay=False),
              help="Write sequences.csv, vertices.csv (with positions) and edges.csv here.")
@click.option("--geojson", type=click.Path(dir_okay=False),
              help="Write drives as lines and edges as segments on their positions (QGIS).")
@click.option("--json", "as_json", is_flag=True, help="Print what was written as JSON.")
def export(map_path: str, graphml: str | None, level: str | None, csv_dir: str | None,
           geojson: str | None, as_json: bool) -> None:
    """Export MAP for other tools: GraphML, CSV tables, GeoJSON (streamed, written atomically).

    \b
    Examples:
      sprint-map export city.map --graphml city.graphml
      sprint-map export city.map --graphml drives.graphml --level sequence --csv city-csv/
      sprint-map export city.map --geojson city.geojson --json
    """
    if not (graphml or csv_dir or geojson):
        raise InputError("nothing to export: give --graphml FILE, --csv DIR or --geojson FILE")
    if level and not graphml:
        raise InputError("--level is the level of the GraphML export: give --graphml FILE")
    with SprintMap.open(map_path, readonly=True) as m:
        reports = ([m.export_graphml(graphml, level)] if graphml else []) + (
            [m.export_csv(csv_dir)] if csv_dir else []) + (
            [m.export_geojson(geojson)] if geojson else [])
    _emit([r.to_dict() for r in reports], as_json, "\n".join(
        f"wrote {r.path}: {r.format}{f' ({r.level} level)' if r.level else ''}, {r.nodes} "
        f"{'drives' if r.format == 'geojson' else 'nodes' if r.format == 'graphml' else 'vertices'}"
        f", {r.edges} edges, {r.bytes} bytes" for r in reports))


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.argument("seq", metavar="SEQ")
@click.option("--by-name", is_flag=True, help="Read SEQ as a name, even all digits.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON: {seq_id, "
              "edges_removed, components}.")
def unmerge(map_path: str, seq: str, by_name: bool, as_json: bool) -> None:
    """Undo the merge of drive SEQ (id or name): revoke every edge it added, atomically.

    Components split where nothing else joins them; the drive stays in the map, as do the
    edges later drives added to it. `components` lists the components the affected ones
    form now. A drive that added no edge is a no-op.

    \b
    Examples:
      sprint-map edges city.map --added-by tuesday   # preview
      sprint-map unmerge city.map tuesday --json
    """
    with SprintMap.open(map_path) as m:
        data = m.unmerge(parse_seq_ref(seq, by_name)).to_dict()
    _emit(data, as_json, f"unmerged sequence {data['seq_id']}: {data['edges_removed']} edges "
                         f"revoked; components now {data['components']}")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def compact(map_path: str, as_json: bool) -> None:
    """Reclaim the space of removed sequences: rewrite shards, index and LMDB compactly.

    The new copy is built beside the old one and selected atomically: a kill at any point
    leaves the old map or the new one. Vertex ids are renumbered; sequence ids stay.

    \b
    Example:
      sprint-map remove city.map 0 1 && sprint-map compact city.map
    """
    with SprintMap.open(map_path) as m:
        data = m.compact().to_dict()
    kept = "" if data["old_generation_removed"] else (
        "; the old copy is kept while a reader has it open (removed by the next writer)")
    _emit(data, as_json, f"compacted into {data['generation']}: {data['vertices_before']} -> "
                         f"{data['vertices_after']} vertices, {data['bytes_before']} -> "
                         f"{data['bytes_after']} bytes on disk{kept}")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--rebuild", "action", flag_value="rebuild", help="Rebuild the index from the "
              "shards (the approximate index keeps its kind, retrained on a fresh sample).")
@click.option("--train", "action", flag_value="train", help="Retrain PCA and the quantizer on "
              "a fresh sample of the map, then re-encode every vertex.")
@click.option("--learn", "action", flag_value="learn", help="Learn a descriptor projection "
              "from the map's merged edges; adopted (index rebuilt with it) only if it "
              "retrieves held-back edges better. Prints {pairs, dim_in, dim_out, adopted, "
              "heldout_recall_before, heldout_recall_after}.")
@click.option("--no-learn", "action", flag_value="unlearn", help="Drop the learned "
              "projection: search the plain descriptor again (index rebuilt).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def index(map_path: str, action: str | None, as_json: bool) -> None:
    """Rebuild or retrain the retrieval index of MAP (its kind is the map's index_type).

    Readers keep searching the old index until the new one is published atomically; a kill
    leaves one or the other. Without an option, show the index.

    \b
    Examples:
      sprint-map index city.map --train      # retrain PCA + IVF on today's map
      sprint-map index city.map --rebuild
      sprint-map index city.map --learn --json   # learn the descriptor from the merges
      sprint-map index city.map --no-learn
      sprint-map index city.map --json
    """
    if action == "learn":
        with SprintMap.open(map_path) as m:
            report = m.learn()
        _emit(report, as_json, f"learned from {report['pairs']} merged pairs "
                               f"({report['dim_in']} -> {report['dim_out']} dims): "
                               f"{'adopted' if report['adopted'] else 'not adopted'}; held-back "
                               f"recall@1 {report['heldout_recall_before']:.3f} -> "
                               f"{report['heldout_recall_after']:.3f}")
        return
    if action == "unlearn":
        with SprintMap.open(map_path) as m:
            dropped = m.unlearn()
        _emit({"dropped": dropped}, as_json, "dropped the learned projection" if dropped
              else "the map had no learned projection")
        return
    with SprintMap.open(map_path, readonly=action is None) as m:
        done = m.rebuild_index(train=action == "train") if action else []
        data = {"done": done, "index": m.info()["index"]}
    _emit(data, as_json, "\n".join(done + [f"index: {data['index']['type']}"]))


def _gnss_option(f: Any) -> Any:
    return click.option(
        "--gnss-sigma", type=float, default=0.0, show_default=True, metavar="M",
        help="Also run GNSS-aided: fixes simulated from the ground-truth positions with M "
        "metres of drift per axis, dropouts and multipath jumps (docs/frontend.md), reported "
        "beside the image-only figures (results.json \"gnss\"); 0: off.")(f)


def _log(quiet: bool) -> Any:
    return (lambda _msg: None) if quiet else (lambda msg: click.echo(msg, err=True))


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
@_gnss_option
@click.option("--learn-every", type=click.IntRange(min=1), default=None, metavar="EDGES",
              help="lifelong: also run it with the maps learning their descriptor from their "
              "merges after every EDGES new edges (learn_every), reported beside the run "
              "without learning (in OUT/learned).")
@_model_options
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
    if layout == "vpr":
        _eval_vpr(dataset, out_dir, descriptor, (model, model_card), radius, map_pairs, k,
                  window, hmm_pairs, quiet)
        return
    if model is not None or model_card is not None:
        raise InputError("--model is for --layout vpr (a traversal data set's map: init "
                         "--descriptor onnx, then ingest)")
    from sprint_map.evaluation.report import markdown_table, write_report
    from sprint_map.evaluation.runner import EvalOptions, config_for, run_evaluation
    from sprint_map.frontend.dataset import Dataset

    gt: dict[str, Any] = {}
    for key, value in (("alignment", alignment), ("tolerance_frames", tolerance),
                       ("radius_m", radius)):
        if value is not None:
            gt[key] = value
    data = Dataset.open(dataset, gt or None)
    config = config_for(data, descriptor)
    if map_pairs:
        config = config.replace(**_key_values(map_pairs, "--map-config"))
    overrides = _hmm_overrides(k, window, hmm_pairs)
    hmm = dataclass_dict.replace(config.hmm, **overrides) if overrides else None
    options = EvalOptions(protocol=protocol, database=database, query=query,
                          both_directions=both_directions, stride=stride, gnss_sigma=gnss_sigma)
    out = Path(out_dir or f"eval-{data.path.resolve().name}")
    runs = [(out, config, "")]
    if learn_every:
        runs.append((out / "learned", config.replace(learn_every=learn_every),
                     f"\nwith learning (learn_every={learn_every}):"))
    for where, cfg, title in runs:
        results = run_evaluation(data, where / "maps", cfg, options, hmm, log=_log(quiet))
        paths = write_report(results, where)
        click.echo(f"{title}\n{markdown_table(results)}" if title else markdown_table(results))
        click.echo("\n".join(f"{kind}: {path}" for kind, path in paths.items()))


def _eval_vpr(dataset: str, out_dir: str | None, descriptor: str,
              model: tuple[str | None, str | None], radius: float | None,
              map_pairs: tuple[str, ...], k: int | None, window: str | None,
              hmm_pairs: tuple[str, ...], quiet: bool) -> None:
    """``eval --layout vpr``: recall@1/5/10/20 of k-NN and SPRINT into results.json."""
    from sprint_map.evaluation.vpr import markdown_recall, run_vpr_evaluation
    from sprint_map.frontend.vpr import VprDataset

    if descriptor == "precomputed":
        raise InputError("--layout vpr describes the images: --descriptor auto, hog or patchnorm")
    data = VprDataset.open(dataset)
    if model[0] is not None:
        from sprint_map.frontend.onnx_model import onnx_params

        params = onnx_params(model[0], model[1])
        config = MapConfig(dim=params["dim"], descriptor="onnx", descriptor_params=params)
    elif model[1] is not None:
        raise InputError("--model-card needs --model FILE")
    else:
        config = MapConfig.for_descriptor("hog" if descriptor == "auto" else descriptor)
    if map_pairs:
        config = dataclass_dict.replace(config, **_key_values(map_pairs, "--map-config"))
    overrides = _hmm_overrides(k, window, hmm_pairs)
    hmm = dataclass_dict.replace(config.hmm, **overrides) if overrides else None
    out = Path(out_dir or f"eval-{data.path.resolve().name}")
    results = run_vpr_evaluation(data, out, config, hmm, 25.0 if radius is None else radius,
                                 log=_log(quiet))
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
@_gnss_option
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

    results, paths = run_demo(Path(out_dir), which, log=_log(quiet), gnss_sigma=gnss_sigma)
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

    options = _read_json_config(config_json)
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
