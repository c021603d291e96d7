"""Curve skeletons: the :class:`Skeleton` graph, its text file format, chains and control nodes.

File format (``.skel``, plain text, one record per line, ``#`` starts a comment)::

    # nestmg skeleton v1
    v 0.0 0.0 0.0      # node 0 (x y z, in the mesh's coordinates)
    v 1.0 0.0 0.0      # node 1
    v 1.0 1.0 0.0      # node 2
    e 0 1              # edge between nodes 0 and 1 (0-based indices, order of the v lines)
    e 1 2
    b 1                # node 1 is a bending node (optional; any number of b lines)

The skeleton must be a tree (connected, no cycle) lying inside the surface. Nodes with one incident
edge are *leaf* nodes, nodes with three or more are *branching* nodes (Casti et al. 2019, Sec. 3);
bending nodes are user-chosen degree-2 nodes. Leaf and bending nodes together are the *control
nodes*: each gets one quadrilateral cross-section of the cage.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import CageOptionError, MeshInputError

__all__ = ["Chain", "Skeleton", "read_skeleton", "write_skeleton"]


@dataclass
class Chain:
    """A maximal path of the skeleton between two key nodes (leaf or branching).

    Attributes
    ----------
    nodes : list of int
        Skeleton node indices from ``nodes[0]`` to ``nodes[-1]`` (both key nodes).
    """

    nodes: list

    @property
    def start(self) -> int:
        return int(self.nodes[0])

    @property
    def end(self) -> int:
        return int(self.nodes[-1])


@dataclass
class Skeleton:
    """A curve skeleton: node positions, edges and the set of bending nodes.

    Attributes
    ----------
    nodes : (k,3) float array
        Node positions.
    edges : (e,2) int array
        Undirected edges (node indices).
    bending : list of int
        Bending nodes (degree-2 nodes where the cage gets a cross-section).
    """

    nodes: np.ndarray
    edges: np.ndarray
    bending: list = field(default_factory=list)

    def __post_init__(self):
        self.nodes = np.asarray(self.nodes, dtype=np.float64)
        self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
        self.bending = sorted({int(b) for b in self.bending})
        self.validate()

    # ------------------------------------------------------------------ structure
    def validate(self) -> None:
        """Raise :class:`MeshInputError` unless the skeleton is a finite tree with valid bending nodes."""
        k = len(self.nodes)
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 3 or k < 2:
            raise MeshInputError(f"skeleton: nodes must be a (k,3) array with k >= 2, got {self.nodes.shape}")
        if not np.isfinite(self.nodes).all():
            raise MeshInputError("skeleton: node positions contain NaN or inf")
        if len(self.edges) == 0:
            raise MeshInputError("skeleton: no edges")
        if self.edges.min() < 0 or self.edges.max() >= k:
            raise MeshInputError(f"skeleton: edge index out of range [0, {k})")
        if np.any(self.edges[:, 0] == self.edges[:, 1]):
            raise MeshInputError("skeleton: an edge joins a node to itself")
        e = np.sort(self.edges, axis=1)
        if len(np.unique(e, axis=0)) != len(e):
            raise MeshInputError("skeleton: duplicate edges")
        if len(self.edges) != k - 1:
            raise MeshInputError(
                f"skeleton: must be a tree (k-1 = {k - 1} edges for {k} nodes), got {len(self.edges)} edges; "
                "skeletons with cycles (shapes with handles) are not supported")
        if self._n_components() != 1:
            raise MeshInputError("skeleton: not connected")
        if np.any(np.linalg.norm(self.nodes[self.edges[:, 0]] - self.nodes[self.edges[:, 1]], axis=1) == 0):
            raise MeshInputError("skeleton: an edge has zero length")
        deg = self.degree
        for b in self.bending:
            if not 0 <= b < k:
                raise MeshInputError(f"skeleton: bending node {b} out of range [0, {k})")
            if deg[b] != 2:
                raise MeshInputError(f"skeleton: bending node {b} has degree {deg[b]} (must be 2: a point "
                                     "inside a branch, not a leaf or branching node)")

    def _n_components(self) -> int:
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        k = len(self.nodes)
        A = sp.coo_matrix((np.ones(len(self.edges)), (self.edges[:, 0], self.edges[:, 1])), shape=(k, k))
        return int(connected_components(A, directed=False)[0])

    @property
    def degree(self) -> np.ndarray:
        """(k,) int: number of edges incident to each node."""
        return np.bincount(self.edges.ravel(), minlength=len(self.nodes))

    @property
    def leaves(self) -> list:
        return [int(i) for i in np.flatnonzero(self.degree == 1)]

    @property
    def branching(self) -> list:
        return [int(i) for i in np.flatnonzero(self.degree >= 3)]

    def neighbors(self) -> list:
        """Adjacency lists."""
        nb: list = [[] for _ in range(len(self.nodes))]
        for a, b in self.edges:
            nb[a].append(int(b))
            nb[b].append(int(a))
        return nb

    def chains(self) -> list:
        """The chains between key nodes (degree != 2); a single path gives one chain."""
        deg = self.degree
        nb = self.neighbors()
        key = set(np.flatnonzero(deg != 2).tolist())
        out, seen = [], set()
        for s in sorted(key):
            for n in nb[s]:
                if (s, n) in seen:
                    continue
                path = [s, n]
                while path[-1] not in key:
                    a, b = nb[path[-1]]
                    path.append(a if a != path[-2] else b)
                seen.add((path[0], path[1]))
                seen.add((path[-1], path[-2]))
                out.append(Chain(path))
        return out

    def with_bending(self, bending) -> Skeleton:
        """A copy with ``bending`` as its bending nodes."""
        return Skeleton(self.nodes.copy(), self.edges.copy(), list(bending))

    def resampled(self, spacing: float) -> Skeleton:
        """A copy whose edges are split so that none is longer than ``spacing``.

        Original nodes keep their indices (new nodes are appended), so bending nodes carry over.
        """
        nodes = [p for p in self.nodes]
        edges = []
        for a, b in self.edges:
            L = float(np.linalg.norm(self.nodes[b] - self.nodes[a]))
            n = max(1, int(np.ceil(L / spacing)))
            prev = int(a)
            for s in range(1, n):
                nodes.append(self.nodes[a] + (self.nodes[b] - self.nodes[a]) * (s / n))
                edges.append((prev, len(nodes) - 1))
                prev = len(nodes) - 1
            edges.append((prev, int(b)))
        return Skeleton(np.array(nodes), np.array(edges), list(self.bending))

    def transformed(self, scale: float, shift: np.ndarray) -> Skeleton:
        """A copy with positions ``(nodes - shift) * scale``."""
        return Skeleton((self.nodes - shift) * scale, self.edges.copy(), list(self.bending))


def read_skeleton(path: str | os.PathLike) -> Skeleton:
    """Read a skeleton file (format in the module docstring).

    Raises
    ------
    MeshInputError
        Unreadable line, bad index, or not a tree (the message names the line or the problem).
    """
    nodes, edges, bending = [], [], []
    with open(path, encoding="utf-8") as fh:
        for no, raw in enumerate(fh, start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            tok = line.split()
            try:
                if tok[0] == "v" and len(tok) == 4:
                    nodes.append([float(t) for t in tok[1:]])
                elif tok[0] == "e" and len(tok) == 3:
                    edges.append([int(t) for t in tok[1:]])
                elif tok[0] == "b" and len(tok) == 2:
                    bending.append(int(tok[1]))
                else:
                    raise CageOptionError("expected 'v x y z', 'e i j' or 'b i'")
            except ValueError as exc:
                raise MeshInputError(f"{path}:{no}: cannot parse {raw.strip()!r} ({exc})") from exc
    if not nodes:
        raise MeshInputError(f"{path}: no 'v' lines (not a skeleton file)")
    return Skeleton(np.array(nodes, dtype=float), np.array(edges, dtype=np.int64).reshape(-1, 2), bending)


def write_skeleton(path: str | os.PathLike, skel: Skeleton, overwrite: bool = False) -> None:
    """Write ``skel`` in the text format read by :func:`read_skeleton`.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``overwrite`` is False.
    """
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(f"{path} exists (pass overwrite=True to replace it)")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# nestmg skeleton v1\n")
        fh.writelines(f"v {p[0]:.17g} {p[1]:.17g} {p[2]:.17g}\n" for p in skel.nodes)
        fh.writelines(f"e {a} {b}\n" for a, b in skel.edges)
        fh.writelines(f"b {b}\n" for b in skel.bending)
