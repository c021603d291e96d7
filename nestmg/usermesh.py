"""Bring your own tet mesh: the caller's mesh is the fine level, cages give the coarse ones.

Simulation code usually has its tet mesh already (gmsh, TetWild, a Medit or VTU file) and its own FEM
assembly. :func:`hierarchy_from_tets` keeps that mesh as level 0 *exactly* (same nodes, same order, same
tets), so any matrix assembled on it pairs with the hierarchy's prolongations::

    H = hierarchy_from_tets(V, T, 3)                 # H.tets[0] is (V, T)
    ml = solvers.MultigridSolver(A_user, H.P)        # A_user: (n, n) on the user's nodes

Steps: validate the tets; extract their boundary surface (oriented outward) and audit it
(:func:`cagegen.check_mesh`: closed, manifold, one piece, no self-intersection); cage it
(:func:`cagegen.build_cages`, certified nested, with a clearance ``min_gap`` so TetWild's epsilon
envelope cannot put a fine node outside a coarse tet mesh); tet-mesh the cages and prolong from the
user's nodes (:func:`nestmg.hierarchy.tet_hierarchy` with ``fine=(V, T)``, which re-meshes a coarse layer
with a smaller envelope while fine nodes remain outside it). ``Hierarchy.certified`` is true when the
surfaces are certified nested and ``n_outside == 0`` on every level.

Also here: the save/load pair of a hierarchy, :func:`save_hierarchy` ``(directory, H)`` /
:func:`load_hierarchy` ``(directory)`` (exact arrays, reusable without the cache; the path comes first, as
in :func:`nestmg.save_mesh`), :func:`write_vtu_levels` ``(directory, H, fields)`` (every level's tet mesh,
and fields, as VTU files ParaView opens) and :func:`p1_to_p2_prolongation` (a P2 fine level on top of the
P1 hierarchy).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from cagegen.errors import MeshInputError, NestmgError

from .cache import arrays_digest, atomic_write_bytes
from .errors import NestmgInputError
from .hierarchy import Hierarchy, tet_hierarchy
from .options import MeshingOptions, SizingOptions, as_dict, typed
from .progress import Timer, stage_line
from .prolongation import ProlongationReport

__all__ = [
    "boundary_surface",
    "check_user_tets",
    "hierarchy_from_tets",
    "load_hierarchy",
    "p1_to_p2_prolongation",
    "save_hierarchy",
    "write_vtu_levels",
]

SAVE_FORMAT = "nestmg-hierarchy"
SAVE_VERSION = 1


def check_user_tets(V, T) -> tuple[np.ndarray, np.ndarray]:
    """Validate a user tet mesh; return float64 / int64 copies with the same values and order.

    Parameters
    ----------
    V : (n,3) array_like of float
    T : (t,4) array_like of int

    Returns
    -------
    V : (n,3) float64 array
    T : (t,4) int64 array

    Raises
    ------
    MeshInputError
        Wrong shapes, NaN/inf, indices out of range, repeated node in a tet, flat (zero-volume) tets, or
        nodes used by no tet (their matrix rows would be empty; remove them first, e.g. meshio's
        ``remove_orphaned_nodes``).

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]])
    >>> check_user_tets(V, [[0, 1, 2, 3]])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    cagegen.errors.MeshInputError: tet mesh: 1 of 5 nodes are used by no tet (first: node 4); remove them ...
    """
    from solvers.errors import SolverInputError
    from solvers.fem import check_tet_mesh

    from .tetmesh import _flat

    try:
        V, T = check_tet_mesh(V, T)
    except SolverInputError as exc:
        raise MeshInputError(f"tet mesh: {exc}") from exc
    used = np.zeros(len(V), dtype=bool)
    used[T.ravel()] = True
    if not used.all():
        bad = np.flatnonzero(~used)
        raise MeshInputError(
            f"tet mesh: {bad.size} of {len(V)} nodes are used by no tet (first: node {bad[0]}); remove them "
            "(meshio: mesh.remove_orphaned_nodes()) so every node carries a degree of freedom"
        )
    flat = _flat(V, T)
    if flat.any():
        raise MeshInputError(f"tet mesh: {int(flat.sum())} flat (near-zero volume) tets (first: tet "
                             f"{int(np.flatnonzero(flat)[0])}); FEM on them is undefined")
    return V, T


def boundary_surface(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boundary surface of a tet mesh, oriented outward, with compact vertex indices.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
        Tets of either orientation (each boundary face is oriented by its own tet).

    Returns
    -------
    Vs : (m,3) float64 array
        Boundary nodes ``V[index]``.
    Fs : (f,3) int64 array
        Boundary triangles into ``Vs``, outward.
    index : (m,) int64 array
        User node of every surface vertex (increasing).

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.2]])
    >>> T = np.array([[0, 1, 2, 4], [0, 1, 4, 3], [0, 4, 2, 3], [4, 1, 2, 3]])
    >>> Vs, Fs, index = boundary_surface(V, T)
    >>> len(Fs), index.tolist()
    (4, [0, 1, 2, 3])
    """
    from solvers.fem import boundary_faces

    from .tetmesh import orient_tets

    Tp = orient_tets(V, T)  # private copy: positively oriented, so boundary faces come out outward
    F, _ = boundary_faces(Tp)
    index = np.unique(F)
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[index] = np.arange(len(index))
    return np.ascontiguousarray(V[index]), remap[F], index


def _mean_edge(V: np.ndarray, T: np.ndarray) -> float:
    E = np.concatenate([T[:, [i, j]] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    E = np.unique(np.sort(E, axis=1), axis=0)
    return float(np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1).mean())


def hierarchy_from_tets(
    V,
    T,
    levels: int = 3,
    method: str = "nested",
    *,
    sizing: SizingOptions | None = None,
    meshing: MeshingOptions | None = None,
    cages=None,
    cache: bool = True,
    progress: bool | None = None,
) -> Hierarchy:
    """A multigrid hierarchy whose fine level is the caller's tet mesh ``(V, T)``, unchanged.

    Parameters
    ----------
    V : (n,3) array_like of float
    T : (t,4) array_like of int
        The user's tet mesh (every node used by a tet; either tet orientation). ``H.tets[0]`` holds
        exactly these nodes and tets, in this order. Several disjoint bodies (no node shared) get one
        hierarchy each, stacked into this one (:func:`nestmg.bodies.hierarchy_from_tet_bodies`).
    levels : int
        Number of levels, the user's mesh included (>= 2): ``levels - 1`` cages of its boundary. A
        ceiling: a mesh with few boundary faces gets the levels whose smallest cage keeps >= 100 faces
        (:func:`nestmg.sizing.plan_levels`; one stage line, ``options["levels_plan"]``).
    method : str
        Cage backend (``cagegen.build_cages``); uncertified ``"decimate"`` is accepted as a baseline.
    sizing : SizingOptions, optional
        ``face_counts`` (default: 4x fewer faces per level than the boundary surface), ``edge_length``
        (relative to the bounding-box diagonal, where the coarse sizing starts; default: the mean edge
        length of the user's tets) and ``coarsening``. The other fields size a fine level this function
        does not build: they must keep their defaults.
    meshing : MeshingOptions, optional
        Mesher of the coarse layers (``tetgen`` is the AGPL opt-in extra), envelope, extrapolation,
        ``tet_retries`` (default 2 for certified methods, 0 for ``decimate``).
    cages : cagegen.CageOptions, optional
        The method's options; with TetWild and a certified method ``min_gap`` None means
        ``2.5 * epsilon``, as in :func:`nestmg.build_hierarchy`.
    cache : bool
        Reuse cages and coarse tet meshes from ``$NESTMG_CACHE``.
    progress : bool or None
        Progress output (None: only on a terminal).

    Returns
    -------
    Hierarchy
        ``tets[0]`` is ``(V, T)`` (float64 / int64, same values and order); ``surfaces[0]`` its boundary
        (:func:`boundary_surface` gives the node map); everything in ``V``'s coordinates
        (``H.frame`` maps to the normalised frame); ``options["fine_level"] == "user"``.

    Raises
    ------
    nestmg.NestmgInputError
        Bad options, or a sizing field this function does not use set.
    cagegen.MeshInputError
        Bad tets, or a boundary that is not one closed, manifold, self-intersection-free surface
        (several solids, a cavity, touching pieces...); the message names the problem.
    cagegen.LevelsError
        Explicit ``face_counts`` that cannot be met (at once), or a boundary too small for one cage.
    cagegen.CageError
        A cage could not be built or certified.
    """
    from .bodies import hierarchy_from_tet_bodies, tet_bodies
    from .cavities import hollow_solid
    from .hierarchy import _normalize, build_cage_surfaces, cage_options_for
    from .sizing import plan_levels

    sizing, meshing = typed(sizing, SizingOptions, "sizing"), typed(meshing, MeshingOptions, "meshing")
    unused = [f for f in ("max_tets", "mesh_time_budget", "same_domain_levels", "fine_level", "predecimate")
              if getattr(sizing, f) != getattr(SizingOptions(), f)]
    if unused:
        raise NestmgInputError(f"hierarchy_from_tets: sizing.{unused[0]} does not apply (the fine level is "
                               "yours)")
    if levels < 2:
        raise NestmgInputError(f"levels must be >= 2, got {levels}")
    cages = cage_options_for(method, cages, meshing)
    if meshing.tet_retries is None:
        meshing = dataclasses.replace(meshing, tet_retries=0 if method == "decimate" else 2)
    t0 = time.perf_counter()
    timer = Timer()
    with timer("boundary"):
        V, T = check_user_tets(V, T)
        bodies = tet_bodies(T, len(V))
        if bodies is not None:  # several bodies: one hierarchy each, stacked (nestmg.bodies)
            return hierarchy_from_tet_bodies(V, T, bodies, levels, method, sizing=sizing, meshing=meshing,
                                             cages=cages, cache=cache, progress=progress)
        Vn, center, scale = _normalize(V)  # the work is done at unit diagonal, the result is in V's frame
        Vs, Fs, index = boundary_surface(Vn, T)
    # `levels` is a ceiling: a mesh with few boundary faces gets the levels whose smallest cage keeps
    # >= 100 faces (one line says so); explicit face counts that cannot be met fail here, before any work
    fc = None if sizing.face_counts is None else list(sizing.face_counts)
    hollow = hollow_solid(Vs, Fs)  # a solid with voids is caged by its outer boundary (nestmg.cavities)
    lp = plan_levels(len(Fs if hollow is None else hollow[0][1]), levels, face_counts=fc)
    if lp.note:
        stage_line(lp.note, t0)
    with timer("cages"):
        try:  # same clearance (min_gap = 2.5 epsilon under TetWild) and cache as build_hierarchy
            surfaces_n, info = build_cage_surfaces(Vs, Fs, lp.levels, method, sizing=sizing, meshing=meshing,
                                                   cages=cages, cache=cache, progress=progress, t0=t0)
        except MeshInputError as exc:
            raise MeshInputError(f"the boundary of the tet mesh is not a usable surface: {exc}") from exc
    h0 = sizing.edge_length if sizing.edge_length is not None else _mean_edge(Vn, T)  # the unit diagonal
    tets_n, Ps, reps, tt = tet_hierarchy(surfaces_n, sizing=sizing, meshing=meshing, edge_length_abs=h0,
                                         cache=cache, progress=progress, fine=(Vn, T), t0=t0)
    surfaces = [(Vk * scale + center, Fk) for Vk, Fk in surfaces_n]
    if np.array_equal(surfaces_n[0][1], Fs):  # not repaired: the boundary of the user's own nodes, exactly
        surfaces[0] = (V[index], Fs)
    tets = [(V, T)] + [(Vt * scale + center, Tt) for Vt, Tt in tets_n[1:]]
    info["frame"] = {"center": center.tolist(), "scale": scale}
    H = Hierarchy(
        surfaces=surfaces, tets=tets, P=Ps, prolongation_reports=reps, method=method, cage_info=info,
        timings={**timer.seconds, **tt, "total": time.perf_counter() - t0},
        options={"fine_level": "user", "levels": lp.levels, "levels_requested": levels,
                 "levels_plan": lp.to_dict(), "edge_length": h0, "sizing": as_dict(sizing),
                 "meshing": as_dict(meshing), "cages": as_dict(cages)},
        frame={"center": center, "scale": scale},
    )
    if method != "decimate" and any(H.n_outside):
        warnings.warn(f"hierarchy_from_tets: fine nodes outside the coarse tet meshes per level: {H.n_outside} "
                      f"(extrapolated by {meshing.extrapolation!r}); the hierarchy is not certified",
                      stacklevel=2)
    return H


# ----------------------------------------------------------------------------- save / load


def _split_fields(H: Hierarchy) -> dict[str, Any]:
    """Non-array dataclass fields of ``H`` (JSON)."""
    skip = {"surfaces", "tets", "P", "prolongation_reports"}
    return {f.name: getattr(H, f.name) for f in dataclasses.fields(H) if f.name not in skip}


def save_hierarchy(directory: str | os.PathLike, H: Hierarchy, *, vtu: bool = False) -> Path:
    """Write ``H`` to ``directory`` (``hierarchy.npz`` + ``hierarchy.json``) for :func:`load_hierarchy`.

    Arrays are stored exactly (surfaces, tets, prolongations as CSR parts); the JSON holds the summary
    (:meth:`Hierarchy.to_dict`), the remaining fields and the arrays' SHA-256. Both files are written
    atomically.

    Parameters
    ----------
    directory : path
        Created if needed; only ``hierarchy.npz``, ``hierarchy.json`` (and ``level_k.vtu`` with
        ``vtu=True``) are written in it.
    H : Hierarchy
    vtu : bool
        Also write every level's tet mesh as ``level_k.vtu`` (:func:`write_vtu_levels`).

    Returns
    -------
    Path of the directory.

    Raises
    ------
    NestmgInputError
        ``H`` is not a :class:`Hierarchy` (e.g. the arguments in the other order).
    """
    from .io import json_default

    if not isinstance(H, Hierarchy):
        raise NestmgInputError(f"save_hierarchy(directory, H): H must be a Hierarchy, got {type(H).__name__}")
    d = Path(directory)
    arrays: dict[str, np.ndarray] = {}
    for k, (Vk, Fk) in enumerate(H.surfaces):
        arrays[f"surface{k}_V"], arrays[f"surface{k}_F"] = np.asarray(Vk), np.asarray(Fk)
    for k, (Vk, Tk) in enumerate(H.tets):
        arrays[f"tets{k}_V"], arrays[f"tets{k}_T"] = np.asarray(Vk), np.asarray(Tk)
    for k, Pk in enumerate(H.P):
        Pk = sp.csr_matrix(Pk)
        arrays[f"P{k}_data"], arrays[f"P{k}_indices"], arrays[f"P{k}_indptr"] = Pk.data, Pk.indices, Pk.indptr
        arrays[f"P{k}_shape"] = np.asarray(Pk.shape, dtype=np.int64)
    import io as _io

    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    meta = {
        "format": SAVE_FORMAT, "version": SAVE_VERSION, "levels": H.levels, "n_surfaces": len(H.surfaces),
        "sha256": arrays_digest(arrays), "fields": _split_fields(H),
        "prolongation_reports": [r.to_dict() for r in H.prolongation_reports], "summary": H.to_dict(),
    }
    atomic_write_bytes(d / "hierarchy.npz", buf.getvalue())
    atomic_write_bytes(d / "hierarchy.json", json.dumps(meta, indent=1, default=json_default).encode())
    if vtu:
        write_vtu_levels(d, H)
    return d


def load_hierarchy(directory: str | os.PathLike) -> Hierarchy:
    """Read a hierarchy written by :func:`save_hierarchy`.

    Parameters
    ----------
    directory : path
        Holding ``hierarchy.npz`` and ``hierarchy.json``.

    Returns
    -------
    Hierarchy

    Raises
    ------
    NestmgError
        Missing files, another format, or arrays that do not match the recorded SHA-256.
    """
    d = Path(directory)
    npz, js = d / "hierarchy.npz", d / "hierarchy.json"
    if not (npz.is_file() and js.is_file()):
        raise NestmgError(f"{d}: no saved hierarchy (hierarchy.npz and hierarchy.json expected)")
    meta = json.loads(js.read_text())
    if meta.get("format") != SAVE_FORMAT:
        raise NestmgError(f"{js}: not a nestmg hierarchy (format {meta.get('format')!r})")
    if int(meta.get("version", 0)) > SAVE_VERSION:
        raise NestmgError(f"{js}: written by a newer nestmg (version {meta['version']} > {SAVE_VERSION})")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    if arrays_digest(arrays) != meta["sha256"]:
        raise NestmgError(f"{npz}: arrays do not match the SHA-256 recorded in {js.name} (altered or corrupt)")
    L = int(meta["levels"])
    surfaces = [(arrays[f"surface{k}_V"], arrays[f"surface{k}_F"]) for k in range(int(meta["n_surfaces"]))]
    tets = [(arrays[f"tets{k}_V"], arrays[f"tets{k}_T"]) for k in range(L)]
    P = [sp.csr_matrix((arrays[f"P{k}_data"], arrays[f"P{k}_indices"], arrays[f"P{k}_indptr"]),
                       shape=tuple(int(s) for s in arrays[f"P{k}_shape"])) for k in range(L - 1)]
    reps = [ProlongationReport(**r) for r in meta["prolongation_reports"]]
    known = {f.name for f in dataclasses.fields(Hierarchy)}
    fields = {k: v for k, v in meta["fields"].items() if k in known}
    return Hierarchy(surfaces=surfaces, tets=tets, P=P, prolongation_reports=reps, **fields)


# ----------------------------------------------------------------------------- VTU output


def write_vtu_levels(
    directory: str | os.PathLike,
    H: Hierarchy,
    fields: dict[str, np.ndarray] | None = None,
    *,
    frame: tuple[np.ndarray, float] | None = None,
) -> list[Path]:
    """Write every level's tet mesh as ``level_k.vtu`` (ParaView), fine-level fields on ``level_0.vtu``.

    Parameters
    ----------
    directory : path
    H : Hierarchy
    fields : dict of name -> (n_0,) or (n_0, c) array, optional
        Point data of the fine level (e.g. the solution). Coarse levels get ``level`` cell data only.
    frame : (center (3,), scale), optional
        Coordinates are written as ``V * scale + center`` (undo :func:`nestmg.normalize`), so files are in
        the user's coordinates.

    Returns
    -------
    list of Path

    Raises
    ------
    NestmgInputError
        ``H`` is not a :class:`Hierarchy`, or a field does not have one value per fine node.
    """
    from .io import save_tet_mesh

    if not isinstance(H, Hierarchy):
        raise NestmgInputError(f"write_vtu_levels(directory, H): H must be a Hierarchy, got {type(H).__name__}")
    d = Path(directory)
    out = []
    n0 = len(H.tets[0][0])
    for name, f in (fields or {}).items():
        if np.asarray(f).shape[0] != n0:
            raise NestmgInputError(f"field {name!r} has {np.asarray(f).shape[0]} values, the fine level {n0} nodes")
    for k, (Vk, Tk) in enumerate(H.tets):
        Vw = np.asarray(Vk) if frame is None else np.asarray(Vk) * frame[1] + np.asarray(frame[0])
        pdata = {n: np.asarray(f) for n, f in (fields or {}).items()} if k == 0 else {}
        p = d / f"level_{k}.vtu"
        save_tet_mesh(p, Vw, Tk, point_data=pdata, cell_data={"level": np.full(len(Tk), k, dtype=np.int32)})
        out.append(p)
    return out


# ----------------------------------------------------------------------------- P2 on top


def p1_to_p2_prolongation(n_vertices: int, edges) -> sp.csr_matrix:
    """Exact interpolation of P1 functions into P2 on the same tets: a P2 fine level above a P1 hierarchy.

    P2 degrees of freedom ordered as in scikit-fem's ``ElementTetP2`` on a ``MeshTet``: the vertices
    first, then one per edge (``mesh.edges.T``). A P1 function is reproduced exactly: vertex values are
    copied, an edge's value is the mean of its two vertices. With ``Ps = [p1_to_p2_prolongation(...)] +
    H.P`` a P2 matrix gets a multigrid whose second level is the user's P1 mesh.

    Parameters
    ----------
    n_vertices : int
    edges : (e,2) int array
        Vertex pairs of the edges, in the P2 numbering order.

    Returns
    -------
    (n_vertices + e, n_vertices) csr_matrix

    Examples
    --------
    >>> P = p1_to_p2_prolongation(3, [[0, 1], [1, 2]])
    >>> P.toarray().tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5]]
    """
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ne = len(E)
    rows = np.concatenate([np.arange(n_vertices), np.repeat(n_vertices + np.arange(ne), 2)])
    cols = np.concatenate([np.arange(n_vertices), E.ravel()])
    vals = np.concatenate([np.ones(n_vertices), np.full(2 * ne, 0.5)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n_vertices + ne, n_vertices))
