"""Inputs made of several closed pieces: one cage hierarchy per piece (``components="separate"``).

A PDE on a solid made of several disjoint pieces decouples into one problem per piece, so each piece
gets its own hierarchy: :func:`build_cages_per_component` splits the input into edge-connected
components and calls :func:`cagegen.build_cages` on each (every piece is audited and, for certified
methods, every cage is verified against its own piece). The cages of different pieces are *not*
checked against each other (they may overlap where pieces nearly touch; that is harmless for
independent problems).

Refused, with :class:`~cagegen.errors.MeshInputError`:

* pieces that intersect each other (the union is not a solid bounded by the given surface);
* a piece inside another one (a solid with an inner cavity, or a separate body floating inside a
  hollow one): independent hierarchies would fill the cavity. Not supported.

Example
-------
>>> import numpy as np, trimesh
>>> s = trimesh.creation.icosphere(subdivisions=3)
>>> V = np.vstack([s.vertices, s.vertices + [3.0, 0, 0]]); F = np.vstack([s.faces, s.faces + len(s.vertices)])
>>> [len(p[1]) for p in split_components(V, F)]
[1280, 1280]
>>> out = build_cages_per_component(V, F, 2, method="decimate")
>>> [[len(Fk) for _, Fk in layers] for layers in out]
[[1280, 320], [1280, 320]]
"""

from __future__ import annotations

import numpy as np

from ._geometry import as_mesh_arrays, cross_intersection_pairs, vertex_components
from .errors import MeshInputError

__all__ = ["build_cages_per_component", "check_components_disjoint", "crossing_pairs", "split_components"]


def split_components(V, F) -> list[tuple[np.ndarray, np.ndarray]]:
    """Edge-connected pieces of ``(V, F)``, each with its own compact vertex array.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int

    Returns
    -------
    list of (V_i (n_i,3) float64, F_i (m_i,3) int64)
        Ordered by the smallest face index of each piece (deterministic); unreferenced vertices are
        dropped. New arrays; the inputs are not modified.
    """
    V, F = as_mesh_arrays(V, F, "input")
    n = V.shape[0]
    flab = vertex_components(F, n)[F[:, 0]]
    _, first = np.unique(flab, return_index=True)
    pieces = []
    for lab in flab[np.sort(first)]:
        Fi = F[flab == lab]
        used = np.unique(Fi)
        remap = np.full(n, -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        pieces.append((V[used].copy(), remap[Fi]))
    return pieces


def crossing_pairs(VA, FA, VB, FB) -> np.ndarray:
    """``(k, 2)`` pairs (face of A, face of B) that intersect, by the verifier's exact test; empty when the
    two surfaces neither cross nor touch."""
    return cross_intersection_pairs(VA, FA, VB, FB)


def check_components_disjoint(pieces: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Raise :class:`MeshInputError` if two pieces intersect or one lies inside another.

    Parameters
    ----------
    pieces : list of (V_i, F_i)
        Closed, outward-oriented surfaces (e.g. from :func:`split_components`).
    """
    import igl

    lo = np.array([V.min(axis=0) for V, _ in pieces])
    hi = np.array([V.max(axis=0) for V, _ in pieces])
    for a in range(len(pieces)):
        for b in range(a + 1, len(pieces)):
            if np.any(hi[a] < lo[b]) or np.any(hi[b] < lo[a]):
                continue  # bounding boxes apart: neither crossing nor containment possible
            (VA, FA), (VB, FB) = pieces[a], pieces[b]
            if len(cross_intersection_pairs(VA, FA, VB, FB)):
                raise MeshInputError(
                    f"components {a} and {b} intersect each other: the input is not the boundary of a "
                    "solid; merge them (mesh boolean union) first"
                )
            for inner, outer, (Vi, _), (Vo, Fo) in ((a, b, pieces[a], pieces[b]), (b, a, pieces[b], pieces[a])):
                w = float(np.asarray(igl.winding_number(Vo, Fo, Vi[:1])).ravel()[0])
                if abs(w) > 0.5:
                    raise MeshInputError(
                        f"component {inner} lies inside component {outer} (a solid with a cavity, or a body "
                        "inside a hollow one): one hierarchy per component would fill the cavity; "
                        "not supported"
                    )


def build_cages_per_component(V, F, levels: int | None = None, method: str = "nested", *,
                              repair: bool = False, return_info: bool = False, **kwargs) -> list:
    """One cage hierarchy per closed piece of a multi-component input.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
        One or more disjoint, closed, outward-oriented pieces (none inside another).
    levels, method, return_info, **kwargs
        As for :func:`cagegen.build_cages`, applied to each piece (``face_counts``, if given, applies
        to every piece; the default 4x-per-level counts follow each piece's own face count).
    repair : bool
        Apply :func:`cagegen.repair_mesh` to the whole input before splitting it.

    Returns
    -------
    list
        One entry per piece (order of :func:`split_components`): what ``build_cages`` returns for it,
        ``layers`` or ``(layers, info)``; with ``return_info`` each info also holds ``component`` (its
        index) and ``n_components``.

    Raises
    ------
    MeshInputError
        A piece is unusable (the message names it), pieces intersect, or one lies inside another.
    """
    from .audit import check_mesh, repair_mesh
    from .build import build_cages

    if repair:
        V, F = repair_mesh(V, F)
    pieces = split_components(V, F)
    # every piece audited, then the pieces against each other, before any cage is built
    for k, (Vk, Fk) in enumerate(pieces):
        check_mesh(Vk, Fk, name=f"component {k} of {len(pieces)}")
    check_components_disjoint(pieces)
    results = []
    for k, (Vk, Fk) in enumerate(pieces):
        res = build_cages(Vk, Fk, levels, method=method, return_info=return_info, **kwargs)
        if return_info:
            res[1]["component"], res[1]["n_components"] = k, len(pieces)
        results.append(res)
    return results
