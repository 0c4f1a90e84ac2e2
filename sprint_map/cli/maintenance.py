"""``sprint-map`` commands that read and keep a map: ``info``, ``sequences``, ``components``,
``check``, ``remove``, ``edges``, ``export``, ``unmerge``, ``compact`` and ``index``
(registered on the group of :mod:`sprint_map.cli.common`)."""

from __future__ import annotations

import sys

import click

from sprint_map.cli.common import (
    emit,
    main,
)
from sprint_map.errors import InputError
from sprint_map.map import SprintMap
from sprint_map.util.validation import parse_seq_ref

__all__ = ["check", "compact", "components", "edges", "export", "index", "info", "remove",
           "sequences", "unmerge"]


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
    emit(data, as_json, text)


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
    emit(rows, as_json, text or "(no sequences)")


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
    emit(rows, as_json, text or "(no components)")


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
    emit(data, as_json, "\n".join(lines))
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
    emit(data, as_json, f"removed {names}: {data['vertices_removed']} vertices, "
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
    emit([e.to_dict() for e in found], as_json, text or "(no edges)")


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
    emit([r.to_dict() for r in reports], as_json, "\n".join(
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
    emit(data, as_json, f"unmerged sequence {data['seq_id']}: {data['edges_removed']} edges "
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
    emit(data, as_json, f"compacted into {data['generation']}: {data['vertices_before']} -> "
                         f"{data['vertices_after']} vertices, {data['bytes_before']} -> "
                         f"{data['bytes_after']} bytes on disk{kept}")


@main.command()
@click.argument("map_path", metavar="MAP", type=click.Path())
@click.option("--per-place", type=click.IntRange(min=1), default=1, show_default=True,
              metavar="K", help="Views kept per place and appearance: a view goes when K kept "
              "views of its place (older drives') look like it.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON: "
              "{vertices_before, vertices_after, sequences_before, sequences_after, stitches, "
              "sightings, bytes_before, bytes_after, seconds}.")
def summarize(map_path: str, per_place: int, as_json: bool) -> None:
    """Drop the views the map repeats: what `init --admission novel` would not have stored.

    A view of a place goes when it was merged to an older drive's view and K kept views of
    that place look like it; each place keeps its first drive and every appearance no kept
    view has. A dropped view's edges move to the view standing for it, which counts a
    sighting; kept stretches are stitched to the places between them. The map is rewritten
    like `compact` (vertex ids renumbered, sequence ids and names kept; a drive with nothing
    left goes) and selected atomically: a kill at any point leaves the map as before or after.

    \b
    Example:
      sprint-map summarize city.map --json
    """
    with SprintMap.open(map_path) as m:
        data = m.summarize(per_place)
    emit(data, as_json, f"summarised: {data['vertices_before']} -> {data['vertices_after']} "
                         f"vertices, {data['sequences_before']} -> {data['sequences_after']} "
                         f"sequences, {data['bytes_before']} -> {data['bytes_after']} bytes")


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
        emit(report, as_json, f"learned from {report['pairs']} merged pairs "
                               f"({report['dim_in']} -> {report['dim_out']} dims): "
                               f"{'adopted' if report['adopted'] else 'not adopted'}; held-back "
                               f"recall@1 {report['heldout_recall_before']:.3f} -> "
                               f"{report['heldout_recall_after']:.3f}")
        return
    if action == "unlearn":
        with SprintMap.open(map_path) as m:
            dropped = m.unlearn()
        emit({"dropped": dropped}, as_json, "dropped the learned projection" if dropped
              else "the map had no learned projection")
        return
    with SprintMap.open(map_path, readonly=action is None) as m:
        done = m.rebuild_index(train=action == "train") if action else []
        data = {"done": done, "index": m.info()["index"]}
    emit(data, as_json, "\n".join(done + [f"index: {data['index']['type']}"]))
