"""Topology checks for triangle meshes: closed, edge- and vertex-manifold, consistently oriented.

Geodesic tools (potpourri3d's heat method and tracer) need a closed 2-manifold; the
intersection metrics need a closed surface to have a volume. These checks say precisely
what is wrong instead of letting a solver assert deep inside C++.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import InputError


@dataclass(frozen=True)
class MeshTopologyReport:
    """What :func:`check_closed_manifold` found.

    ``boundary_edges``: edges used by one face; ``nonmanifold_edges``: by three or more;
    ``misoriented_edges``: interior edges whose two faces traverse them the same way;
    ``nonmanifold_vertices``: vertices whose faces form more than one fan;
    ``degenerate_faces``: faces that repeat a vertex; ``components``: connected pieces.
    """

    n_vertices: int
    n_faces: int
    boundary_edges: int
    nonmanifold_edges: int
    misoriented_edges: int
    nonmanifold_vertices: int
    degenerate_faces: int
    unreferenced_vertices: int
    components: int

    @property
    def closed(self) -> bool:
        return self.boundary_edges == 0 and self.nonmanifold_edges == 0

    @property
    def manifold(self) -> bool:
        return (
            self.nonmanifold_edges == 0
            and self.nonmanifold_vertices == 0
            and self.degenerate_faces == 0
            and self.misoriented_edges == 0
        )

    def describe(self) -> str:
        """One line: "closed, manifold" or what is wrong."""
        if self.closed and self.manifold:
            text = "closed, manifold"
        else:
            problems = []
            for label, count in (
                ("boundary edges", self.boundary_edges),
                ("non-manifold edges", self.nonmanifold_edges),
                ("inconsistently oriented edges", self.misoriented_edges),
                ("non-manifold vertices", self.nonmanifold_vertices),
                ("degenerate faces", self.degenerate_faces),
            ):
                if count:
                    problems.append(f"{count} {label}")
            text = ("closed" if self.closed else "open") + ", " + (
                "manifold" if self.manifold else "NOT manifold"
            ) + " (" + ", ".join(problems) + ")"
        if self.components != 1:
            text += f", {self.components} components"
        return text


def check_closed_manifold(faces: np.ndarray, n_vertices: int | None = None) -> MeshTopologyReport:
    """Inspect the topology of a triangle mesh.

    faces: (F, 3) int vertex indices. n_vertices: V (defaults to max index + 1).
    """
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces must have shape (F, 3), got {faces.shape}", element="faces")
    faces = faces.astype(np.int64)
    n_faces = len(faces)
    if n_vertices is None:
        n_vertices = int(faces.max()) + 1 if n_faces else 0

    degenerate = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    good = faces[~degenerate]

    # Directed half-edges a->b of every face.
    tails = good.reshape(-1)
    heads = np.roll(good, -1, axis=1).reshape(-1)
    lo = np.minimum(tails, heads)
    hi = np.maximum(tails, heads)
    undirected = lo * n_vertices + hi
    _, inverse, counts = np.unique(undirected, return_inverse=True, return_counts=True)
    boundary = int(np.sum(counts == 1))
    nonmanifold_edges = int(np.sum(counts > 2))

    # An interior edge is consistently oriented when its two faces traverse it in opposite
    # directions: the directed key a->b then occurs exactly once.
    directed = tails * n_vertices + heads
    _, dcounts = np.unique(directed, return_counts=True)
    misoriented = int(np.sum(dcounts > 1))

    # Vertex manifoldness: around each vertex, step from one outgoing half-edge to the next
    # through the neighbouring face. Each vertex of a manifold has exactly one such cycle.
    nonmanifold_vertices = 0
    if boundary == 0 and nonmanifold_edges == 0 and misoriented == 0 and len(good):
        n_he = len(tails)
        order = np.argsort(directed)
        sorted_keys = directed[order]
        # prev vertex in the same face of half-edge h (a->b) is c; next outgoing from a is a->c.
        prev_vertex = np.roll(good, 1, axis=1).reshape(-1)
        wanted = tails * n_vertices + prev_vertex
        pos = np.searchsorted(sorted_keys, wanted)
        pos = np.clip(pos, 0, n_he - 1)
        found = sorted_keys[pos] == wanted
        nxt = np.where(found, order[pos], np.arange(n_he))
        graph = coo_matrix((np.ones(n_he), (np.arange(n_he), nxt)), shape=(n_he, n_he))
        n_cycles, _ = connected_components(graph, directed=False)
        used_vertices = len(np.unique(tails))
        nonmanifold_vertices = int(n_cycles - used_vertices)

    referenced = np.zeros(n_vertices, dtype=bool)
    referenced[faces.reshape(-1)] = True
    unreferenced = int(np.sum(~referenced))

    if len(good):
        adjacency = coo_matrix(
            (np.ones(len(tails)), (tails, heads)), shape=(n_vertices, n_vertices)
        )
        n_comp, labels = connected_components(adjacency, directed=False)
        components = len(np.unique(labels[referenced]))
    else:
        components = 0

    return MeshTopologyReport(
        n_vertices=int(n_vertices),
        n_faces=int(n_faces),
        boundary_edges=boundary,
        nonmanifold_edges=nonmanifold_edges,
        misoriented_edges=misoriented,
        nonmanifold_vertices=nonmanifold_vertices,
        degenerate_faces=int(np.sum(degenerate)),
        unreferenced_vertices=unreferenced,
        components=int(components),
    )


def require_closed_manifold(
    faces: np.ndarray, n_vertices: int | None = None, *, source: str = "", element: str = "surface"
) -> MeshTopologyReport:
    """Raise :class:`InputError` naming ``source`` and ``element`` unless the mesh is a closed,
    connected, consistently oriented 2-manifold."""
    report = check_closed_manifold(faces, n_vertices)
    if not (report.closed and report.manifold) or report.components != 1:
        raise InputError(
            "a closed, connected 2-manifold surface is needed here, but it is "
            + report.describe(),
            source=source,
            element=element,
        )
    return report
