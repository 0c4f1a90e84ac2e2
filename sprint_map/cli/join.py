"""``sprint-map join``: drives of another map brought into this one (:meth:`SprintMap.join`)."""

from __future__ import annotations

from typing import Any

import click

from sprint_map.cli.common import emit, hmm_overrides, main
from sprint_map.fleet.runtime import RAY_HELP
from sprint_map.map import SprintMap
from sprint_map.util import dataclass_dict

__all__ = ["join"]


@main.command()
@click.argument("target", metavar="TARGET", type=click.Path())
@click.argument("source", metavar="SOURCE", type=click.Path())
@click.option("--drives", "drive_names", multiple=True, metavar="NAME",
              help="Only these drives of SOURCE (repeat the option; default: all).")
@click.option("--prefix", default="", help="Prepended to the name of every imported drive "
              "(resolves name clashes with TARGET's drives).")
@click.option("--no-merge", is_flag=True, help="Only copy: do not localise the imported drives "
              "against TARGET (no cross-map edges).")
@click.option("--require-connected", is_flag=True, help="Refuse (changing nothing) a join that "
              "would leave an imported drive without a path to TARGET's drives.")
@click.option("--ray", "ray_spec", metavar="local|auto|ADDRESS", help=RAY_HELP + " (the "
              "imported drives are localised in parallel, with the serial result).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON: per drive "
              "its cross-map edges and whether it is connected, and the totals.")
@click.option("--k", type=int, default=None, help="Override the HMM's k for the localisation.")
@click.option("--hmm", "hmm_pairs", multiple=True, metavar="FIELD=VALUE",
              help="Override a field of the HMM config for the localisation (repeatable).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def join(target: str, source: str, drive_names: tuple[str, ...], prefix: str, no_merge: bool,
         require_connected: bool, ray_spec: str | None, as_json: bool, k: int | None,
         hmm_pairs: tuple[str, ...], quiet: bool) -> None:
    """Bring the drives of map SOURCE into map TARGET, then merge them as ingest would.

    Each drive comes with everything it carries (descriptors, thumbnails, positions and fixes,
    sightings, per-drive statistics, its edges to the other drives with their provenance);
    then it is localised against what TARGET held before the join and its confident decisions
    become cross-map edges (the merge rule, verification and GNSS gates of ingest), all in one
    atomic commit. The maps must hold the same descriptor (kind, dimension, model, parameters)
    in the same coordinate frame. SOURCE is only read (a writer is kept out of it meanwhile);
    a drive TARGET already holds (same descriptors) is not copied again, so a second join of
    the same SOURCE changes nothing. `unmerge TARGET DRIVE` revokes what the join's merge of
    DRIVE added; `remove` forgets an imported drive like any other.

    \b
    Examples:
      sprint-map join city.map van7.map --json
      sprint-map join city.map van7.map --prefix van7- --require-connected
      sprint-map join city.map van7.map --drives monday --drives tuesday
      sprint-map join city.map site.map --no-merge
      sprint-map join city.map van7.map --ray auto
    """
    from sprint_map.cli.progress import progress_display  # loaded when run, not at start-up

    overrides = hmm_overrides(k, None, hmm_pairs)
    if ray_spec is not None:
        from sprint_map.fleet.join import farm_localise_join
        from sprint_map.fleet.runtime import connect

        connect(ray_spec)
    with SprintMap.open(target) as m, progress_display("joining", quiet) as bar:
        hmm = dataclass_dict.replace(m.config.hmm, **overrides) if overrides else None
        done = [0]

        def progress(rows: int) -> None:
            done[0] += rows
            if bar is not None:
                bar(done[0], None)

        localise_many = (farm_localise_join(str(m.path), source, hmm)
                         if ray_spec is not None else None)
        result = m.join(source, drives=list(drive_names) or None, prefix=prefix,
                        merge=not no_merge, require_connected=require_connected, hmm=hmm,
                        localise_many=localise_many, progress=progress)
    for warning in m.warnings:
        click.echo(f"Warning: {warning}", err=True)
    data = result.to_dict()
    emit(data, as_json, "\n".join([_drive_line(d) for d in data["drives"]] + [
        f"joined {data['imported']} drive(s) ({data['vertices_copied']} vertices, "
        f"{data['edges_copied']} edges copied, {data['cross_edges']} cross-map edges); "
        f"{data['already_present']} already in the map"]))


def _drive_line(d: dict[str, Any]) -> str:
    if d["already_present"]:
        return f"{d['source_name']}: already in the map as sequence {d['seq_id']} ({d['name']})"
    link = "connected" if d["connected"] else "NOT connected"
    return (f"{d['source_name']} -> sequence {d['seq_id']} ({d['name']}): {d['frames']} frames, "
            f"{d['cross_edges']} cross-map edges, {link}, component {d['component']}")
