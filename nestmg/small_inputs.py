"""Inputs too small for a cage: every level from one coarse tet mesh of the input, by red refinement.

A cage keeps at least :data:`cagegen.sizes.MIN_FACES` faces and the default cages have 4x fewer faces per
level, so an input of fewer than ``4 * MIN_FACES`` faces (a CAD box of 12 triangles, a 128-face cylinder)
has no cage level. Its surface is already coarse, so no coarser surface is needed: the input is meshed once
at ``2**(L-1)`` times the fine edge and each finer level is the red refinement of the next coarser one
(:func:`nestmg.refine.refine_tets`). The levels are then exactly nested (every prolongation is exact,
``n_outside = 0``) and share the input's surface; the hierarchy is certified by construction.

The number of levels is ``levels`` (a ceiling) unless the refined fine level would exceed twice the tet cap
(``max_tets``, default 1.5M) -- TetWild refines a thin or sharp input beyond the planned edge --, then one
stage line says how many levels were kept.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["cage_fits", "refinement_hierarchy"]


def cage_fits(n_faces: int) -> bool:
    """Whether one default cage (4x fewer faces, at least ``MIN_FACES``) fits an input of ``n_faces``."""
    from cagegen.sizes import MIN_FACES, fitting_levels

    return n_faces >= 4 and fitting_levels(int(n_faces), 2, 4.0, MIN_FACES) >= 2


def refinement_hierarchy(V, F, Vn, frame, levels: int, method: str, *, sizing, meshing, cages, cache: bool,
                         progress, t0: float, solid=None, voids: dict | None = None):
    """The hierarchy of an input with no cage level (module docstring).

    Parameters
    ----------
    V, F
        The input (user coordinates) and ``Vn`` its normalised vertices; ``frame`` ``(center, scale)``.
    levels, method, sizing, meshing, cages, cache, progress
        As for :func:`nestmg.build_hierarchy` (``method`` is recorded; no cage is built).
    t0 : float
        Start of the run (stage lines).
    solid : dict, optional
        The repair's record when ``V, F`` is a repaired input.
    voids : dict, optional
        ``V, F`` is a solid with voids (:func:`nestmg.hierarchy._voids`, voids audited): the outer surface is
        audited, the whole surface meshed.

    Returns
    -------
    Hierarchy
    """
    import cagegen
    from cagegen.sizes import MIN_FACES

    from .hierarchy import Hierarchy, _refined_fine_level, tet_hierarchy
    from .options import as_dict
    from .progress import Timer, stage_line
    from .sizing import DEFAULT_MAX_TETS, plan_hierarchy

    center, scale = frame
    F_in = F
    if voids is None:
        Vn, F = cagegen.check_mesh(Vn, F, repair=bool(getattr(cages, "repair", False)), name="input")
    else:  # the voids were audited one by one; the outer surface here, the whole surface is meshed
        cagegen.check_mesh((voids["outer"][0] - center) / scale, voids["outer"][1], name="input (outer surface)")
    same = F.shape == F_in.shape and np.array_equal(F, F_in)  # not repaired: level 0's surface is the caller's
    n_ref = levels - 1  # refinements: level L-1 is meshed, levels L-2 .. 0 are refined
    plan = plan_hierarchy(Vn, F, levels, mesher=meshing.mesher, edge_length=sizing.edge_length,
                          max_tets=sizing.max_tets, mesh_time_budget=sizing.mesh_time_budget,
                          # the fine edge as the pipeline's (the mesher's edge at 2x it at most the input's
                          # resolution), the mesher's work that of the coarsest level
                          meshed_fraction=8.0**-n_ref, mesh_edge_factor=2.0, fixed_levels=levels - 2)
    stage_line(f"levels: no cage fits {len(F):,} faces (a cage keeps >= {MIN_FACES}); the coarsest level is the "
               f"input meshed at {2**n_ref}x the fine edge {plan.edge_length:.3g}, every finer level the red "
               f"refinement of the next (exactly nested)", t0)
    timer = Timer()
    tets_n, Ps, reps, tt = tet_hierarchy([(Vn, F)], sizing=sizing, meshing=meshing,
                                         edge_length_abs=plan.edge_length * 2.0**n_ref, cache=cache,
                                         progress=progress, t0=t0)
    cap = 2 * (sizing.max_tets or DEFAULT_MAX_TETS)
    while n_ref > 1 and len(tets_n[0][1]) * 8**n_ref > cap:
        n_ref -= 1
    if n_ref < levels - 1:
        stage_line(f"levels: {n_ref + 1} of the {levels} asked (the mesher made {len(tets_n[0][1]):,} coarse tets; "
                   f"{n_ref + 1} refinements would exceed {cap:,} fine tets)", t0)
    surfaces_n = [(Vn, F)]
    for _ in range(n_ref):
        tets_n, Ps, reps, surfaces_n = _refined_fine_level(tets_n, Ps, reps, surfaces_n, tt, plan, timer, t0)
    info = {"coarse_levels": "refinement", "verification": {"ok": True, "by": "refinement: exactly nested"},
            "frame": {"center": np.asarray(center).tolist(), "scale": scale}}
    if solid is not None:
        info["solid"] = solid
    h = Hierarchy(
        surfaces=[(V, F) if same else (Vn * scale + center, F)] * len(tets_n),
        tets=[(Vt * scale + center, T) for Vt, T in tets_n], P=Ps, prolongation_reports=reps, method=method,
        cage_info=info, timings={**timer.seconds, **tt, "total": time.perf_counter() - t0},
        options={"levels": len(tets_n), "levels_requested": levels, "fine_level": "refine",
                 "coarse_levels": "refinement", "sizing": as_dict(sizing), "meshing": as_dict(meshing),
                 "cages": as_dict(cages), "plan": plan.to_dict()},
        frame={"center": center, "scale": scale},
    )
    stage_line(f"hierarchy: tets {[len(T) for _, T in h.tets]}, n_outside {h.n_outside}, certified {h.certified}",
               t0)
    return h
