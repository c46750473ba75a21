"""A revision's pose graph as the workbench stores it, and the edges a user sees in it.

The pose graph of a revision (``Revision.graph``) is a small JSON document::

    {"loops": [{"i", "j", "kind": "loop"|"manual", "fitness", "rms", "transform"}],
     "removed": [[i, j], ...],     # sequential edges deleted by hand
     "rejected": [[i, j], ...]}    # loop hypotheses a person turned down

``transform`` is scan j in scan i's frame as ICP found it; loop closing and relaxation use it.
"""

from __future__ import annotations

from typing import Any

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
