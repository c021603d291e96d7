"""The ``"skeleton"`` cage backend: Casti et al. (2019), skeleton-based cages guided by a harmonic field.

Steps (each timed in ``info["seconds"]``, each failure raised as a :class:`CageError` naming it):

1. ``skeleton``: the user's skeleton (:class:`Skeleton`, a ``.skel`` file, or ``(nodes, edges)``), or
   automatic extraction (:func:`cagegen.skeleton.extract.extract_skeleton`, needs ``pygel3d``).
2. ``bending``: the user's bending nodes, or automatic ones where the thickness changes (Sec. 4).
3. ``field``: TetWild mesh + harmonic field f (0 on the skeleton, 1 on M; Sec. 3.1).
4. ``sections``: one quad per control node (leaf or bending) from integral lines of ∇f (Sec. 3.3),
   moved along the chain or dropped when the lines do not reach M; optionally mirror-symmetrised
   (Sec. 3.4, :mod:`cagegen.skeleton.symmetry`).
5. ``assembly``: tubes, junction hulls (with Steiner vertices, Sec. 3.3), leaf caps -> closed tight
   cage with its vertices on M; junction sections moved away / dropped / shrunk and self-intersecting
   tight cages repaired by shrinking or dropping sections (ours, recorded in ``info``).
6. ``pre_inflation``: along the integral lines (Sec. 3.5), then a containment push.
7. ``containment`` (timed as ``inflation``): M swept down the guiding field's level sets and re-inflated,
   pushing the cage out (:mod:`cagegen.skeleton.contain`, issue 29; ``containment="flow"``: the
   ``nested`` backend's flow + re-inflation), then the clearance (``push_out``) and certification by
   :func:`cagegen.verify_nesting`.

Everything runs on a copy scaled to a unit bounding-box diagonal; the cage is returned in the
caller's coordinates.

What the options of :func:`skeleton_cage` do when a step meets a hard case (ours, not the paper's;
defaults in :class:`cagegen.SkeletonOptions`):

* ``drop_bad_sections``: when a junction's convex hull misses an edge of an incident bending section
  (the paper fixes this with Steiner vertices, not implemented), drop that bending node and use the
  next section along its chain (``info["junction_recovery"]``); also, when the tight cage intersects
  itself and shrinking the offending sections does not help, drop the bending node with most
  intersecting faces and rebuild (``info["assembly_dropped"]``). False: raise.
* ``relocate_sections``: when fewer than 4 integral lines of a section reach M (thin parts), move the
  section along its chain (bending nodes: up to one inscribed radius either way; leaves: inwards, up
  to half the chain), then drop a bending node whose chain keeps another section
  (``info["sections_moved"]``, ``info["sections_dropped"]``). False: raise.
* ``symmetry`` (paper Sec. 3.4): ``"auto"`` detects a mirror plane
  (:func:`cagegen.skeleton.symmetry.detect_mirror_plane`) and, if found, symmetrises the sections
  (:func:`~cagegen.skeleton.symmetry.symmetrize_sections`); a (point, normal) pair (caller's
  coordinates) imposes that plane. The tight cage is then symmetric unless the assembly had to shrink
  or drop sections; the final inflation does not enforce it (``info["symmetry"]``).
* ``untangle``: before each assembly, flatten a degenerate section (two corners closer than 0.25 x its
  inscribed radius) or a section that crosses its neighbour along the chain onto the plane orthogonal
  to the skeleton (:func:`cagegen.skeleton.cage.untangle_sections`; ``info["sections_flattened"]``).
  False: leave such folds to the recoveries (dropping bending nodes).
* ``containment`` (step 7): ``"mesh"`` (default) sweeps M down the guiding field's level sets,
  collapses it onto the skeleton nodes inside the pre-inflated cage and re-inflates it to rest pushing
  the cage out (IPC barrier + CCD; :mod:`cagegen.skeleton.contain`), then makes the clearance by
  :func:`cagegen.nested.backend.push_out` (or, when blocked, a re-inflation of M to its offset); no
  flow, so no stall. ``"flow"``: the paper's route, the Nested Cages flow + re-inflation after the full
  pre-inflation (stalls on most zoo characters); ``**nested_opts`` then go to
  :func:`cagegen.nested.backend.nest_pair` (defaults here: ``flow_max_iter=2000``,
  ``flow_stall_window=200``, ``flow_active_depth=0.01``, the local flow; ``None``: the paper's flow).
* ``skeleton_cache``: cache of automatically extracted skeletons
  (:func:`cagegen.skeleton.extract.extract_skeleton`'s ``cache``): None, ``$NESTMG_CACHE/skeleton``;
  False, none (then PyGEL3D's extraction may give a different skeleton, hence a different cage, on
  every call). Unused with a given skeleton.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from .._geometry import normalize
from ..errors import CageError, CageOptionError, CageTypeError, MeshInputError
from ..verify import verify_nesting
from .cage import (JunctionError, auto_bending_nodes, cross_section, inscribed_radius, tight_cage,
                   untangle_sections)
from .field import GuidingField
from .graph import Skeleton, read_skeleton
from .inflate import pre_inflate

__all__ = ["SkeletonCage", "skeleton_backend", "skeleton_cage"]


class SkeletonCage:
    """Result of :func:`skeleton_cage` (all arrays in the caller's coordinates).

    Attributes
    ----------
    V : (n,3) float array
        Certified cage vertices.
    F : (m,3) int array
        Cage triangles (outward): the quads split along their recorded diagonal, plus junction triangles.
    quads : (q,4) int array
        The quad faces (tube sides and leaf caps), same vertices; their triangulation is ``F[:2q]``.
    tris : (t,3) int array
        The junction triangles.
    tight_V : (n,3) float array
        The tight cage before inflation (vertices on M).
    skeleton : Skeleton
        The skeleton used (resampled when bending nodes were placed automatically).
    sections : list of dict
        Per control node: ``node``, ``center``, ``quad`` (4,3), ``hits`` (integral-line ends).
    info : dict
        JSON-serialisable figures (seconds per step, counts, verification).
    certified : bool
        True for a returned cage. A :class:`CageError` of the assembly step or a later one carries what
        was built as ``exc.partial``: ``certified=False`` and ``V`` the pre-inflated cage (it does *not*
        contain the mesh), with the skeleton, sections and tight cage, for pictures; from the assembly,
        ``V`` is the self-intersecting tight cage, or None (skeleton and sections only) when a junction
        hull could not be built.
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def write_obj(self, path: str | os.PathLike, quads: bool = True, overwrite: bool = False) -> None:
        """Write the cage as OBJ: quads + junction triangles (``quads=True``) or the certified triangles.

        Raises
        ------
        FileExistsError
            ``path`` exists and ``overwrite`` is False.
        """
        if os.path.exists(path) and not overwrite:
            raise FileExistsError(f"{path} exists (pass overwrite=True to replace it)")
        faces = ([list(q) for q in self.quads] + [list(t) for t in self.tris]) if quads else self.F.tolist()
        with open(path, "w", encoding="utf-8") as fh:
            fh.write("# nestmg skeleton cage (Casti et al. 2019); quads split along the shorter diagonal "
                     "before inflation are certified\n")
            fh.writelines(f"v {p[0]:.17g} {p[1]:.17g} {p[2]:.17g}\n" for p in self.V)
            fh.writelines("f " + " ".join(str(int(i) + 1) for i in f) + "\n" for f in faces)


def _as_skeleton(skeleton) -> Skeleton:
    if isinstance(skeleton, Skeleton):
        return Skeleton(skeleton.nodes.copy(), skeleton.edges.copy(), list(skeleton.bending))
    if isinstance(skeleton, (str, os.PathLike)):
        return read_skeleton(skeleton)
    if isinstance(skeleton, (tuple, list)) and len(skeleton) in (2, 3):
        return Skeleton(*skeleton)
    raise CageTypeError("skeleton must be a Skeleton, a path to a .skel file, or (nodes, edges[, bending])")


def _tangent(S: Skeleton, chain, i: int, reach: float) -> np.ndarray:
    """Unit direction of the chain at its i-th node, from the points ``reach`` before and after it."""
    X = S.nodes[np.asarray(chain.nodes)]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]
    a = np.array([np.interp(max(s[i] - reach, 0.0), s, X[:, k]) for k in range(3)])
    b = np.array([np.interp(min(s[i] + reach, s[-1]), s, X[:, k]) for k in range(3)])
    t = b - a
    return t / np.linalg.norm(t)


def _section_positions(S: Skeleton, chain, i: int, radius: float, leaf):
    """Chain indices to try for the section of the chain's i-th node: i first, then (``leaf`` False)
    alternately farther on both sides up to ``radius`` of arc length, or (``leaf`` True) inwards up to
    half the chain; ``leaf`` None: only i."""
    yield i
    if leaf is None:
        return
    X = S.nodes[np.asarray(chain.nodes)]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]
    n = len(chain.nodes)
    if leaf:
        step = 1 if i == 0 else -1
        j = i + step
        while 0 < j < n - 1 and abs(s[j] - s[i]) <= 0.5 * s[-1]:
            yield j
            j += step
        return
    for k in range(1, n):
        for j in (i - k, i + k):
            if 0 < j < n - 1 and abs(s[j] - s[i]) <= radius:
                yield j
        if abs(s[min(i + k, n - 1)] - s[i]) > radius and abs(s[max(i - k, 0)] - s[i]) > radius:
            return


def skeleton_cage(
    V: np.ndarray, F: np.ndarray, skeleton=None, *, bending="auto", n_seeds: int = 20,
    seed_radius: float = 0.2, tet_edge_length: float | None = None, preinflate_rounds: int = 3,
    drop_bad_sections: bool = True,
    relocate_sections: bool = True, symmetry=None, min_gap: float = 0.0, certify: bool = True,
    inner: tuple | None = None, progress=None, skeleton_cache=None, untangle: bool = True,
    containment: str = "mesh", **nested_opts,
) -> SkeletonCage:
    """Build a certified skeleton cage around the closed surface ``(V, F)`` (Casti et al. 2019).

    The steps, and what ``drop_bad_sections``, ``relocate_sections``, ``symmetry``, ``untangle``,
    ``containment`` and ``skeleton_cache`` do, are described in this module's docstring.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, outward-oriented, self-intersection-free surface M (not modified).
    skeleton : Skeleton, path, (nodes, edges[, bending]) or None
        Curve skeleton inside M, a tree (format: :mod:`cagegen.skeleton.graph`). None: extract one
        automatically (needs ``pygel3d``, MIT).
    bending : "auto", "given" or sequence of int
        ``"auto"``: the skeleton's own bending nodes plus automatic ones (Sec. 4); ``"given"``: only the
        skeleton's own; a sequence: these node indices (of the input skeleton).
    n_seeds, seed_radius : int, float
        Seeds per section and their circle radius as a fraction of the inscribed radius (paper: 20, 0.2).
    tet_edge_length : float, optional
        Edge length of the guiding field's tet mesh, fraction of the bounding-box diagonal (default:
        half the smallest inscribed radius at a control node, clamped to [0.015, 0.03]).
    preinflate_rounds : int
        Pre-inflation rounds (paper: 1).
    drop_bad_sections, relocate_sections, untangle : bool
        Recoveries of the sections and the assembly (False: raise, or leave folds to the recoveries).
    symmetry : None, "auto" or (point, normal)
        Mirror symmetry of the sections (paper Sec. 3.4).
    min_gap : float
        Clearance demanded between M and the cage, relative to M's bounding-box diagonal.
    certify : bool
        Run :func:`cagegen.verify_nesting` (a failing cage raises :class:`CageError`).
    inner : (Vi, Fi), optional
        A surface between M and the cage (e.g. the coarsest ``nested`` layer of a hierarchy): the
        final inflation and the certification are done around it instead of M.
    progress : callable, optional
        ``progress(message)`` at each step.
    skeleton_cache : None, False or path
        Cache of automatically extracted skeletons (None: ``$NESTMG_CACHE/skeleton``; False: none).
    containment : {"mesh", "flow"}
        How the cage is made to contain M (step 7): M swept down the guiding field and re-inflated, or
        the Nested Cages flow (``**nested_opts`` go to :func:`cagegen.nested.backend.nest_pair`).

    Returns
    -------
    SkeletonCage

    Raises
    ------
    MeshInputError
        Bad skeleton (not a tree, nodes outside M, ...).
    CageError
        A step failed; the message starts with the step's name. From the assembly on, ``exc.partial``
        holds what was built (:class:`SkeletonCage`, ``certified=False``).
    """
    say = progress if callable(progress) else (lambda msg: None)
    t_all = time.perf_counter()
    if containment not in _CONTAINMENTS:
        raise CageOptionError(f"containment must be one of {_CONTAINMENTS}, got {containment!r}")
    sec: dict = {}
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    lo, hi = V.min(0), V.max(0)
    diag = float(np.linalg.norm(hi - lo))  # this backend's own measure (its cages depend on its bits)
    Vn, center, _ = normalize(V, diag)
    info: dict = {"method": "skeleton"}
    S, S_in = _timed(sec, "skeleton", _skeleton_step, Vn, F, skeleton, bending, diag, center, skeleton_cache,
                     info, say)
    S, chain_controls, spacing = _timed(sec, "bending", _bending_step, S, Vn, F, bending, info, say)
    field, rad_of = _timed(sec, "field", _field_step, S, chain_controls, Vn, F, tet_edge_length, info, say)
    t = time.perf_counter()
    kit = _SectionKit(S, S.degree, Vn, F, field, rad_of, spacing, n_seeds, seed_radius, say)
    sections, chain_controls = _sections_step(kit, chain_controls, relocate_sections, symmetry, center, diag,
                                              info)
    sec["sections"] = time.perf_counter() - t
    t = time.perf_counter()
    try:
        tc = _assembly_step(kit, sections, chain_controls, drop_bad_sections, untangle, info)
    except CageError as exc:
        sec["assembly"] = time.perf_counter() - t
        raise _assembly_failure(exc, {"S": S, "S_in": S_in, "sections": sections, "diag": diag,
                                      "center": center, "info": info, "sec": sec, "t_all": t_all}) from exc
    sec["assembly"] = time.perf_counter() - t
    Vp, Ft, Vt, quads_out, tris_out = _timed(sec, "pre_inflation", _pre_inflation_step, field, tc, Vn, F,
                                             preinflate_rounds, info, say, pushes=containment == "flow")
    # what was built, for the result and for the ``exc.partial`` of a later failure
    parts = {"S": S, "S_in": S_in, "sections": sections, "tc": tc, "Ft": Ft, "quads": quads_out,
             "tris": tris_out, "Vt": Vt, "Vp": Vp, "diag": diag, "center": center, "info": info, "sec": sec,
             "t_all": t_all}
    if info["pre_inflation"]["self_intersections"]:
        n_pairs = info["pre_inflation"]["self_intersections"]
        raise _failure(f"skeleton cage, pre-inflation: the cage intersects itself ({n_pairs} face pairs); "
                       "add bending nodes", parts)
    if containment == "flow":
        C = _timed(sec, "inflation", _inflation_step, parts, inner, Vn, F, min_gap, nested_opts)
    else:
        C = _timed(sec, "inflation", _sweep_step, parts, field, inner, Vn, F, min_gap, containment, say)
    Vc = C * diag + center
    Fc = np.ascontiguousarray(Ft, dtype=np.int64)
    t = time.perf_counter()
    if certify:
        _certification_step(parts, V, F, inner, Vc, Fc, min_gap)
    sec["verify"] = time.perf_counter() - t
    sec["total"] = time.perf_counter() - t_all
    info["seconds"] = sec
    info["n_vertices"], info["n_faces"] = len(Vc), len(Fc)
    info["n_quads"], info["n_junction_triangles"] = len(quads_out), len(tris_out)
    return _cage_result(Vc, True, parts)


def _timed(sec: dict, step: str, fn: Callable, *args, **kwargs):
    """``fn(*args, **kwargs)``, its wall seconds stored in ``sec[step]``."""
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    sec[step] = time.perf_counter() - t
    return out


class _SectionKit(NamedTuple):
    """What building a cross-section needs (steps 4 and 5 of :func:`skeleton_cage`), unit-diagonal frame."""

    S: Skeleton
    deg: np.ndarray
    Vn: np.ndarray
    F: np.ndarray
    field: GuidingField
    rad_of: dict
    spacing: float
    n_seeds: int
    seed_radius: float
    say: Callable


def _skeleton_step(Vn, F, skeleton, bending, diag, center, cache, info, say):
    """Step 1: the given skeleton (normalised) or an extracted one; its nodes must lie inside M."""
    if skeleton is None:
        from .extract import extract_skeleton

        say("skeleton: automatic extraction (pygel3d)")
        S, xinfo = extract_skeleton(Vn, F, cache=cache)
        say(f"skeleton: cache {xinfo['cache']}, digest {xinfo['skeleton_digest'][:12]}")
        info["extraction"] = xinfo
        S_in = S
    else:
        S_in = _as_skeleton(skeleton)
        S = S_in.transformed(1.0 / diag, center)
    if not isinstance(bending, str):
        S = S.with_bending(list(bending))
    elif bending not in ("auto", "given"):
        raise CageOptionError(f"bending must be 'auto', 'given' or a list of node indices, got {bending!r}")
    w = np.asarray(_winding(Vn, F, S.nodes))
    if np.any(w < 0.5):
        bad = np.flatnonzero(w < 0.5)
        raise MeshInputError(f"skeleton: {len(bad)} node(s) outside the surface (first: node {int(bad[0])}); "
                             "the skeleton must lie inside the mesh")
    return S, S_in


def _bending_step(S, Vn, F, bending, info, say):
    """Step 2: bending nodes (automatic or given) on the resampled skeleton; each chain's control nodes."""
    L_edges = np.linalg.norm(S.nodes[S.edges[:, 0]] - S.nodes[S.edges[:, 1]], axis=1)
    spacing = float(min(0.01, max(L_edges.mean() / 4, 0.002)))
    if bending == "auto":
        S, binfo = auto_bending_nodes(S, Vn, F, spacing)
        info["auto_bending"] = binfo
    else:
        S = S.resampled(spacing)  # original nodes keep their indices
    chains = S.chains()
    deg = S.degree
    chain_controls = []
    added = []
    bset = set(S.bending)
    for ch in chains:
        ctrl = [n for n in ch.nodes if n in bset or deg[n] == 1]
        if not ctrl:  # a chain between two branching nodes without a section: one at its middle
            X = S.nodes[np.asarray(ch.nodes)]
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]
            i = int(np.clip(np.argmin(np.abs(s - s[-1] / 2)), 1, len(ch.nodes) - 2))
            ctrl = [ch.nodes[i]]
            added.append(int(ch.nodes[i]))
        chain_controls.append((ch, ctrl))
    if added:
        S = S.with_bending(sorted(bset | set(added)))
    info["skeleton"] = {"n_nodes": len(S.nodes), "n_leaves": len(S.leaves), "n_branching": len(S.branching),
                        "n_bending": len(S.bending), "bending_added_mid_chain": added}
    say(f"skeleton: {len(S.leaves)} leaves, {len(S.branching)} branching, {len(S.bending)} bending nodes")
    return S, chain_controls, spacing


def _field_step(S, chain_controls, Vn, F, tet_edge_length, info, say):
    """Step 3: inscribed radii at the control nodes, the tet mesh and the harmonic guiding field."""
    ctrl_nodes = sorted({n for _, c in chain_controls for n in c})
    radii = inscribed_radius(S.nodes[ctrl_nodes], Vn, F)
    rad_of = dict(zip(ctrl_nodes, radii))
    h = tet_edge_length if tet_edge_length is not None else float(np.clip(0.5 * radii.min(), 0.015, 0.03))
    samples = S.resampled(h / 2).nodes
    say(f"field: delaunay tets (edge {h:.3g}) + harmonic solve")
    field = GuidingField(Vn, F, samples, edge_length=h)
    info["field"] = {"edge_length": h, "n_tets": field.n_tets, "n_nodes": field.n_nodes,
                     "skeleton_offset": field.skeleton_offset, "seconds": field.seconds}
    return field, rad_of


def _sections_step(kit, chain_controls, relocate_sections, symmetry, center, diag, info):
    """Step 4: one quad section per control node, moved or dropped where its integral lines fail."""
    sections = {}
    moved: list = []
    sec_dropped: list = []
    for ch, ctrl in chain_controls:
        ref = None  # first axis of the previous section along the chain (untwisted round sections)
        for n in ctrl:
            if n in sections:
                ref = sections[n].axis
                continue
            cs, first_error = _section_at(kit, ch, n, ref, relocate_sections, moved)
            if cs is None:
                others = [c for c in ctrl if c != n]
                if relocate_sections and kit.deg[n] == 2 and others:
                    sec_dropped.append(int(n))
                    kit.say(f"section at node {n}: integral lines failed, bending node dropped")
                    continue
                raise first_error
            sections[n] = cs
            ref = cs.axis
    if sec_dropped:
        chain_controls = [(ch, [c for c in ctrl if c not in sec_dropped]) for ch, ctrl in chain_controls]
    if symmetry is not None:  # paper Sec. 3.4: mirror-symmetric sections
        info["symmetry"] = _symmetry_step(sections, symmetry, kit.Vn, kit.F, center, diag, kit.say)
    info["sections_moved"], info["sections_dropped"] = moved, sec_dropped
    return sections, chain_controls


def _section_at(kit, ch, n, ref, relocate_sections, moved):
    """The section of control node ``n`` at the first position along its chain where it can be built."""
    S, rad_of = kit.S, kit.rad_of
    i = ch.nodes.index(n)
    first_error = None
    for j in _section_positions(S, ch, i, rad_of[n], kit.deg[n] == 1 if relocate_sections else None):
        m = ch.nodes[j]
        tan = _tangent(S, ch, j, reach=max(rad_of[n], 2 * kit.spacing))
        rm = rad_of[n] if j == i else float(inscribed_radius(S.nodes[m], kit.Vn, kit.F)[0])
        try:
            cs = cross_section(kit.field, n, S.nodes[m], tan, rm, n_seeds=kit.n_seeds,
                               seed_radius=kit.seed_radius, ref=ref)
        except CageError as exc:
            first_error = exc if j == i else first_error
            continue
        if j != i:
            moved.append({"node": int(n), "moved_to": int(m),
                          "distance": float(np.linalg.norm(S.nodes[m] - S.nodes[n]))})
            kit.say(f"section at node {n}: integral lines failed, moved to node {m}")
        return cs, None
    return None, first_error


def _symmetry_step(sections, symmetry, Vn, F, center, diag, say) -> dict:
    """Step 4b: mirror-symmetrise the sections about a detected or given plane (paper Sec. 3.4)."""
    from .symmetry import detect_mirror_plane, symmetrize_sections

    if isinstance(symmetry, str):
        if symmetry != "auto":
            raise CageOptionError(f"symmetry must be None, 'auto' or (point, normal), got {symmetry!r}")
        plane = detect_mirror_plane(Vn, F)
    else:
        pt, nr = (np.asarray(x, float) for x in symmetry)
        plane = {"point": (pt - center) / diag, "normal": nr / np.linalg.norm(nr), "symmetric": True}
    sinfo = {"detected": plane["symmetric"], "score": plane.get("score"),
             "normal": plane["normal"].tolist(), "point": (plane["point"] * diag + center).tolist()}
    if plane["symmetric"]:
        new_q, si = symmetrize_sections({n: cs.quad for n, cs in sections.items()}, plane["point"],
                                        plane["normal"])
        for n, q in new_q.items():
            sections[n].quad = q
        sinfo.update(si)
        say(f"symmetry: plane normal {np.round(plane['normal'], 3).tolist()}, {len(si['pairs'])} section "
            f"pairs mirrored, {len(si['self'])} sections crossed by the plane")
    return sinfo


def _assembly_step(kit, sections, chain_controls, drop_bad_sections, untangle, info) -> dict:
    """Step 5: the tight cage from the sections, with the recoveries when it cannot be built cleanly."""
    rec = {"dropped": [], "asm_dropped": [], "shrunk": {}, "moved_away": {}, "away_log": [], "flattened": []}
    try:
        tc, shrink_steps = _assemble(kit, sections, chain_controls, drop_bad_sections, untangle, rec)
    finally:  # the recoveries tried, also for a failure's ``exc.partial``
        info["junction_recovery"] = rec["dropped"]
        info["sections_flattened"] = rec["flattened"]
        info["assembly_dropped"] = rec["asm_dropped"]
        info["junction_sections_shrunk"] = {int(k): v for k, v in rec["shrunk"].items()}
        info["junction_sections_moved_away"] = rec["away_log"]
    info["steiner_vertices"] = tc["n_steiner"]
    info["steiner_per_junction"] = tc["n_steiner_per_junction"]
    info["tight_cage_shrink_steps"] = shrink_steps
    info["tight_cage"] = {"n_vertices": len(tc["V"]), "n_faces": len(tc["F"]), "n_quads": len(tc["quads"]),
                          "n_junction_triangles": len(tc["tris"])}
    kit.say(f"tight cage: {len(tc['V'])} vertices, {len(tc['quads'])} quads + {len(tc['tris'])} triangles")
    return tc


def _assemble(kit, sections, chain_controls, drop_bad_sections, untangle, rec) -> tuple[dict, int]:
    """Step 5's loop: untangle, build the tight cage, recover from junction misses and crossings."""
    while True:
        # degenerate sections, and sections that cross their neighbour along the chain (the tube between
        # them folds): flatten them onto the plane orthogonal to the skeleton (ours; idempotent, so every
        # rebuild re-checks the sections the recoveries below moved or added)
        if untangle:
            for nd in untangle_sections(sections, chain_controls, V=kit.Vn, F=kit.F):
                rec["flattened"].append(nd)
                kit.say(f"sections: the section at node {nd} is degenerate or crosses its neighbour along "
                        "the chain, flattened")
        try:
            tc = tight_cage(kit.S, sections, chain_controls)
        except JunctionError as exc:
            if not _junction_recovery(kit, exc, sections, chain_controls, drop_bad_sections, rec):
                raise
            continue
        # a tight cage that intersects itself (sections of neighbouring limbs crossing, or consecutive
        # sections of a bent limb crossing): shrink the offending sections towards their skeleton node,
        # 20% per step; if that fails, drop the bending node owning most intersecting faces and rebuild
        # (ours; the paper has no such case)
        owner, pairs0, pairs, shrink_steps = _shrink_crossing_sections(kit.S, tc)
        if not len(pairs):
            return tc, shrink_steps
        try:
            _drop_crossing_section(kit, tc, owner, pairs0, pairs, chain_controls, drop_bad_sections, rec)
        except CageError as exc:
            exc.tight_cage, exc.crossing_pairs = tc, np.asarray(pairs)  # for the step's ``exc.partial``
            raise


def _junction_recovery(kit, exc, sections, chain_controls, drop_bad_sections, rec) -> bool:
    """Step 5, a junction hull misses a section's edge: move, drop or shrink the section (False: give up)."""
    nd = exc.section
    k = next((j for j, (_, c) in enumerate(chain_controls) if nd in c), None)
    # recovery 1 (ours): move the junction's section away from it along its chain (its projection
    # on the junction's sphere shrinks), half an inscribed radius at a time, 4 times at most,
    # never past the chain's next section; a leaf section alone on its chain gets a new section
    # at the chain's middle instead
    if drop_bad_sections and k is not None and rec["moved_away"].get(nd, 0) < 4:
        ch, ctrl = chain_controls[k]
        res = _move_away(kit, sections, rec, ch, ctrl, nd, exc.junction)
        if res is not None:
            chain_controls[k] = (ch, res)
            return True
    # recovery 2 (ours): use the next section along that chain instead (drop the bending node),
    # when the chain keeps a section
    if (not drop_bad_sections or k is None or kit.deg[nd] != 2 or len(chain_controls[k][1]) < 2
            or len(rec["dropped"]) >= 20):
        # no bending node to drop (a leaf section, or the chain's only one): shrink the section
        # towards its skeleton node, 20% at a time, so that its projection on the junction's
        # sphere no longer overlaps its neighbours'
        if not drop_bad_sections or rec["shrunk"].get(nd, 0) >= 4:
            return False
        cs = sections[nd]
        cs.quad = cs.center + 0.8 * (cs.quad - cs.center)
        rec["shrunk"][nd] = rec["shrunk"].get(nd, 0) + 1
        kit.say(f"junction at node {exc.junction}: shrinking the section at node {nd}")
        return True
    chain_controls[k] = (chain_controls[k][0], [n for n in chain_controls[k][1] if n != nd])
    rec["dropped"].append({"junction": exc.junction, "bending_node_dropped": nd})
    kit.say(f"junction at node {exc.junction}: dropping the bending node {nd} next to it")
    return True


def _move_away(kit, sections, rec, ch, ctrl, nd, junction):
    """New control list of chain ``ch`` after moving the section ``nd`` away from ``junction`` (or adding a
    middle section for a lone leaf section); None when impossible."""
    S, rad_of, moved_away = kit.S, kit.rad_of, rec["moved_away"]
    nodes = ch.nodes
    X = S.nodes[np.asarray(nodes)]
    s_arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]
    if ch.start != junction and ch.end != junction:
        return None
    step = 1 if ch.start == junction else -1
    i = nodes.index(nd)
    if kit.deg[nd] == 1:  # a lone leaf section at the junction: add one at the middle of the chain
        if len(ctrl) != 1 or len(nodes) < 3:
            return None
        j = int(np.clip(np.argmin(np.abs(s_arc - s_arc[-1] / 2)), 1, len(nodes) - 2))
        key, target = int(nodes[j]), j
    else:
        key = nd
        r0 = rad_of.get(nd, 0.0)
        nxt = [nodes.index(c) for c in ctrl if (nodes.index(c) - i) * step > 0]
        lim = s_arc[nxt[0] if step > 0 else nxt[-1]] if nxt else s_arc[-1 if step > 0 else 0]
        want = s_arc[i] + step * 0.5 * r0
        target = int(np.argmin(np.abs(s_arc - want)))
        if target == i:
            target = i + step
        if not (0 < target < len(nodes) - 1) or abs(lim - s_arc[target]) < 0.5 * r0:
            return None
    m = nodes[target]
    rm = float(inscribed_radius(S.nodes[m], kit.Vn, kit.F)[0])
    try:
        tan = _tangent(S, ch, target, reach=max(rm, 2 * kit.spacing))
        cs = cross_section(kit.field, key, S.nodes[m], tan, rm, n_seeds=kit.n_seeds,
                           seed_radius=kit.seed_radius, ref=sections[nd].axis if nd in sections else None)
    except CageError:
        return None
    moved_away[nd] = moved_away.get(nd, 0) + 1
    rec["away_log"].append({"junction": int(junction), "section": int(nd), "to_node": int(m),
                            "added": key != nd})
    if key != nd:  # new middle section
        rad_of[key] = rm
        sections[key] = cs
        S.bending = sorted(set(S.bending) | {key})
        kit.say(f"junction at node {junction}: new section at node {key} (middle of the leaf chain of {nd})")
        return sorted([key] + list(ctrl), key=nodes.index)
    # the moved section keeps its key; its skeleton node is now m (for the shrink steps)
    sections[nd] = cs
    rad_of[nd] = rm
    ctrl_new = list(ctrl)
    # the moved section replaces nd at its new place along the chain: re-key it to m
    sections[int(m)] = sections.pop(nd)
    rad_of[int(m)] = rm
    moved_away[int(m)] = moved_away.pop(nd)
    ctrl_new[ctrl_new.index(nd)] = int(m)
    S.bending = sorted((set(S.bending) - {nd}) | {int(m)})
    kit.say(f"junction at node {junction}: section at node {nd} moved away to node {m}")
    return ctrl_new


def _shrink_crossing_sections(S, tc):
    """Step 5, a self-intersecting tight cage: shrink the faces involved towards their sections' nodes."""
    from .._geometry import self_intersection_pairs

    owner = np.full(len(tc["V"]), -1)
    owner_center = np.zeros((len(tc["V"]), 3))
    for nd, vids in tc["section_rings"].items():
        owner[vids] = nd
        owner_center[vids] = S.nodes[nd]
    pairs = self_intersection_pairs(tc["V"], tc["F"])
    pairs0 = pairs
    shrink_steps = 0
    while len(pairs) and shrink_steps < 10:
        bad = np.unique(tc["F"][np.unique(pairs.ravel())].ravel())
        tc["V"][bad] += 0.2 * (owner_center[bad] - tc["V"][bad])
        shrink_steps += 1
        pairs = self_intersection_pairs(tc["V"], tc["F"])
    return owner, pairs0, pairs, shrink_steps


def _drop_crossing_section(kit, tc, owner, pairs0, pairs, chain_controls, drop_bad_sections, rec) -> None:
    """Step 5, shrinking did not help: drop the bending node owning most crossing faces, or raise."""
    votes: dict = {}
    for f in np.unique(np.asarray(pairs0).ravel()):
        for v in tc["F"][f]:
            nd = int(owner[v])
            if kit.deg[nd] == 2:
                votes[nd] = votes.get(nd, 0) + 1
    cand = [nd for nd in sorted(votes, key=lambda n: -votes[n])
            if len(next(c for _, c in chain_controls if nd in c)) >= 2]
    if not drop_bad_sections or not cand or len(rec["asm_dropped"]) >= 30:
        culprits = sorted({int(owner[v]) for f in np.unique(np.asarray(pairs0).ravel()) for v in tc["F"][f]})
        n_dropped = len(rec["asm_dropped"])
        raise CageError(f"skeleton cage, assembly: the tight cage intersects itself ({len(pairs)} face "
                        f"pairs) after 10 shrink steps and {n_dropped} dropped bending nodes; sections "
                        f"involved at skeleton nodes {culprits}; add or move bending nodes", layer=1)
    nd = cand[0]
    k = next(j for j, (_, c) in enumerate(chain_controls) if nd in c)
    chain_controls[k] = (chain_controls[k][0], [n for n in chain_controls[k][1] if n != nd])
    rec["asm_dropped"].append({"bending_node_dropped": nd, "face_pairs": int(len(pairs0))})
    kit.say(f"assembly: tight cage self-intersects ({len(pairs0)} face pairs), dropping bending node {nd}")


def _pre_inflation_step(field, tc, Vn, F, rounds, info, say, pushes=True):
    """Step 6: pull the tight cage out to M along the integral lines.

    ``pushes`` False: the paper's step only (no containment, crease or polish pushes: the sweep
    containment does not need M inside the cage, only the skeleton)."""
    Vt, Ft = tc["V"], tc["F"]
    extra = {} if pushes else {"crease_rounds": 0, "polish_rounds": 0}
    Vp, pinfo = pre_inflate(field, Vt, Ft, Vn, F, rounds=rounds, **extra)
    quads_out, tris_out = tc["quads"], tc["tris"]
    info["pre_inflation"] = pinfo
    return Vp, Ft, Vt, quads_out, tris_out


def _inflation_step(parts, inner, Vn, F, min_gap, nested_opts):
    """Step 7: the Nested Cages flow + re-inflation of the pre-inflated cage around M (or ``inner``)."""
    from ..failures import PairFailure
    from ..nested.backend import nest_pair

    diag, center, Vp, Ft = parts["diag"], parts["center"], parts["Vp"], parts["Ft"]
    if inner is not None:
        Vi = (np.asarray(inner[0], dtype=float) - center) / diag
        Fi = np.asarray(inner[1], dtype=np.int64)
    else:
        Vi, Fi = Vn, F
    gap = 1.1 * float(min_gap)
    nested_opts.setdefault("flow_max_iter", 2000)  # spot: 945 iterations after the crease push
    # fail fast: stop a flow that cannot finish within flow_max_iter at its rate over the last 200
    # iterations (zoo: stuck flows cost 86-439 s at the 2000-iteration cap)
    nested_opts.setdefault("flow_stall_window", 200)
    # local flow: only the parts of M outside the pre-inflated cage or less than 0.01 of the diagonal
    # inside it move (issue 18: residual 0.0081 -> 0.0007 on cheburashka, 0.045 -> 0.0014 on elephant;
    # a point deep inside pushed away from the cage gains nothing and stretches the triangles)
    nested_opts.setdefault("flow_active_depth", 0.01)
    try:
        C, ninfo, _ = nest_pair(Vi, Fi, Vp, Ft, gap=gap, **nested_opts)
    except PairFailure as exc:
        hint = ""
        if exc.stage == "flow":
            n_out = int(np.sum(_winding(Vp, Ft, Vi) < 0.5))
            where = ("give a skeleton or bending nodes closer to those parts" if n_out else
                     "the cage's faces still cut its triangles; give bending nodes there")
            hint = (f"; {n_out} of {len(Vi)} vertices of the input were outside the pre-inflated cage: "
                    f"{where}, or raise flow_max_iter (now {nested_opts['flow_max_iter']}) / pass "
                    "flow_stall_window=None to run the flow to its cap")
        raise _failure(f"skeleton cage, inflation (nested flow/re-inflation): {exc.stage} failed: "
                       f"{exc.reason}" + hint, parts, reason=exc.reason) from exc
    info = parts["info"]
    info["inflation"] = {k: v for k, v in ninfo.items() if k != "seconds"}
    info["inflation"]["seconds"] = ninfo["seconds"]
    return C


_CONTAINMENTS = ("mesh", "flow")


def _sweep_step(parts, field, inner, Vn, F, min_gap, containment, say):
    """Step 7 (default): re-inflate a target swept down the guiding field's level sets, pushing the
    tight cage out (:mod:`cagegen.skeleton.contain`), then complete the clearance."""
    from ..nested.backend import complete_clearance
    from ..nested.reinflate import reinflate
    from .contain import collapse_inside, start_level, sweep_history

    diag, center, Vc, Fc = parts["diag"], parts["center"], parts["Vp"], parts["Ft"]
    gap = 1.1 * float(min_gap)
    t = time.perf_counter()
    if inner is not None:
        inner = ((np.asarray(inner[0], dtype=float) - center) / diag, np.asarray(inner[1], dtype=np.int64))
    # the surface carried down the field and re-inflated: M itself, or the inner layer of a hierarchy
    # (an offset envelope and a 1500-face nested proxy were measured and dropped: docs/skeleton.md)
    VT, FT, kind = (inner[0], inner[1], "inner") if inner is not None else (Vn, F, "mesh")
    rec = {"target": kind, "seconds_target": time.perf_counter() - t}
    parts["info"]["containment"] = rec
    levels = [0.8, 0.6, 0.4, 0.25, 0.15, 0.08, 0.04]
    hist, rec["sweep"] = sweep_history(field, VT, Vn, F, levels)
    core = collapse_inside(field, hist[-1], FT, Vc, Fc)
    if core is not None:
        hist.append(core)
        rec["sweep"]["levels"].append("collapsed")
    j = start_level(hist, FT, Vc, Fc)
    rec["start_level"] = rec["sweep"]["levels"][j] if j >= 0 else None
    if j < 0:
        raise _failure("skeleton cage, containment: the target swept down the guiding field and "
                       "collapsed onto the skeleton is not inside the tight cage",
                       parts, reason="start")
    say(f"containment: re-inflating the {kind} target ({len(VT)} vertices) from f = {rec['start_level']}")
    for dhat in (5e-3, 2e-3):  # nest_pair's barrier range, then a shorter one where limbs are close
        # the final (volume) phase's barrier range keeps room for the clearance's push_out
        rr = reinflate(hist[: j + 1], FT, Vc, Fc, energy="volume", dhat=dhat, max_move=min(5e-3, dhat),
                       dhat_final=max(1e-3, 4.0 * gap))
        rec["reinflate"] = {k: (float(v) if isinstance(v, (float, np.floating)) else v)
                            for k, v in rr.stats.items()}
        rec["reinflate"]["dhat"] = dhat
        if rr.success:
            break
        say(f"containment: re-inflation with dhat {dhat:g} failed ({rr.reason})")
    if not rr.success:
        raise _failure(f"skeleton cage, containment (re-inflation of the swept {kind} target): {rr.reason}",
                       parts, reason=rr.reason)
    C = rr.cage
    Vi, Fi = inner if inner is not None else (Vn, F)
    if gap > 0:
        C, d, rec["clearance_completion"] = complete_clearance(C, Fc, Vi, Fi, gap)
        if d < float(min_gap):  # push_out blocked: carry M out to its offset, pushing the cage (a short
            C, d = _clearance_by_reinflation(C, Fc, Vi, Fi, gap, rec, say)  # re-inflation, nest_pair's way)
        rec["distance"] = float(d)
        if d < float(min_gap):
            why = (rec["clearance_completion"] or {}).get("reason")
            raise _failure(f"skeleton cage, clearance: the contained cage is {d:.3g} from the input, "
                           f"less than min_gap {min_gap:.3g} ({why})", parts, reason="clearance")
    return C


def _clearance_by_reinflation(C, Fc, Vi, Fi, gap, rec, say):
    """The contained cage ``C`` pushed out by re-inflating the inner surface from rest to its offset by
    ``gap`` (:func:`cagegen.nested.backend.offset_surface`), then :func:`push_out` again."""
    from ..nested.backend import complete_clearance, offset_surface
    from ..nested.reinflate import reinflate

    say("clearance: push_out blocked, re-inflating the input to its offset")
    target = offset_surface(Vi, Fi, gap)
    rr = reinflate([target, np.asarray(Vi, dtype=float)], Fi, C, Fc, energy="volume", dhat=2e-3,
                   max_move=2e-3, dhat_final=max(1e-3, 4.0 * gap))
    rec["clearance_reinflation"] = {"success": bool(rr.success), "reason": rr.reason}
    if not rr.success:
        return C, 0.0
    C2, d, rec["clearance_completion_2"] = complete_clearance(rr.cage, Fc, Vi, Fi, gap)
    return C2, d


def _certification_step(parts, V, F, inner, Vc, Fc, min_gap) -> None:
    """Step 7, certification: :func:`cagegen.verify_nesting` around M (or ``inner``); a failure raises."""
    ref = (np.asarray(inner[0], float), np.asarray(inner[1], np.int64)) if inner is not None else (V, F)
    rep = verify_nesting([ref, (Vc, Fc)], min_gap=min_gap * parts["diag"] / _diag(ref[0]))
    parts["info"]["verification"] = rep.to_dict()
    if not rep.ok:
        raise _failure(f"skeleton cage, certification: {rep.pairs[0].reason}", parts,
                       reason=str(rep.pairs[0].reason))


def _cage_result(Vc, certified, parts) -> SkeletonCage:
    """The :class:`SkeletonCage` of the cage ``Vc`` (caller's coordinates) and what was built on the way."""
    diag, center, tc, S = parts["diag"], parts["center"], parts["tc"], parts["S"]
    sections = [{"node": int(n), "center": s_.center * diag + center, "quad": s_.quad * diag + center,
                 "hits": s_.hits * diag + center} for n, s_ in sorted(parts["sections"].items())
                if n in tc["section_vertices"]]
    return SkeletonCage(V=Vc, F=np.ascontiguousarray(parts["Ft"], dtype=np.int64), quads=parts["quads"],
                        tris=parts["tris"], tight_V=parts["Vt"] * diag + center,
                        preinflated_V=parts["Vp"] * diag + center,
                        skeleton=Skeleton(S.nodes * diag + center, S.edges,
                                          [b for b in S.bending if b in tc["section_vertices"]]),
                        input_skeleton=parts["S_in"], sections=sections, info=parts["info"],
                        certified=certified)


def _failure(msg, parts, **kw) -> CageError:
    """The :class:`CageError` of a step from the pre-inflation on; the uncertified cage as ``partial``."""
    # what was built before the failing step (the pre-inflated cage, NOT certified), for pictures and
    # diagnosis: ``exc.partial`` (a SkeletonCage with ``certified=False``, ``V`` = the pre-inflated cage)
    sec = parts["sec"]
    sec["total"] = time.perf_counter() - parts["t_all"]
    parts["info"]["seconds"] = sec
    exc = CageError(msg, layer=1, **kw)
    exc.partial = _cage_result(parts["Vp"] * parts["diag"] + parts["center"], False, parts)
    return exc


def _assembly_failure(exc: CageError, parts: dict) -> CageError:
    """The assembly step's :class:`CageError`, named ``assembly``, with ``exc.partial``.

    A self-intersecting tight cage (``exc.tight_cage``, set by :func:`_assembly_step`) is the partial's
    ``V`` = ``tight_V`` (``certified=False``, ``info["assembly_crossing_pairs"]`` the face pairs still
    crossing); a junction hull that could not be built leaves no cage (``V``, ``F``, ``quads``, ``tris``,
    ``tight_V`` None): the skeleton and the sections only.
    """
    msg = str(exc)
    if not msg.startswith("skeleton cage, assembly"):
        msg = "skeleton cage, assembly: " + msg.removeprefix("skeleton cage, ")
    new = (JunctionError(msg, exc.junction, exc.section) if isinstance(exc, JunctionError)
           else CageError(msg, layer=1))
    sec, info = parts["sec"], parts["info"]
    sec["total"] = time.perf_counter() - parts["t_all"]
    info["seconds"] = sec
    tc = getattr(exc, "tight_cage", None)
    if tc is not None:
        info["assembly_crossing_pairs"] = np.asarray(exc.crossing_pairs).tolist()
        parts.update(tc=tc, Ft=tc["F"], quads=tc["quads"], tris=tc["tris"], Vt=tc["V"], Vp=tc["V"])
        new.partial = _cage_result(tc["V"] * parts["diag"] + parts["center"], False, parts)
        return new
    diag, center, S = parts["diag"], parts["center"], parts["S"]
    sections = [{"node": int(n), "center": s_.center * diag + center, "quad": s_.quad * diag + center,
                 "hits": s_.hits * diag + center} for n, s_ in sorted(parts["sections"].items())]
    new.partial = SkeletonCage(V=None, F=None, quads=None, tris=None, tight_V=None, preinflated_V=None,
                               skeleton=Skeleton(S.nodes * diag + center, S.edges, list(S.bending)),
                               input_skeleton=parts["S_in"], sections=sections, info=info, certified=False)
    return new


def _winding(V, F, P):
    import igl

    return igl.winding_number(V, F, np.atleast_2d(P))


def _diag(V: np.ndarray) -> float:
    return float(np.linalg.norm(V.max(0) - V.min(0)))


def skeleton_backend(V: np.ndarray, F: np.ndarray, face_counts, *, skeleton=None, bending="auto",
                     min_gap: float = 0.0, progress=None, nested_face_counts: str = "above",
                     **opts) -> tuple[list, dict]:
    """Cage backend ``"skeleton"`` for :func:`cagegen.build_cages`.

    The coarsest cage is the skeleton cage (its size is set by the skeleton and the bending nodes,
    not by ``face_counts[-1]``, which is only recorded). With more than one cage, the finer ones are
    ``nested`` cages with ``face_counts[:-1]`` faces built first, and the skeleton cage is inflated
    around the coarsest of them.

    Parameters
    ----------
    V, F : the audited input surface.
    face_counts : sequence of int
        Targets, finest first; all but the last must exceed the skeleton cage's face count.
    skeleton, bending :
        See :func:`skeleton_cage`.
    min_gap : float
        Clearance between consecutive layers (relative to the input's diagonal).
    **opts
        Passed to :func:`skeleton_cage`.

    Returns
    -------
    layers, info
    """
    info: dict = {"method": "skeleton", "skeleton_target_ignored": int(face_counts[-1])}
    layers: list = []
    inner = None
    if len(face_counts) > 1:
        from ..nested import nested_backend

        nl, ninfo = nested_backend(V, F, list(face_counts[:-1]), min_gap=min_gap, progress=progress)
        layers.extend(nl)
        inner = nl[-1]
        info["nested"] = ninfo
    cage = skeleton_cage(V, F, skeleton, bending=bending, min_gap=min_gap, progress=progress, inner=inner,
                         **opts)
    if layers and len(cage.F) >= len(layers[-1][1]):
        raise CageError(f"skeleton cage has {len(cage.F)} faces, not fewer than the nested layer below it "
                        f"({len(layers[-1][1])}); use larger face counts for the nested layers",
                        layer=len(face_counts))
    layers.append((cage.V, cage.F))
    info["skeleton"] = cage.info
    return layers, info
