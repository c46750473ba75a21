"""A session revision's pose graph: the document the journal stores, and the edges it stands for.

The workbench edits it (accepting loops, adding and deleting edges); ``slam6d relax SESSION
--method graph`` and the workbench's graph relaxation read it the same way, through
:func:`graph_edges`.

The pose graph of a revision (``Revision.graph``) is a small JSON document::

    {"loops": [{"i", "j", "kind": "loop"|"manual", "fitness", "rms", "transform"}],
     "removed": [[i, j], ...],     # sequential edges deleted by hand
     "rejected": [[i, j], ...]}    # loop hypotheses a person turned down

``transform`` is scan j in scan i's frame as ICP found it; loop closing and relaxation use it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slam6d.graph_relaxation import GraphEdge

GraphDocument = dict[str, Any]


def edge_key(i: int, j: int) -> list[int]:
    """An undirected edge's key: its scans in ascending order."""
    return [min(i, j), max(i, j)]


def graph_edge_list(count: int, graph: GraphDocument) -> list[dict[str, Any]]:
    """The edges of a revision as the user sees them: sequential (unless removed), then loops and manual ones.

    ``k`` numbers them in this order: what ``DELETE .../edges/{k}`` and the edge list of the 3D view take.
    """
    removed = {tuple(edge_key(*e)) for e in graph.get("removed", [])}
    edges: list[dict[str, Any]] = [
        {"i": k, "j": k + 1, "kind": "sequential"} for k in range(count - 1) if (k, k + 1) not in removed
    ]
    for loop in graph.get("loops", []):
        if tuple(edge_key(int(loop["i"]), int(loop["j"]))) not in removed:
            edges.append({**loop, "i": int(loop["i"]), "j": int(loop["j"]), "kind": str(loop.get("kind", "loop"))})
    return [{"k": k, **e} for k, e in enumerate(edges)]


def sequential_links(count: int, graph: GraphDocument) -> list[tuple[int, int]]:
    """The consecutive pairs a revision keeps (its sequential edges not removed by hand).

    ``lum`` and ``simultaneous`` take them as ``links``: a pair registered one onto the other stays a
    neighbour however little it overlaps, as in ``slam6d run``; a removed one counts only by overlap.
    """
    return [(e["i"], e["j"]) for e in graph_edge_list(count, graph) if e["kind"] == "sequential"]


def with_loop(graph: GraphDocument, edge: dict[str, Any]) -> GraphDocument:
    """``graph`` with ``edge`` as its loop between those scans (replacing one there, undoing a removal or rejection)."""
    key = edge_key(edge["i"], edge["j"])
    loops = [e for e in graph.get("loops", []) if edge_key(int(e["i"]), int(e["j"])) != key]
    return {
        **graph,
        "loops": [*loops, edge],
        "removed": [e for e in graph.get("removed", []) if edge_key(*e) != key],
        "rejected": [e for e in graph.get("rejected", []) if edge_key(*e) != key],
    }


def without_loop(graph: GraphDocument, i: int, j: int) -> GraphDocument:
    """``graph`` without its loop or manual edge between scans i and j."""
    key = edge_key(i, j)
    return {**graph, "loops": [e for e in graph.get("loops", []) if edge_key(int(e["i"]), int(e["j"])) != key]}


def graph_edges(count: int, graph: GraphDocument) -> list[GraphEdge]:
    """The edges of a revision of ``count`` scans as relaxation takes them (loops with their ICP transforms)."""
    return [
        GraphEdge(e["i"], e["j"], None if e.get("transform") is None else np.asarray(e["transform"], dtype=np.float64))
        for e in graph_edge_list(count, graph)
    ]
