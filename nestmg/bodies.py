"""Inputs of several disjoint closed bodies (an assembly exported as one file): one hierarchy per body.

A PDE on disjoint solids decouples into one problem per solid, so ``nestmg solve`` and ``nestmg cages``
split such an input into its bodies, build one hierarchy per body (:func:`build_body_hierarchies`) and
solve each body's problem on its own; the files they write hold all bodies. The rules:

* **bodies**: the edge-connected pieces of the input (:func:`cagegen.split_components`) when no two of
  them intersect and none lies inside another (:func:`cagegen.components.check_components_disjoint`); a
  piece facing inward inside an outward one is a void of that body (:mod:`nestmg.cavities`) and goes with
  it. Other pieces that intersect or nest describe one solid: the audit refuses them and ``--repair``
  makes their union (:func:`nestmg.hierarchy.build_hierarchy`).
* **one resolution for the file**: the fine edge is planned once on the whole input, with the file's
  budgets (``max_tets``, ``mesh_time_budget`` and the memory check count all bodies' tets;
  :func:`body_sizings`), and every body is meshed at that edge.
* **levels**: ``levels`` is a ceiling for each body (a small body gets the levels that fit it).
* the cage clearance and TetWild's envelope are relative to each body's own bounding box, as they are for
  a single input; the model problems are posed in the whole file's normalised frame (one centre, one
  scale: :func:`file_frame`), so every body sees the same right-hand side and ``--lam``.
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager

import numpy as np

from .errors import NestmgError, NestmgInputError
from .options import MeshingOptions, SizingOptions, typed

__all__ = ["SPECK_FRACTION", "audit_bodies", "body_sizings", "build_body_hierarchies", "disjoint_bodies",
           "drop_specks", "file_frame", "hierarchy_from_tet_bodies", "merge_meshes", "naming_body", "solve_bodies", "summed_timings",
           "tet_bodies", "tet_components"]


def disjoint_bodies(V: np.ndarray, F: np.ndarray, why: list | None = None
                    ) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """The bodies of a surface made of several closed pieces that neither intersect nor nest, else None.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    why : list, optional
        Receives the reason when the input has several pieces that cross or nest (one line).

    Returns
    -------
    list of (V_i, F_i) or None
        One entry per piece (order of :func:`cagegen.split_components`; new arrays), or None when the
        input is one piece or its pieces intersect or nest (one solid: the audit or the repair decides).
    """
    import cagegen
    from cagegen.components import check_components_disjoint

    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        return None  # not a triangle surface: the single-input path gives the error
    from .cavities import merge_surfaces, solid_groups

    pieces = cagegen.split_components(V, F)
    if len(pieces) < 2:
        return None
    groups = solid_groups(pieces)  # solids with voids: each outer surface with the voids inside it
    if groups is not None and len(groups) == 1:
        return None  # one solid with voids: the single-input path (nestmg.cavities)
    outers = pieces if groups is None else [outer for outer, _ in groups]
    try:
        check_components_disjoint(outers)
    except cagegen.MeshInputError as exc:
        if why is not None:
            why.append(str(exc))
        return None
    return pieces if groups is None else [merge_surfaces([outer, *voids]) for outer, voids in groups]


#: A body enclosing less than this fraction of the whole input's volume is a speck (scan debris, a stray
#: shell of a CAD export): refused, or dropped with ``repair`` (as the repair's solid drops them).
SPECK_FRACTION = 1e-3


def drop_specks(bodies: list, repair: bool = False) -> list:
    """``bodies`` without the specks (:data:`SPECK_FRACTION`) when ``repair``; without ``repair`` an input with
    specks is refused (:class:`cagegen.MeshInputError` naming the option), not meshed body by body."""
    import cagegen

    from .memory import enclosed_volume
    from .progress import stage_line

    vols = np.array([enclosed_volume(Vb, Fb) for Vb, Fb in bodies])
    specks = np.flatnonzero(vols < SPECK_FRACTION * vols.sum())
    if not specks.size:
        return bodies
    if not repair:
        raise cagegen.MeshInputError(
            f"input: {len(bodies)} disjoint bodies, {specks.size} of them specks (volume under "
            f"{SPECK_FRACTION:g} of the whole; first: body {specks[0] + 1}); --repair drops them")
    stage_line(f"bodies: {specks.size} of {len(bodies)} dropped, specks under {SPECK_FRACTION:g} of the volume")
    return [b for k, b in enumerate(bodies) if k not in set(specks.tolist())]


def audit_bodies(bodies: list, repair: bool = False) -> None:
    """Audit every body before any is built, so that a bad last body fails in seconds, not after the others'
    hierarchies (:func:`cagegen.check_mesh`, the message naming the body). With ``repair`` only what the
    cheap repairs and TetWild's solid cannot mend is refused here (the rest is mended body by body)."""
    import cagegen

    from .cavities import audit_voids
    from .solid import UNREPAIRABLE

    for k, (Vb, Fb) in enumerate(bodies):
        name = f"body {k + 1} of {len(bodies)}"
        if not repair:
            audit_voids(Vb, Fb, name=name)  # a body with voids: its outer surface and each void
            continue
        Vr, Fr = cagegen.repair_mesh(Vb, Fb)
        bad = [p for p in cagegen.audit_mesh(Vr, Fr).problems if p.startswith(UNREPAIRABLE)]
        if bad:
            raise cagegen.MeshInputError(f"{name} is not a usable closed surface: {'; '.join(bad)}")


def file_frame(V: np.ndarray) -> tuple[np.ndarray, float]:
    """``(center, scale)`` of the whole input: ``(V - center) / scale`` has a centred unit-diagonal box (the
    frame :func:`nestmg.build_hierarchy` normalises a single input to)."""
    from .hierarchy import _normalize

    _, center, scale = _normalize(np.asarray(V, dtype=np.float64))
    return center, scale


@contextmanager
def naming_body(k: int, n: int):
    """Re-raise a :class:`NestmgError` of body ``k`` (0-based) of ``n`` with "body k+1 of n: " in front."""
    try:
        yield
    except NestmgError as exc:
        exc.args = (f"body {k + 1} of {n}: {exc}", *exc.args[1:])
        raise


def summed_timings(hierarchies: list) -> dict:
    """The hierarchies' numeric ``timings``, summed key by key (seconds over all bodies)."""
    out: dict = {}
    for h in hierarchies:
        for key, v in h.timings.items():
            if isinstance(v, (int, float)):
                out[key] = out.get(key, 0.0) + v
    return out


def body_sizings(V: np.ndarray, F: np.ndarray, bodies: list, levels: int,
                 sizing: SizingOptions | None = None, meshing: MeshingOptions | None = None
                 ) -> tuple[list[SizingOptions], dict]:
    """Every body's sizing options: the fine edge planned once on the whole input.

    The whole input (all bodies) is planned as one (:func:`nestmg.sizing.plan_hierarchy`: the enclosed
    volume and faces of all bodies against ``max_tets``, ``mesh_time_budget`` and the memory), so the
    budgets are the file's and every body gets the same absolute fine edge, given to it as
    ``edge_length`` relative to its own bounding-box diagonal.

    Returns
    -------
    (list of SizingOptions, dict)
        One per body, and the whole input's plan (``SizingPlan.to_dict()``).

    Raises
    ------
    NestmgInputError
        Explicit ``face_counts`` (they count one solid's cage faces).
    nestmg.sizing.SizingError, nestmg.memory.TetMeshMemoryError
        The whole input does not fit the budget (before any body is built).
    """
    from cagegen import bbox_diagonal

    from .hierarchy import _fine_level, _plan

    sizing, meshing = typed(sizing, SizingOptions, "sizing"), typed(meshing, MeshingOptions, "meshing")
    if sizing.face_counts is not None:
        raise NestmgInputError(
            f"face_counts count one solid's cage faces; this input has {len(bodies)} disjoint bodies: give "
            "levels instead (each body gets the levels that fit it), or split the file")
    _, refine = _fine_level(levels, sizing, meshing.mesher)
    center, scale = file_frame(V)
    plan = _plan((np.asarray(V, dtype=np.float64) - center) / scale, np.asarray(F, dtype=np.int64), levels,
                 sizing, meshing.mesher, refine)
    out = [dataclasses.replace(sizing, edge_length=plan.edge_length * scale / float(bbox_diagonal(Vb)),
                               max_tets=None) for Vb, _ in bodies]
    return out, plan.to_dict()


def build_body_hierarchies(V: np.ndarray, F: np.ndarray, levels: int = 3, method: str = "nested", *,
                           bodies: list | None = None, sizing: SizingOptions | None = None,
                           meshing: MeshingOptions | None = None, cages=None, cache: bool = True,
                           progress: bool | None = None) -> list:
    """One :class:`nestmg.Hierarchy` per disjoint body of ``(V, F)`` (see the module's rules).

    Parameters
    ----------
    V, F
        The whole input (several closed bodies).
    levels, method, sizing, meshing, cages, cache, progress
        As for :func:`nestmg.build_hierarchy`, for each body (``sizing`` planned on the whole input,
        :func:`body_sizings`).
    bodies : list of (V_i, F_i), optional
        :func:`disjoint_bodies` of the input, when already computed.

    Returns
    -------
    list of Hierarchy
        In the order of the bodies, each in the input's coordinates.

    Raises
    ------
    NestmgInputError
        The input is not several disjoint bodies.
    cagegen.MeshInputError, cagegen.CageError, nestmg.sizing.SizingError
        As for :func:`nestmg.build_hierarchy`; a body's error names the body.
    """
    import time

    from .hierarchy import build_hierarchy
    from .progress import stage_line

    t0 = time.perf_counter()
    bodies = disjoint_bodies(V, F) if bodies is None else bodies
    if not bodies:
        raise NestmgInputError("build_body_hierarchies: the input is not several disjoint closed bodies")
    sizings, plan = body_sizings(V, F, bodies, levels, sizing, meshing)
    audit_bodies(bodies, repair=bool(getattr(cages, "repair", False)))
    stage_line(f"bodies: {len(bodies)} disjoint bodies ({', '.join(f'{len(Fb):,}' for _, Fb in bodies)} "
               f"faces): one hierarchy each, fine edge {plan['edge_length']:.3g} of the whole input's "
               f"diagonal ({plan['rule']}), ~{plan['expected_tets'][0]:,} fine tets in all", t0)
    out = []
    for k, ((Vb, Fb), sz) in enumerate(zip(bodies, sizings)):
        stage_line(f"body {k + 1}/{len(bodies)}: {len(Fb):,} faces", t0)
        with naming_body(k, len(bodies)):
            out.append(build_hierarchy(Vb, Fb, levels, method, sizing=sz, meshing=meshing, cages=cages,
                                       cache=cache, progress=progress))
    return out


def merge_meshes(meshes: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One mesh from several: ``(V, C, owner)`` with every piece's cells re-indexed and ``owner[i]`` the
    piece of cell ``i`` (for files that hold all bodies)."""
    offsets = np.cumsum([0] + [len(Vk) for Vk, _ in meshes])
    V = np.vstack([np.asarray(Vk, dtype=np.float64) for Vk, _ in meshes])
    C = np.vstack([np.asarray(Ck, dtype=np.int64) + o for (_, Ck), o in zip(meshes, offsets)])
    owner = np.repeat(np.arange(len(meshes), dtype=np.int32), [len(Ck) for _, Ck in meshes])
    return V, C, owner


def solve_bodies(hierarchies: list, frame: tuple[np.ndarray, float], problem: str = "poisson-dirichlet",
                 options=None, *, return_solution: bool = False) -> dict:
    """Each body's problem on its own hierarchy (:func:`nestmg.solve_on_hierarchy`), posed in one frame.

    Parameters
    ----------
    hierarchies : list of Hierarchy
        :func:`build_body_hierarchies` (input coordinates).
    frame : (center (3,), scale)
        The frame the problems are posed in (:func:`file_frame` of the whole input): nodes
        ``(V - center) / scale``.
    problem, options, return_solution
        As for :func:`nestmg.solve_on_hierarchy`.

    Returns
    -------
    dict
        ``bodies``: every body's report. The combined fields: ``converged`` (every body), ``diverged``
        (some body), ``iterations`` (the most), ``factor`` and ``operator_complexity`` (the largest),
        ``seconds`` and ``cpu_seconds`` (sums), ``residuals`` (the body with the largest factor's);
        ``solution`` (``return_solution``): the bodies' solutions one after the other (the nodes of
        :func:`merge_meshes` of the fine levels).
    """
    from .run import solve_on_hierarchy

    center, scale = np.asarray(frame[0], dtype=np.float64), float(frame[1])
    reports = []
    for h in hierarchies:
        tets = [((np.asarray(Vt) - center) / scale, T) for Vt, T in h.tets]
        reports.append(solve_on_hierarchy(tets, h.P, problem, options, return_solution=return_solution))
    sols = [r.pop("solution", None) for r in reports]
    worst = max(range(len(reports)), key=lambda k: reports[k]["factor"])
    out = dict(reports[worst])
    out.update(bodies=reports, worst_body=worst, converged=all(r["converged"] for r in reports),
               diverged=any(r["diverged"] for r in reports), iterations=max(r["iterations"] for r in reports),
               operator_complexity=max((r.get("operator_complexity") or 0.0) for r in reports) or None)
    for key in ("seconds", "cpu_seconds"):
        vals = [r.get(key) for r in reports]
        if all(isinstance(v, dict) for v in vals):
            out[key] = {k: sum(v[k] for v in vals) for k in vals[0]}
        elif all(isinstance(v, (int, float)) for v in vals):
            out[key] = float(sum(vals))
    if return_solution:
        out["solution"] = np.concatenate(sols, axis=0)
    return out


def tet_bodies(T: np.ndarray, n: int) -> list[np.ndarray] | None:
    """The nodes of every body of a tet mesh (tets sharing a node are one body), or None for one body.

    Parameters
    ----------
    T : (t,4) int array
    n : int
        Number of nodes (every one used by a tet).

    Returns
    -------
    list of int arrays or None
        Sorted node indices per body, bodies ordered by their smallest node.
    """
    labels = tet_components(T, n)
    k = int(labels.max()) + 1 if n else 0
    if k < 2:
        return None
    order = np.argsort(labels, kind="stable")
    return np.split(order, np.cumsum(np.bincount(labels, minlength=k))[:-1])


def tet_components(T: np.ndarray, n: int) -> np.ndarray:
    """Body label of every node of a tet mesh (0, 1, ... in the order of their smallest node)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    T = np.asarray(T, dtype=np.int64)
    rows, cols = np.repeat(T[:, 0], 3), T[:, 1:].ravel()  # three edges span a tet
    g = sp.coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n)).tocsr()
    _, labels = connected_components(g, directed=False)
    _, first = np.unique(labels, return_index=True)  # the smallest node of every label
    rank = np.empty(first.size, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[labels]


def hierarchy_from_tet_bodies(V: np.ndarray, T: np.ndarray, bodies: list, levels: int = 3,
                              method: str = "nested", *, sizing: SizingOptions | None = None, **kwargs):
    """One :class:`nestmg.Hierarchy` for a tet mesh of several bodies: each body's own hierarchy
    (:func:`nestmg.hierarchy_from_tets`), stacked block by block.

    Level 0 is ``(V, T)`` itself (the caller's nodes and order). Level ``k >= 1`` holds level ``k`` of every
    body, one after the other; a body with fewer levels (``levels`` is a ceiling per body) repeats its
    coarsest level, prolonged by the identity. ``P[0]`` maps each body's coarse nodes to that body's
    nodes only, so a matrix assembled on ``(V, T)`` and ``H.P`` make one multigrid for all bodies.

    Parameters
    ----------
    V, T
        The caller's tet mesh (checked by :func:`nestmg.usermesh.check_user_tets`).
    bodies : list of int arrays
        :func:`tet_bodies` of ``T``.
    levels, method, sizing, **kwargs
        As for :func:`nestmg.hierarchy_from_tets`, applied to every body (``sizing.edge_length`` is the
        whole mesh's fraction: converted to each body's diagonal).

    Returns
    -------
    Hierarchy
        ``cage_info["bodies"]``: every body's cage info and node count; certified when every body is.
    """
    from cagegen import bbox_diagonal

    from .hierarchy import Hierarchy
    from .progress import stage_line
    from .usermesh import boundary_surface, hierarchy_from_tets

    sizing = typed(sizing, SizingOptions, "sizing")
    center, scale = file_frame(V)
    stage_line(f"bodies: the tet mesh has {len(bodies)} disjoint bodies "
               f"({', '.join(f'{len(b):,}' for b in bodies)} nodes): one hierarchy each")
    meshes = _body_meshes(V, T, bodies)
    audit_bodies([boundary_surface(Vb, Tb)[:2] for Vb, Tb in meshes],  # in seconds, before any is built
                 repair=bool(getattr(kwargs.get("cages"), "repair", False)))
    hs = []
    for k, (Vb, Tb) in enumerate(meshes):
        sz = sizing if sizing.edge_length is None else dataclasses.replace(
            sizing, edge_length=sizing.edge_length * scale / float(bbox_diagonal(Vb)))
        stage_line(f"body {k + 1}/{len(bodies)}: {len(Tb):,} tets")
        with naming_body(k, len(bodies)):
            hs.append(hierarchy_from_tets(Vb, Tb, levels, method, sizing=sz, **kwargs))
    tets, surfaces, P, reports = _stacked_levels(V, T, bodies, hs)
    oks = [h.surfaces_nested for h in hs]
    layers = [dict(d, body=b) for b, h in enumerate(hs)
              for d in (h.cage_info.get("backend") or {}).get("layers", [])]  # for fallback_layers
    info = {"bodies": [{"nodes": len(b), "levels": h.levels, **h.cage_info} for b, h in zip(bodies, hs)],
            "verification": {"ok": None if any(o is None for o in oks) else all(oks)},
            "backend": {"layers": layers}, "frame": {"center": center.tolist(), "scale": scale}}
    return Hierarchy(surfaces=surfaces, tets=tets, P=P, prolongation_reports=reports, method=method,
                     cage_info=info, timings=summed_timings(hs),
                     options=dict(hs[0].options, levels=len(tets), bodies=[h.levels for h in hs]),
                     frame={"center": center, "scale": scale})


def _body_meshes(V: np.ndarray, T: np.ndarray, bodies: list) -> list:
    """Every body's own tet mesh ``(V_b, T_b)``: its nodes in ``bodies[b]``'s order, its tets in ``T``'s."""
    label, local = np.empty(len(V), dtype=np.int64), np.empty(len(V), dtype=np.int64)
    for b, nodes in enumerate(bodies):
        label[nodes], local[nodes] = b, np.arange(len(nodes))
    tet_body = label[T[:, 0]]
    return [(V[nodes], local[T[tet_body == b]]) for b, nodes in enumerate(bodies)]


def _stacked_levels(V: np.ndarray, T: np.ndarray, bodies: list, hs: list) -> tuple[list, list, list, list]:
    """The bodies' levels one after the other: ``(tets, surfaces, P, reports)`` of the stacked hierarchy
    (level 0 the caller's ``(V, T)``; past its own levels a body repeats its coarsest, by the identity)."""
    import scipy.sparse as sp

    from .prolongation import ProlongationReport

    n_levels = max(h.levels for h in hs)

    def at(h, k):  # a body's level k, its coarsest past its own levels
        return min(k, h.levels - 1)

    tets = [(V, T)] + [merge_meshes([h.tets[at(h, k)] for h in hs])[:2] for k in range(1, n_levels)]
    surfaces = [merge_meshes([h.surfaces[at(h, k)] for h in hs])[:2] for k in range(n_levels)]
    P, reports = [], []
    for k in range(n_levels - 1):
        Pk = sp.block_diag([h.P[k] if k < h.levels - 1 else sp.identity(len(h.tets[at(h, k)][0]), format="csr")
                            for h in hs], format="csr")
        if k == 0:  # rows in the caller's node order
            Pk = Pk[np.argsort(np.concatenate(bodies))]
        P.append(sp.csr_matrix(Pk))
        reps = [h.prolongation_reports[k] for h in hs if k < h.levels - 1]
        reports.append(ProlongationReport(
            n_fine=Pk.shape[0], n_coarse=Pk.shape[1], n_outside=sum(r.n_outside for r in reps),
            n_on_boundary=sum(r.n_on_boundary for r in reps), max_distance=max(r.max_distance for r in reps),
            max_distance_rel=max(r.max_distance_rel for r in reps), extrapolation=reps[0].extrapolation,
            seconds=sum(r.seconds for r in reps)))
    return tets, surfaces, P, reports
