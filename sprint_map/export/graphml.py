"""GraphML export through networkx: the sequence graph whole, the vertex graph streamed.

**Sequence level** (:func:`sequence_graph`): one node per live drive (``seq_id``, ``name``,
``frames``, ``component``, ``source``, ``created``, ``positions``) and one directed edge per
ordered pair of drives joined by at least one vertex edge (``edges``: how many, ``prob_mean``,
``prob_min``, ``prob_max``, ``added_by``: the drives whose merges wrote them, space-separated).
It is small (O(sequences + drive pairs)) and written by ``networkx.write_graphml``.

**Vertex level** (:func:`write_vertex_graphml`): one node per live frame, id ``"seq:image"``
(stable across ``compact``, unlike vertex ids), with ``seq_id``, ``image_id``, ``component`` and,
when known, ``x``, ``y``, ``heading``, ``timestamp``; one directed edge per map edge with
``prob``, ``time`` and, when known, ``added_by`` and ``frame`` (the provenance of ``sprint-map
edges``). ``networkx.write_graphml`` builds the whole document in memory, so it is streamed
instead, still with networkx's own writer: the stdlib's ``XMLGenerator`` writes the document's
frame (declaration, ``<graphml>``, ``<graph>`` and their end tags), one
``networkx.readwrite.graphml.GraphMLWriter`` declares the keys (every attribute, in a fixed
order, so key ids are the same in every writer), and each chunk of :data:`CHUNK` nodes or edges
is a small ``networkx.DiGraph`` turned into ``<node>``/``<edge>`` elements by a fresh
``GraphMLWriter`` with the same keys, then serialised. Memory: one chunk, the sequence records
and one drive's positions; never the graph. Read back by ``networkx.read_graphml`` it is the
graph :func:`vertex_graph` builds in memory (the tests compare them).
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Iterator
from typing import IO, Any, cast
from xml.etree.ElementTree import tostring
from xml.sax.saxutils import XMLGenerator
from xml.sax.xmlreader import AttributesImpl

import networkx as nx
from networkx.readwrite.graphml import GraphMLWriter

from sprint_map.storage.records import EdgeInfo, SequenceRecord
from sprint_map.storage.scan import MapScan

#: Nodes or edges per chunk of the streamed vertex graph.
CHUNK = 4096
#: The vertex graph's attributes and their types, in key-declaration order.
GRAPH_KEYS: dict[str, type] = {"level": str, "sequences": int, "vertices": int, "edges": int}
NODE_KEYS: dict[str, type] = {"seq_id": int, "image_id": int, "component": int, "x": float,
                              "y": float, "heading": float, "timestamp": float,
                              "sigma_m": float}
EDGE_KEYS: dict[str, type] = {"prob": float, "added_by": int, "frame": int, "time": float}
_POSITION_KEYS = ("x", "y", "heading", "timestamp", "sigma_m")


#: Characters XML 1.0 cannot hold (C0 controls but tab and newlines, lone surrogates, U+FFFE/F).
_NOT_XML = re.compile("[^\t\n\r\u0020-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def xml_text(text: str) -> str:
    """``text`` with every character XML cannot hold replaced by U+FFFD (a drive's ``source``
    is free text). O(len)."""
    return _NOT_XML.sub("\ufffd", text)


def node_id(seq_id: int, image_id: int) -> str:
    """The GraphML node id of a frame: ``"seq:image"``."""
    return f"{seq_id}:{image_id}"


def _vertex_nodes(scan: MapScan) -> Iterator[tuple[str, dict[str, Any]]]:
    """Every live frame with its attributes (unknown positions left out), in vertex order."""
    for seq, pos in scan.positions():
        component = scan.component.get(seq.seq_id, seq.seq_id)
        rows = pos.tolist() if pos is not None else None
        for image in range(seq.length):
            data: dict[str, Any] = {"seq_id": seq.seq_id, "image_id": image,
                                    "component": component}
            if rows is not None:
                for name, value in zip(_POSITION_KEYS, rows[image], strict=True):
                    if not math.isnan(value):
                        data[name] = float(value)
            yield node_id(seq.seq_id, image), data


def edge_data(edge: EdgeInfo) -> dict[str, Any]:
    """An edge's GraphML attributes: provenance fields that are unknown are left out."""
    data: dict[str, Any] = {"prob": float(edge.prob), "time": float(edge.time)}
    if edge.added_by is not None:
        data["added_by"] = int(edge.added_by)
    if edge.frame is not None:
        data["frame"] = int(edge.frame)
    return data


def _vertex_edges(scan: MapScan) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for _, _, e in scan.edges():
        yield node_id(e.src_seq, e.src_image), node_id(e.dst_seq, e.dst_image), edge_data(e)


def graph_data(scan: MapScan, level: str) -> dict[str, Any]:
    return {"level": level, "sequences": len(scan.sequences), "vertices": scan.vertices,
            "edges": scan.edge_count}


def vertex_graph(scan: MapScan) -> nx.DiGraph:
    """The vertex graph in memory (what :func:`write_vertex_graphml` streams). O(V + E)
    memory: for tests and small maps."""
    graph = nx.DiGraph(**graph_data(scan, "vertex"))
    graph.add_nodes_from(_vertex_nodes(scan))
    graph.add_edges_from(_vertex_edges(scan))
    return graph


def _declared_writer() -> GraphMLWriter:
    """A GraphMLWriter with every key of the vertex graph declared, always in the same order
    (so each writer gives each attribute the same key id)."""
    writer = GraphMLWriter(prettyprint=False)
    for scope, keys in (("graph", GRAPH_KEYS), ("node", NODE_KEYS), ("edge", EDGE_KEYS)):
        for name, kind in keys.items():
            writer.get_key(name, writer.get_xml_type(kind), scope, None)
    return writer


def _chunks(items: Iterator[Any], size: int) -> Iterator[list[Any]]:
    chunk = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _write_elements(out: IO[str], keys: dict[Any, str], graph: nx.DiGraph, tag: str) -> None:
    """Serialise the ``tag`` elements (``node`` or ``edge``) of ``graph``, not its frame, with
    a fresh declared writer (an edge chunk's endpoints are nodes of its graph: not written)."""
    writer = _declared_writer()
    writer.add_graph_element(graph)
    if writer.keys != keys:  # an attribute outside the schema: its key was never declared
        raise ValueError(f"undeclared GraphML attributes: {set(writer.keys) - set(keys)}")
    element = writer.xml.find("graph")
    assert element is not None
    for child in element.iterfind(tag):
        out.write(tostring(child, encoding="unicode"))
        out.write("\n")


def write_vertex_graphml(scan: MapScan, out: IO[str]) -> tuple[int, int]:
    """Stream the vertex graph of ``scan`` to the text stream ``out``; return (nodes, edges).

    Notes
    -----
    O(V + E) time; memory of one :data:`CHUNK` of nodes or edges (see the module notes).
    """
    header = _declared_writer()
    # XMLGenerator writes to a text stream as it is and (short_empty_elements=False) ends
    # each start tag at once: its tags and our elements interleave in order.
    xml = XMLGenerator(cast(io.TextIOBase, out), "utf-8", short_empty_elements=False)
    xml.startDocument()
    out.write("\n")
    xml.startElement("graphml", AttributesImpl(dict(header.xml.attrib)))
    out.write("\n")
    for key in reversed(list(header.xml)):  # get_key inserts each at the front
        out.write(tostring(key, encoding="unicode"))
        out.write("\n")
    xml.startElement("graph", AttributesImpl({"edgedefault": "directed"}))
    out.write("\n")
    for name, value in graph_data(scan, "vertex").items():
        out.write(tostring(header.add_data(name, type(value), value, "graph"),
                           encoding="unicode"))
        out.write("\n")
    nodes = edges = 0
    for chunk in _chunks(_vertex_nodes(scan), CHUNK):
        part = nx.DiGraph()
        part.add_nodes_from(chunk)
        _write_elements(out, header.keys, part, "node")
        nodes += len(chunk)
    for chunk in _chunks(_vertex_edges(scan), CHUNK):
        part = nx.DiGraph()
        part.add_edges_from(chunk)
        _write_elements(out, header.keys, part, "edge")
        edges += len(chunk)
    xml.endElement("graph")
    out.write("\n")
    xml.endElement("graphml")
    out.write("\n")
    xml.endDocument()
    return nodes, edges


def sequence_graph(scan: MapScan) -> nx.DiGraph:
    """The sequence graph of ``scan`` (see the module notes). O(S + E) time, O(S + pairs)
    memory."""
    graph = nx.DiGraph(level="sequence", sequences=len(scan.sequences), vertices=scan.vertices,
                       edges=scan.edge_count)
    for seq, has_pos in _has_positions(scan):
        graph.add_node(str(seq.seq_id), seq_id=seq.seq_id, name=xml_text(seq.name),
                       frames=seq.length, component=scan.component.get(seq.seq_id, seq.seq_id),
                       source=xml_text(seq.source),
                       created=float(seq.created), positions=has_pos)
    pairs: dict[tuple[int, int], list[Any]] = {}
    for _, _, e in scan.edges():
        agg = pairs.get((e.src_seq, e.dst_seq))
        if agg is None:
            agg = pairs[(e.src_seq, e.dst_seq)] = [0, 0.0, math.inf, -math.inf, set()]
        agg[0] += 1
        agg[1] += e.prob
        agg[2] = min(agg[2], e.prob)
        agg[3] = max(agg[3], e.prob)
        if e.added_by is not None:
            agg[4].add(e.added_by)
    for (a, b), (count, total, low, high, by) in sorted(pairs.items()):
        graph.add_edge(str(a), str(b), edges=count, prob_mean=total / count, prob_min=low,
                       prob_max=high, added_by=" ".join(str(s) for s in sorted(by)))
    return graph


def _has_positions(scan: MapScan) -> Iterator[tuple[SequenceRecord, bool]]:
    for seq in scan.sequences:
        yield seq, scan.position(seq.first_vertex) is not None


def write_sequence_graphml(scan: MapScan, out: IO[bytes]) -> tuple[int, int]:
    """Write the sequence graph with ``networkx.write_graphml`` to the binary stream ``out``;
    return (nodes, edges)."""
    graph = sequence_graph(scan)
    nx.write_graphml(graph, out)
    return graph.number_of_nodes(), graph.number_of_edges()


__all__ = ["CHUNK", "EDGE_KEYS", "GRAPH_KEYS", "NODE_KEYS", "edge_data", "graph_data", "node_id",
           "sequence_graph", "vertex_graph", "write_sequence_graphml", "write_vertex_graphml",
           "xml_text"]
