"""What the ``sprint-map`` commands share: the command group, JSON or text output, options.

The group turns a :class:`SprintMapError` into one ``Error: ...`` line on stderr and the
error's own exit code (:class:`Group`); the commands live in :mod:`sprint_map.cli.main` (making
and localising drives), :mod:`sprint_map.cli.maintenance` (reading and keeping a map) and
:mod:`sprint_map.cli.runs` (evaluation, the demo, the service and the viewer).
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

import click

from sprint_map.errors import InputError, SprintMapError

__all__ = ["Group", "bag_options", "emit", "gnss_option", "hmm_overrides", "key_values",
           "log_to_stderr", "main", "model_options", "read_json_config", "trace_option"]


class Group(click.Group):
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


def emit(data: Any, as_json: bool, text: str) -> None:
    click.echo(json.dumps(data, indent=2) if as_json else text)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
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


def read_json_config(path: str | None) -> dict[str, Any]:
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


def hmm_overrides(k: int | None, window: str | None, pairs: tuple[str, ...]) -> dict[str, Any]:
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


def key_values(pairs: tuple[str, ...], option: str) -> dict[str, Any]:
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


def trace_option(f: Any) -> Any:
    return click.option("--trace", type=click.Path(dir_okay=False), metavar="OUT",
                        help="Record per frame the hits, active components and top belief "
                             "states to OUT (.npz) for `sprint-map view --trace OUT`.")(f)


def bag_options(f: Any) -> Any:
    f = click.option("--every-m", type=float, metavar="M", help="ROS bags: keep a frame each "
                     "M metres travelled (by GNSS), after --stride.")(f)
    f = click.option("--gnss-topic", metavar="TOPIC", help="ROS bags: the NavSatFix topic of "
                     "the positions (default: the only one, if any).")(f)
    f = click.option("--image-topic", metavar="TOPIC", help="ROS bags: the Image or "
                     "CompressedImage topic (default: the only one).")(f)
    return f


def model_options(f: Any) -> Any:
    f = click.option("--hmm", "hmm_pairs", multiple=True, metavar="KEY=VALUE",
                     help="Override any HMM parameter for this call (repeatable).")(f)
    f = click.option("--window", help="Forward transition window, e.g. 0.2,0.4,0.3,0.1.")(f)
    f = click.option("--k", type=int, help="Neighbours retrieved per frame.")(f)
    f = click.option("--stride", type=click.IntRange(min=1), default=1, show_default=True,
                     help="Keep every STRIDE-th frame (video and image folders).")(f)
    f = click.option("--quiet", "-q", is_flag=True,
                     help="No progress bar (none either when stderr is not a terminal).")(f)
    return f


def gnss_option(f: Any) -> Any:
    return click.option(
        "--gnss-sigma", type=float, default=0.0, show_default=True, metavar="M",
        help="Also run GNSS-aided: fixes simulated from the ground-truth positions with M "
        "metres of drift per axis, dropouts and multipath jumps (docs/frontend.md), reported "
        "beside the image-only figures (results.json \"gnss\"); 0: off.")(f)


def log_to_stderr(quiet: bool) -> Any:
    return (lambda _msg: None) if quiet else (lambda msg: click.echo(msg, err=True))


