"""Cage backend ``"lazy"``: loose but cheap enclosing cages (Sellán et al.'s "lazy cage").

For one layer with target ``m`` faces around a fine surface ``S`` (:func:`lazy_cage_layer`):

1. offset ``S`` outward by ``d`` (marching cubes of the signed distance on a ``grid_size``-cell
   grid, ``gpytoolbox.offset_surface``);
2. decimate the offset surface to ``m`` faces (``gpytoolbox.decimate``, libigl's collapses);
3. "self-union" the result to resolve self-intersections the collapses made
   (``gpytoolbox.copyleft.mesh_boolean``, CGAL -- the GPL part);
4. binary search on ``d`` in ``[0, d_max]`` (``d_max`` = half the largest bounding-box extent of ``S``)
   for ``max_iter`` steps, keeping the smallest ``d`` whose candidate passes the acceptance test.

gpytoolbox's own ``copyleft.lazy_cage`` accepts a candidate when it does not cross ``S``. Here the
acceptance test is nestmg's certification of the pair (closed manifold cage, positive volume, no
self-intersection, no crossing or touching, every fine vertex inside, no cage vertex inside ``S``:
:func:`cagegen.verify_nesting`), so a returned layer is always certified; when no step of the search
is accepted, ``d`` is doubled past ``d_max`` a few times before :class:`cagegen.CageError` is raised.

Clearance (``gap`` / the backend's ``min_gap``): the offset is ``d`` *before* decimation, and the
collapses cut back towards ``S`` (a ``d = 0.02`` offset of gargo decimated to 1.3k faces came within
3e-4 of it), so ``d`` alone does not keep a clearance. With ``gap > 0`` a nested candidate closer than
``gap`` is moved out by the missing clearance with :func:`cagegen.nested.backend.push_out` (offset of
the cage along its normals where it is too close, a straight path cut by ipctk's CCD: it meets
neither itself nor ``S`` on the way), then re-checked by the same rule and accepted only at distance
``>= gap``; a candidate whose push is blocked is rejected, so the search moves to a larger ``d``.

The cage may have a different genus from ``S`` (the offset closes handles thinner than ``2 d``):
that is reported per layer (``genus_fine``, ``genus``, ``genus_changed``), never hidden.

``build_cages(V, F, levels=K, method="lazy")`` applies :func:`lazy_cage_layer` to the previous layer
for each coarser layer, at the face counts of :func:`cagegen.default_face_counts` like the other
backends, with the clearance ``min_gap`` that :func:`cagegen.build_cages` passes (relative to the
input's bounding-box diagonal, the verifier's unit; nestmg's pipeline asks ``2.5 epsilon`` under
TetWild). :func:`lazy_cage_layer` is also the recovery hook of the ``nested`` backend (one layer,
``(V, F, info)`` out; its ``gap`` is absolute).

License: gpytoolbox's ``copyleft`` module is GPL-3; this module imports it and is only loaded when
``method="lazy"`` is requested (the ``lazy`` extra). Importing it without gpytoolbox raises
:class:`cagegen.BackendUnavailableError`.
"""

from __future__ import annotations

import time

import numpy as np

from .._geometry import (
    as_mesh_arrays,
    bbox_diagonal,
    cross_intersection_pairs,
    edge_stats,
    n_components,
    self_intersection_pairs,
)
from .._geometry import signed_volume as _signed_volume
from ..errors import BackendUnavailableError, CageError, CageOptionError
from ..verify import WINDING_THRESHOLD

try:  # optional GPL dependency: fail at import time with an actionable message
    from gpytoolbox import decimate as _gp_decimate
    from gpytoolbox import offset_surface as _gp_offset_surface
    from gpytoolbox.copyleft import mesh_boolean as _gp_mesh_boolean
except ImportError as _exc:  # pragma: no cover - exercised by a test that hides gpytoolbox
    raise BackendUnavailableError(
        "the 'lazy' cage backend needs gpytoolbox (GPL-3, its copyleft.mesh_boolean): "
        "pip install 'nestmg[lazy]'  (or: pip install gpytoolbox)"
        f" [import failed: {_exc}]"
    ) from _exc

__all__ = ["genus", "lazy_layer", "lazy_cage_layer"]

#: how many times ``d`` is doubled beyond ``d_max`` when no step of the binary search is accepted
_MAX_GROW = 3


def genus(V: np.ndarray, F: np.ndarray) -> int | None:
    """Total genus of a closed manifold triangle mesh (sum over its components).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array

    Returns
    -------
    int or None
        ``(2 c - χ) / 2`` with ``χ = V - E + F`` over referenced vertices and ``c`` components;
        None when the mesh is not a closed manifold.

    Examples
    --------
    >>> import trimesh
    >>> t = trimesh.creation.torus(1.0, 0.3)
    >>> genus(t.vertices, t.faces)
    1
    """
    F = np.asarray(F, dtype=np.int64)
    es = edge_stats(F, len(V))
    if es.n_boundary_edges or es.n_nonmanifold_edges:
        return None
    chi = np.unique(F).size - es.n_edges + F.shape[0]
    c = n_components(F, len(V))
    return int((2 * c - chi) // 2)


def _candidate(V, F32, d, n_faces, grid_size, decimator, self_union):
    """Offset by ``d``, decimate to ``n_faces``, self-union. Returns (U, G) or raises CageError (a RuntimeError)."""
    Uo, Go = _gp_offset_surface(V, F32, float(d), int(grid_size))
    if len(Go) == 0:
        raise CageError("empty offset surface")
    if len(Go) > n_faces:
        U, G, _, _ = _gp_decimate(np.asarray(Uo, float), np.asarray(Go, np.int32), num_faces=int(n_faces),
                                  method=decimator)
    else:  # the offset surface is already coarser than the target (tiny grid)
        U, G = Uo, Go
    if self_union:
        U, G = _gp_mesh_boolean(np.asarray(U, float), np.asarray(G, np.int32), np.asarray(U, float),
                                np.asarray(G, np.int32), boolean_type="union")
    U = np.ascontiguousarray(U, dtype=np.float64)
    G = np.ascontiguousarray(G, dtype=np.int64)
    if len(G) == 0:
        raise CageError("empty cage after decimation / self-union")
    used = np.unique(G)  # drop unreferenced vertices left by the collapses or the boolean
    if used.size != len(U):
        remap = np.full(len(U), -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        U, G = U[used], remap[G]
    return U, G


def _accept(V, F, U, G) -> str:
    """Empty string when ``(U, G)`` nests ``(V, F)`` by the verifier's rule; otherwise the reason.

    The rule of :func:`cagegen.verify_nesting` (closed oriented manifold, positive volume, no
    crossing or touching, fine vertices inside, no cage vertex inside, no self-intersection), cheapest
    test first and without the gap figures, which the search does not need.
    """
    import igl

    es = edge_stats(G, len(U))
    if es.n_boundary_edges or es.n_nonmanifold_edges or es.n_inconsistent_edges:
        return (f"cage not a closed oriented manifold ({es.n_boundary_edges} boundary, {es.n_nonmanifold_edges} "
                f"non-manifold, {es.n_inconsistent_edges} inconsistent edges)")
    if _signed_volume(U, G) <= 0:
        return "cage is inside-out or flat"
    k = len(cross_intersection_pairs(V, F, U, G))
    if k:
        return f"cage intersects the fine layer ({k} intersecting or touching triangle pairs)"
    w = igl.winding_number(U, G, V)
    n_out = int(np.count_nonzero(w < WINDING_THRESHOLD))
    if n_out:
        return f"{n_out} fine vertices outside the cage"
    n_in = int(np.count_nonzero(igl.winding_number(V, F, U) >= WINDING_THRESHOLD))
    if n_in:
        return f"{n_in} cage vertices inside the fine layer"
    k = len(self_intersection_pairs(U, G))
    return f"cage self-intersects ({k} face pairs)" if k else ""


def _distance_lower_bound(U, G, V, F) -> float:
    """A lower bound on the distance between the surfaces ``(U, G)`` and ``(V, F)`` (disjoint, nested).

    Every point of a triangle ``t`` of ``G`` is within ``t``'s longest edge ``L_t`` of a vertex of ``t``, so
    the distance is at least ``min_t (min_{v in t} d(v, F) - L_t)``. Cheap (one AABB query per cage
    vertex); lets a candidate far from ``(V, F)`` skip the exact distance, whose search costs seconds
    when the surfaces are far apart.
    """
    import igl

    d2, _, _ = igl.point_mesh_squared_distance(U, V, F)
    E = U[G[:, [1, 2, 0]]] - U[G]
    longest = np.linalg.norm(E, axis=2).max(axis=1)
    return float((np.sqrt(d2)[G].min(axis=1) - longest).min())


def _keep_clearance(V, F, U, G, gap: float) -> tuple[np.ndarray, str, dict]:
    """A nested candidate moved out to distance ``>= gap`` from ``(V, F)`` (reason "" when it is).

    A candidate whose :func:`_distance_lower_bound` is already ``>= gap`` is kept as it is; otherwise
    :func:`cagegen.nested.backend.push_out` (exact distance, CCD-safe offset by the missing clearance;
    a no-op when the candidate keeps ``gap``) moves it, and a moved cage is re-checked by :func:`_accept`.
    """
    lb = _distance_lower_bound(U, G, V, F)
    if lb >= gap:
        return U, "", {"distance_lower_bound": lb, "passes": 0}
    from ..nested.backend import push_out  # MIT, ipctk; loaded only when a clearance is asked

    U2, pinfo = push_out(U, G, V, F, float(gap))
    clear = {"distance_before": float(pinfo["distance_before"]), "distance": float(pinfo["distance"]),
             "passes": int(pinfo["passes"])}
    if U2 is None:
        return U, (f"closer than the clearance ({clear['distance_before']:.3g} < {gap:.3g}) and the push-out "
                   f"failed: {pinfo['reason']}"), clear
    reason = _accept(V, F, U2, G) if clear["passes"] else ""
    return U2, reason, clear


def lazy_cage_layer(
    V,
    F,
    n_faces: int,
    *,
    gap: float = 0.0,
    grid_size: int = 50,
    max_iter: int = 10,
    decimator: str = "shortest_edge",
    self_union: bool = True,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """One certified enclosing cage of about ``n_faces`` faces around the closed surface ``(V, F)``.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
        Closed, outward-oriented, self-intersection-free surface (not modified).
    n_faces : int
        Target face count of the cage (>= 4). The self-union may change it by a few faces.
    gap : float
        Clearance (absolute, ``V``'s units) the cage must keep from ``(V, F)``: a candidate closer than
        that is pushed out (:func:`_keep_clearance`) and accepted only at distance ``>= gap``. 0: none.
    grid_size : int
        Cells along the longest side of the signed-distance grid (>= 8); finer grids give tighter
        cages (the offset cannot be much thinner than one cell) at a cubic cost.
    max_iter : int
        Binary-search steps on the offset distance (>= 1); each halves the uncertainty on ``d``.
    decimator : {"shortest_edge", "qslim"}
        gpytoolbox's decimator (libigl's ``decimate`` or ``qslim``).
    self_union : bool
        Resolve self-intersections of the decimated offset with a CGAL self-union (GPL). Without it,
        self-intersecting candidates are simply rejected by the acceptance test.

    Returns
    -------
    U : (p,3) float64 array
    G : (q,3) int64 array
        The cage: certified to strictly contain ``(V, F)``.
    info : dict
        JSON-serialisable: ``target``, ``n_faces``, ``n_vertices``, ``offset`` (absolute ``d``),
        ``offset_relative`` (``d`` / bounding-box diagonal of ``(V, F)``), ``genus_fine``, ``genus``,
        ``genus_changed``, ``components``, ``volume_ratio`` (cage / fine), ``iterations`` (per step:
        ``d_relative``, ``accepted``, ``reason``, ``seconds``, and with ``gap > 0`` the candidate's
        ``distance_before`` / ``distance`` or ``distance_lower_bound``, and push-out ``passes``),
        ``seconds``; with ``gap > 0`` also ``gap`` (asked, absolute), ``distance`` (achieved, absolute;
        None when the cage was far enough by ``distance_lower_bound`` not to need the exact figure) and
        ``pushed`` (push-out passes).

    Raises
    ------
    cagegen.MeshInputError
        Malformed arrays.
    ValueError
        Bad option values.
    cagegen.CageError
        No certified cage was found (the message lists the reasons of the last attempts).

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(subdivisions=3)
    >>> U, G, info = lazy_cage_layer(s.vertices, s.faces, 200, grid_size=24, max_iter=4)
    >>> info["n_faces"] <= 220, info["genus"], 1.0 < info["volume_ratio"] < 2.5
    (True, 0, True)
    """
    V, F = as_mesh_arrays(V, F, "fine layer")
    if isinstance(n_faces, (bool, np.bool_)) or int(n_faces) != n_faces or int(n_faces) < 4:
        raise CageOptionError(f"n_faces must be an integer >= 4, got {n_faces!r}")
    if isinstance(grid_size, (bool, np.bool_)) or int(grid_size) != grid_size or int(grid_size) < 8:
        raise CageOptionError(f"grid_size must be an integer >= 8, got {grid_size!r}")
    if isinstance(max_iter, (bool, np.bool_)) or int(max_iter) != max_iter or int(max_iter) < 1:
        raise CageOptionError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    if decimator not in ("shortest_edge", "qslim"):
        raise CageOptionError(f"decimator must be 'shortest_edge' or 'qslim', got {decimator!r}")
    if isinstance(gap, (bool, np.bool_)) or not (np.isfinite(gap) and gap >= 0):
        raise CageOptionError(f"gap must be a finite number >= 0, got {gap!r}")
    n_faces, gap = int(n_faces), float(gap)
    t0 = time.perf_counter()
    diag = bbox_diagonal(V)
    F32 = F.astype(np.int32)
    lo, hi = 0.0, 0.5 * float(np.max(V.max(axis=0) - V.min(axis=0)))
    best: tuple[np.ndarray, np.ndarray, float, dict] | None = None
    steps: list[dict] = []

    def attempt(d: float) -> bool:
        nonlocal best
        t = time.perf_counter()
        clear: dict = {}
        try:
            U, G = _candidate(V, F32, d, n_faces, grid_size, decimator, self_union)
            reason = _accept(V, F, U, G)
            if not reason and gap > 0:
                U, reason, clear = _keep_clearance(V, F, U, G, gap)
        except (RuntimeError, ValueError) as exc:  # gpytoolbox / CGAL failures on a candidate
            U = G = None
            reason = f"candidate failed: {exc}"
        ok = not reason
        if ok:
            best = (U, G, d, clear)
        steps.append({"d_relative": d / diag, "accepted": ok, "reason": reason,
                      "seconds": time.perf_counter() - t, **clear})
        return ok

    for _ in range(int(max_iter)):
        d = 0.5 * (lo + hi)
        if attempt(d):
            hi = d
        else:
            lo = d
    d = hi
    grow = 0
    while best is None and grow < _MAX_GROW:
        d *= 2.0
        grow += 1
        attempt(d)
    if best is None:
        last = "; ".join(f"d={s['d_relative']:.3g}: {s['reason']}" for s in steps[-3:])
        raise CageError(f"lazy cage with {n_faces} faces: no certified candidate in {len(steps)} attempts ({last})",
                        reason=steps[-1]["reason"])
    U, G, d, clear = best
    g_fine, g_cage = genus(V, F), genus(U, G)
    info = {
        "target": n_faces,
        "n_faces": len(G),
        "n_vertices": len(U),
        "offset": float(d),
        "offset_relative": float(d / diag),
        "grid_size": int(grid_size),
        "max_iter": int(max_iter),
        "decimator": decimator,
        "self_union": bool(self_union),
        "genus_fine": g_fine,
        "genus": g_cage,
        "genus_changed": bool(g_fine != g_cage),
        "components": n_components(G, len(U)),
        "volume_ratio": _signed_volume(U, G) / _signed_volume(V, F),
        "iterations": steps,
        "seconds": time.perf_counter() - t0,
    }
    if gap > 0:
        info.update(gap=gap, distance=clear.get("distance"),
                    distance_lower_bound=clear.get("distance_lower_bound"), pushed=clear["passes"])
    return U, G, info


def lazy_layer(
    V: np.ndarray,
    F: np.ndarray,
    n_faces: int,
    *,
    unit: float,
    min_gap: float = 0.0,
    grid_size: int = 50,
    max_iter: int = 10,
    decimator: str = "shortest_edge",
    self_union: bool = True,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-layer function of the ``"lazy"`` backend: a lazy cage of ``(V, F)`` (nested, loose).

    :func:`cagegen.build_cages` loops over the layers (registry contract, :mod:`cagegen.registry`).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        The previous layer (the audited input for the first cage).
    n_faces : int
        Target face count.
    unit : float
        The input's bounding-box diagonal: ``min_gap`` is relative to it on every layer.
    min_gap : float
        Clearance from ``(V, F)`` relative to ``unit`` (the unit of :func:`cagegen.verify_nesting`'s
        ``min_gap``, which :func:`cagegen.build_cages` passes here): the cage keeps ``min_gap * unit``.
    grid_size, max_iter, decimator, self_union
        See :func:`lazy_cage_layer`.

    Returns
    -------
    U, G : arrays
        The cage, ``U`` (p,3) float64, ``G`` (q,3) int64.
    info : dict
        :func:`lazy_cage_layer`'s info plus ``progress`` (the detail of the layer's progress line).
    """
    V = np.array(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64)
    gap = float(min_gap) * float(unit)
    if not (np.isfinite(gap) and gap >= 0):
        raise CageOptionError(f"min_gap must be a finite number >= 0, got {min_gap!r}")
    U, G, li = lazy_cage_layer(V, F, int(n_faces), gap=gap, grid_size=grid_size, max_iter=max_iter,
                               decimator=decimator, self_union=self_union)
    c = ""
    if gap > 0:
        got = (f"{li['distance'] / unit:.3g}" if li["distance"] is not None
               else f"> {li['distance_lower_bound'] / unit:.3g}")
        pushed = f" (pushed out, {li['pushed']} passes)" if li["pushed"] else ""
        c = f", gap {got} >= min_gap {gap / unit:.3g}{pushed}"
    li["progress"] = f"offset {li['offset_relative']:.3g} of the diagonal{c}"
    return U, G, li
