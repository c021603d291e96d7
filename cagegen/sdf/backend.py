"""The ``"sdf"`` cage backend: Qiu, Liao, Chen (2024), *High-quality Cage Generation Based on SDF*.

One layer (:func:`sdf_cage_layer`), in coordinates normalised to a unit bounding-box diagonal of the
*input* (so ``c`` means the same on every layer):

1. **Envelope** (:mod:`cagegen.envelope`): iso-surface ``{phi * xi = c}`` of the locally
   amplified signed distance by marching cubes; it strictly contains the fine layer.
2. **Constrained simplification** (:mod:`cagegen.sdf.simplify`) to exactly ``n_faces`` faces: QEM
   collapses, infeasible (skipped) when the new triangles would cross the fine layer or the cage.
   For speed, a plain QEM pre-pass (``igl.qslim`` via :func:`cagegen.decimate.decimate_surface`) to a
   few times the target is accepted first *when its result passes the same exact constraints*
   (no crossing with the fine layer, closed, same genus, no self-intersection); otherwise the
   constrained collapses start from the envelope itself.
3. **Optimisation** (:mod:`cagegen.sdf.optimize`): spacing + MIPS energy under an IPC barrier with a
   CCD line search, and edge flips.
4. Every layer is certified by :func:`cagegen.verify_nesting` before it is returned; if a step
   cannot finish (simplification stuck, certification failed), the layer is rebuilt with ``c``
   doubled (more room), up to ``max_retries`` times, then :class:`CageError` is raised.

``build_cages(V, F, levels=K, method="sdf")`` runs :func:`sdf_cage_layer` on the previous layer for
each coarser layer. License: MIT (numpy, scipy, scikit-image, libigl's MIT core, ipctk).

Options beyond the paper (units and defaults: :class:`cagegen.SdfOptions`):

* ``h``: the grid spacing defaults to ``c`` but is made finer (at most 4x) when the envelope would have
  fewer than ``ENVELOPE_OVER_TARGET = 4`` times ``n_faces`` faces, so the cage is a simplification of
  it and not the marching-cubes surface itself (``info["envelope"]["refined_for_target"]``).
* ``opt_time_limit`` is CPU seconds, not wall, so a loaded machine gives the same cage.
* ``pull`` (0 = off): input vertices farther than ``c`` from the cage (concavities the envelope
  bridged) pull the cage toward them, under the same barrier and CCD
  (:func:`cagegen.sdf.optimize.optimize_cage`, ``w_p``).
* ``check_input``: audit ``(V, F)`` first (:func:`cagegen.check_mesh`: closed, manifold, oriented,
  exact self-intersection test; measured 46 CPU s on an 85k-face input) and refuse a bad surface at
  once with :class:`cagegen.MeshInputError` (a self-intersecting input has no cage that contains it
  strictly; without the check the backend spends minutes of rebuilds before giving up). False: the
  caller guarantees an audited input (``build_cages`` does, and every layer it returns is certified).
* ``hug`` (0 = off; default 0.1 since the zoo runs ``zoo_sdf_hug01.json`` /
  ``zoo4_tighten_hug01.json``): spacing target of the optimisation near the input's active points
  (where two parts nearly touch), in units of ``c``, so the cage hugs the input there and a coarser
  layer built on it can still separate the parts (homer's second layer: genus 0 instead of 1);
  elsewhere ``spacing``. Inputs without active points are unaffected. ``hug_radius`` is its falloff
  radius around the active points, in units of ``r``.
* ``hug_dhat``: with ``hug`` and active points found, the barrier activation distance becomes
  ``min(dhat, hug_dhat)`` (units of ``c``; everywhere, ipctk's barrier has one ``dhat``): the descent
  holds the cage vertices in barrier pairs when the CCD blocks a step, so with ``dhat = 0.25 c`` the
  cage cannot come closer than ~0.25 ``c`` (homer: the lower target alone and the lower barrier alone
  both leave the second layer at genus 1, together genus 0).
* ``tighten`` (0 = off), ``tighten_rounds``: when an input vertex is farther than ``tighten * c`` from
  the optimised cage (a concavity the envelope bridged), :func:`cagegen.sdf.tighten.tighten_cage`
  inserts a cage vertex above each such point, lowers it with the pull under a ``0.05 c`` barrier,
  collapses as many edges elsewhere (the inserted vertices frozen) and keeps the round only if it is
  certified and tighter.
* ``bridge_retry`` (0 = off): when the finished cage is still farther than ``tighten * c`` from the
  fine layer *and* the envelope itself was (the offset bridged a concavity: an eye socket, a slot
  between two parts, which neither the optimisation nor the tightening pass can enter from above),
  the layer is built once more at ``c * bridge_retry`` and that cage is kept if it is certified, has
  the first one's genus and is tighter (input-to-cage and symmetric Hausdorff distances both
  smaller). It runs only if three times the first build's seconds fit in what is left of
  ``cage_time_budget`` / ``deadline``, and only if ``c * bridge_retry >= 4 min_gap`` (the clearance
  leaves room to simplify). ``info["bridge_retry"]`` records the trigger, the distances and what was
  kept. Measured: ``docs/sdf.md``.
* ``cage_time_budget``: wall-clock seconds a call may take (None: no limit). Checked first, in
  milliseconds: when :func:`estimate_layer_seconds` of the input exceeds it, :class:`CageError`
  (``reason="time budget"``) names the option before the audit or any other work. During the run, a
  tightening round is started only if the time already spent plus the last round's time fits the
  budget (the pass is an improvement of an already certified cage; ``info["tighten"]["stopped"]``
  records it). ``deadline`` (a ``time.perf_counter()`` value; :func:`sdf_schedule` sets it from the
  run's budget) stops tightening rounds the same way.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from .._geometry import (as_mesh_arrays, bbox_diagonal, cross_intersection_pairs, edge_stats, n_components,
                         normalize)
from .._geometry import signed_volume as _signed_volume
from ..audit import check_mesh
from ..decimate import decimate_surface
from ..errors import CageError, CageOptionError
from ..options import check_time_budget
from ..verify import verify_nesting
from ..envelope import active_points, build_envelope
from .optimize import _min_angles, mips, optimize_cage
from .simplify import SimplifyStuck, constrained_simplify
from .tighten import tighten_cage

__all__ = ["budget_check", "estimate_layer_seconds", "genus", "sdf_cage_layer", "sdf_schedule"]

#: paper defaults (Sec. 4), lengths relative to the unit bounding-box diagonal
DEFAULTS = {"c": 0.01, "r": 0.025, "l": 0.15, "alpha": 3.0, "beta": 8.0}


def genus(V: np.ndarray, F: np.ndarray) -> int | None:
    """Total genus of a closed manifold triangle mesh (None if not closed manifold)."""
    F = np.asarray(F, dtype=np.int64)
    es = edge_stats(F, len(V))
    if es.n_boundary_edges or es.n_nonmanifold_edges:
        return None
    chi = np.unique(F).size - es.n_edges + F.shape[0]
    return int((2 * n_components(F, len(V)) - chi) // 2)


def _min_angle_deg(V: np.ndarray, F: np.ndarray) -> float:
    """Smallest interior angle of the triangles ``(V, F)``, in degrees."""
    return float(_min_angles(V, F).min())


def _prepass(U, G, Vf, Ff, n_faces, mults=(32, 16, 8, 4, 2), clear: float = 0.0, bisect: int = 3,
             min_step: float = 0.75):
    """Plain QEM in steps to ``mult * n_faces`` faces (each step from the last accepted one), a step
    being accepted only when its result satisfies the constraints (closed, same genus, no
    self-intersection: :func:`decimate_surface`; no crossing, the fine layer inside and, with
    ``clear > 0``, the cage no closer than ``clear`` to the fine layer (the caller's ``min_gap``: the
    sampled test of the constrained collapses, then ipctk's exact vertex-face / edge-edge distance):
    here). Without the clearance test a pre-pass
    step could come within 2e-4 of a coarse fine layer: the constrained collapses only check the
    triangles they create, so the layer then failed its ``min_gap`` certificate and was rebuilt with
    ``c`` doubled (nestmg's second cage layer on bunny and gargo, 7-9% of the diagonal).

    A refused step is not the end: plain QEM shortens a thin protrusion of the fine layer (a spike of a
    coarse input, wrapped by the envelope at distance ``c``) once the cage's edges there grow past ~``c``,
    so the step that fails is the one whose reduction is too large *near the spikes*, while a smaller
    reduction is still clean. The face count is then bisected (geometric mean) between the last accepted
    cage and the refused count, at most ``bisect`` times, and no step smaller than ``min_step`` times
    the current count is tried (it would not pay for its test). Each bisected step is tested like the
    others, so the constrained collapses still start from a cage satisfying every constraint."""
    import igl
    from scipy.spatial import cKDTree

    from ..collision import min_distance
    from .simplify import too_close

    tree = cKDTree(Vf) if clear > 0 else None

    def step(U, G, m):
        try:
            U2, G2, dinfo = decimate_surface(U, G, m)
        except CageError as exc:
            return None, {"faces": m, "ok": False, "reason": str(exc)}
        k = len(cross_intersection_pairs(U2, G2, Vf, Ff))
        if k:
            return None, {"faces": m, "ok": False, "reason": f"crosses the fine layer ({k} pairs)"}
        if igl.winding_number(U2, G2, Vf[:1])[0] < 0.5:
            return None, {"faces": m, "ok": False, "reason": "fine layer outside"}
        if clear > 0:
            k = int(too_close(U2[G2], Vf, Ff, tree, clear).sum())
            dmin = min_distance(U2, G2, Vf, Ff, upper=2 * clear) if not k else 0.0
            if k or dmin < clear:
                return None, {"faces": m, "ok": False,
                              "reason": f"closer than min_gap ({k} faces sampled, exact distance {dmin:.3g})"}
        return (U2, G2), {"faces": len(G2), "ok": True, "reason": "", "seconds": dinfo["seconds"]}

    tried = []
    refused = None
    for mult in mults:
        m = int(2 * round(mult * n_faces / 2))
        if m >= len(G):
            continue
        res, rec = step(U, G, m)
        tried.append(rec)
        if res is None:
            refused = m
            break
        U, G = res
    for _ in range(int(bisect) if refused is not None else 0):
        m = int(2 * round(np.sqrt(len(G) * refused) / 2))
        if m <= refused or m > min_step * len(G):
            break
        res, rec = step(U, G, m)
        rec["bisected"] = True
        tried.append(rec)
        if res is None:
            refused = m
        else:
            U, G = res
    return U, G, tried


def _pick_envelope(tried: list[dict], g_fine: int | None) -> int | None:
    """Index of the envelope to keep among the grids tried (``{"crossings", "genus"}`` each, coarsest
    first): the clean ones (no crossing of the fine layer), the closest genus to ``g_fine``, the coarsest
    on ties; None if every one crosses the fine layer."""
    clean = [i for i, t in enumerate(tried) if not t["crossings"]]
    if not clean:
        return None

    def dist(g):
        return abs(g - g_fine) if g is not None and g_fine is not None else float("inf")

    return min(clean, key=lambda i: (dist(tried[i]["genus"]), i))


#: the envelope is built (``h`` not given) with at least this many times the target's faces
ENVELOPE_OVER_TARGET = 4.0

#: default wall-clock budget (seconds) of one sdf run (all its layers) or sdf_cage_layer call; None = no limit
DEFAULT_TIME_BUDGET = 900.0


def estimate_layer_seconds(n_input_faces: int) -> float:
    """Seconds one :func:`sdf_cage_layer` call is expected to take (one core of the 2-core dev machine).

    ``15 + 0.005 n`` for an ``n``-face input: an upper envelope of the measured layers of ``>= 5k``
    input faces (``benchmarks/results/sdf/zoo_sdf_tighten_hug01_d89697c.json``: homer 12k faces 74 s,
    gargo 5.3k 24 s, bumpy-cube 40k 48 s; gargo subdivided twice, 85k faces: 379 CPU s, docs/sdf.md).
    The audit, the certificates and the optimisation's distance queries grow with the input; the
    envelope's grid does not (``c`` fixes it). Coarse inputs with spikes can take longer per face
    (decimated-knight, 1k faces: 55 s), which the constant covers only in part: it is a guard against
    starting an hour of work, not a prediction.
    """
    return 15.0 + 5e-3 * float(n_input_faces)


def _budget_check(n_input: list[int], cage_time_budget: float | None, what: str) -> float:
    """Raise :class:`CageError` (in milliseconds, before any work) when the estimate exceeds the budget."""
    est = float(sum(estimate_layer_seconds(n) for n in n_input))
    check_time_budget(est, cage_time_budget,
                      f"{what}: estimated {est:.0f} s for a {n_input[0]:,}-face input ({len(n_input)} layer(s), "
                      f"~{estimate_layer_seconds(1):.0f} s + 5 ms per input face each)")
    return est


def budget_check(n_faces: int, face_counts, *, cage_time_budget: float | None = DEFAULT_TIME_BUDGET,
                 **opts) -> float:
    """The estimate of a run of ``"sdf"`` layers (:func:`estimate_layer_seconds` of each layer's input)
    checked against ``cage_time_budget``: the registry's ``budget`` check (:func:`cagegen.build_cages` calls
    it before the input audit; :func:`sdf_schedule` checks it again on the audited input)."""
    counts = [int(m) for m in face_counts]
    return _budget_check([int(n_faces)] + counts[:-1], cage_time_budget, f"sdf cages {counts}")


def _check_target(n_faces) -> int:
    if isinstance(n_faces, (bool, np.bool_)) or int(n_faces) != n_faces or int(n_faces) < 4:
        raise CageOptionError(f"n_faces must be an integer >= 4, got {n_faces!r}")
    if int(n_faces) % 2:
        raise CageOptionError(f"n_faces must be even (a closed triangle mesh has an even face count), got {n_faces}")
    return int(n_faces)


def sdf_cage_layer(
    V, F, n_faces: int, *, unit: float | None = None,
    c: float = DEFAULTS["c"], h: float | None = None, amplify: bool = True, r: float = DEFAULTS["r"],
    l: float = DEFAULTS["l"], alpha: float = DEFAULTS["alpha"], beta: float = DEFAULTS["beta"],  # noqa: E741
    margin: float = 0.3, optimize: bool = True, spacing: float = 0.5, dhat: float = 0.25, opt_iters: int = 15,
    flip_rounds: int = 1, opt_time_limit: float = 30.0, pull: float = 50.0, prepass: bool = True,
    max_retries: int = 3, min_gap: float = 0.0, check_input: bool = True, hug: float = 0.1,
    hug_radius: float = 1.0, hug_dhat: float = 0.05, tighten: float = 1.5, tighten_rounds: int = 3,
    bridge_retry: float = 0.5, cage_time_budget: float | None = DEFAULT_TIME_BUDGET,
    deadline: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """One certified cage with exactly ``n_faces`` faces strictly containing the closed surface ``(V, F)``.

    The options are the fields of :class:`cagegen.SdfOptions` (units and defaults there); those beyond
    the paper are described in this module's docstring.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
        Closed, outward-oriented, self-intersection-free surface (not modified).
    n_faces : int
        Exact face count of the cage (even, >= 4).
    unit : float, optional
        Length that ``c``, ``h``, ``r``, ``l`` and ``1/beta`` are relative to (default: the bounding-box
        diagonal of ``(V, F)``; the backend passes the input's, so all layers share one scale).
    c, h, amplify, r, l, alpha, beta
        Envelope (step 1): iso-value (paper: 0.01), grid spacing (default ``c``), local amplification
        near nearly-touching parts and its parameters (paper eqs. 2-3: 0.025, 0.15, 3, 8).
    margin, prepass, max_retries
        Simplification (step 2): clearance on the distance grid (units of ``c``), the plain-QEM
        pre-pass, rebuilds with ``c`` doubled when a layer cannot be finished or certified.
    optimize, spacing, dhat, opt_iters, flip_rounds, opt_time_limit, pull
        Optimisation (step 3): on/off, target spacing and barrier distance (units of ``c``), descent
        steps per round, rounds of edge flips, CPU seconds of the descent, weight of the input pull.
    hug, hug_radius, hug_dhat, tighten, tighten_rounds, bridge_retry
        Beyond the paper (module docstring); 0 turns ``hug``, ``tighten``, ``bridge_retry`` off.
    min_gap : float
        Clearance the cage must keep from ``(V, F)``, relative to ``unit`` (certified exactly; the
        simplification keeps twice that on its distance grid).
    check_input : bool
        Audit ``(V, F)`` first (False: the caller guarantees an audited input, as ``build_cages``).
    cage_time_budget : float or None
        Wall-clock seconds this call may take, estimated before any work and enforced in the simplification
        (no batch of collapses starts past it: :class:`cagegen.CageError`) (None: no limit).
    deadline : float, optional
        A ``time.perf_counter()`` value after which no tightening round starts.

    Returns
    -------
    U : (p,3) float64 array
    G : (n_faces,3) int64 array
        The cage, certified by :func:`cagegen.verify_nesting` against ``(V, F)``.
    info : dict
        JSON-serialisable figures: ``n_faces``, ``c_used``, ``envelope``, ``prepass``, ``simplify``,
        ``optimize``, ``genus_fine``, ``genus``, ``genus_envelope``, ``min_angle_deg``,
        ``mips_mean``/``mips_max``, ``hausdorff_relative`` (to ``(V, F)``, over ``unit``),
        ``volume_ratio``, ``verification``, ``attempts``, ``seconds`` per phase, ``bridge_retry``.

    Raises
    ------
    cagegen.MeshInputError
        Malformed arrays; with ``check_input``, a surface that fails the audit (self-intersecting,
        open, non-manifold, ...), before any work.
    ValueError
        Bad option values (odd or too small ``n_faces``, ...).
    cagegen.CageError
        No certified cage after ``max_retries`` rebuilds (the message gives each attempt's reason), or
        the estimated time exceeds ``cage_time_budget`` (raised before any work).
    """
    call = dict(locals())  # this call's arguments (first statement: nothing else is local yet), for the retry
    opts = SimpleNamespace(**call)
    t0 = time.perf_counter()
    V, F, n_faces, tight_deadline, t_check = _layer_inputs(opts, t0)
    Vn, center, unit = normalize(V, unit)
    g_fine = genus(Vn, F)
    gap_rel = float(min_gap) / bbox_diagonal(Vn)  # verify_nesting's min_gap is relative to layer 0
    ck, attempts, (env, U, G, rep, steps), sec = _certified_attempt(opts, Vn, F, n_faces, g_fine, gap_rel,
                                                                     tight_deadline)
    if len(G) != n_faces:  # every collapse removes two faces; flips keep the count
        raise CageError(f"sdf cage has {len(G)} faces, {n_faces} requested", reason="face count")
    Uo = U * unit + center
    info = _layer_info(U, G, Vn, F, n_faces, ck, attempts, env, steps, g_fine, rep, sec, t0)
    if t_check is not None:
        info["seconds"]["check_input"] = t_check
    info["genus_changed"] = bool(info["genus"] != g_fine)
    G = np.ascontiguousarray(G, dtype=np.int64)
    if bridge_retry > 0 and tighten > 0:
        Uo, G, info = _bridge_retry(call, Uo, G, info, Vn, F, U, env, ck, tighten * ck, t0, tight_deadline)
    return Uo, G, info


def _layer_inputs(opts, t0: float) -> tuple:
    """Arrays, face count, time budget, option values and (``check_input``) the audit of a layer's input.

    Returns ``(V, F, n_faces, tightening deadline, audit seconds or None)``.
    """
    V, F = as_mesh_arrays(opts.V, opts.F, "fine layer")
    n_faces = _check_target(opts.n_faces)
    _budget_check([len(F)], opts.cage_time_budget, f"sdf cage with {n_faces} faces")
    o = opts
    tight_deadline = o.deadline
    o.budget_deadline = None  # the call's own budget, enforced in the simplification (a run's layers have none)
    if o.cage_time_budget is not None:
        o.budget_deadline = t0 + float(o.cage_time_budget)
        tight_deadline = min(o.budget_deadline, np.inf if o.deadline is None else o.deadline)
    if not o.c > 0 or not o.margin >= 0 or not o.spacing >= 0 or not o.dhat > 0 or not o.min_gap >= 0 \
            or not o.pull >= 0:
        raise CageOptionError("c and dhat must be > 0; margin, spacing, pull and min_gap >= 0")
    t_check = None
    if opts.check_input:
        t = time.perf_counter()
        check_mesh(V, F, name="sdf input")  # MeshInputError naming every problem (self-intersections, ...)
        t_check = time.perf_counter() - t
    return V, F, n_faces, tight_deadline, t_check


def _certified_attempt(opts, Vn, F, n_faces, g_fine, gap_rel, deadline) -> tuple:
    """Attempts at ``c``, ``2c``, ``4c``, ... (step 4) until one is certified.

    Returns ``(c used, failed attempts, _layer_attempt's result, seconds per phase)``.
    """
    attempts = []
    hug_cache: dict = {}  # the input's active points, found once
    for attempt in range(int(opts.max_retries) + 1):
        ck = opts.c * 2.0 ** attempt
        sec: dict = {}
        try:
            result = _layer_attempt(opts, Vn, F, n_faces, ck, attempt, g_fine, gap_rel, hug_cache, deadline,
                                    sec)
            return ck, attempts, result, sec
        except SimplifyStuck as exc:
            attempts.append({"c": ck, "reason": str(exc)})
    detail = "; ".join(f"c={a['c']:.3g}: {a['reason']}" for a in attempts)
    raise CageError(f"sdf cage with {n_faces} faces: no certified cage in {len(attempts)} attempts "
                    f"({detail})", reason=attempts[-1]["reason"])


def _layer_attempt(opts, Vn, F, n_faces, ck, attempt, g_fine, gap_rel, hug_cache, deadline, sec):
    """One attempt at offset ``ck``: envelope, simplification, certificate, optimisation, tightening."""
    t = time.perf_counter()
    env = _envelope_step(opts, Vn, F, n_faces, ck, attempt, g_fine)
    sec["envelope"] = time.perf_counter() - t
    U, G, pre, sinfo = _simplify_step(opts, env, Vn, F, n_faces, ck, sec)
    t = time.perf_counter()
    rep = verify_nesting([(Vn, F), (U, G)], min_gap=gap_rel)
    sec["verify"] = time.perf_counter() - t
    if not rep.ok:
        raise SimplifyStuck(f"simplified cage not certified: {rep.pairs[0].reason}")
    U, G, rep, oinfo = _optimize_step(opts, U, G, Vn, F, ck, gap_rel, rep, hug_cache, sec)
    U, G, rep, tinfo = _tighten_step(opts, U, G, Vn, F, env, ck, gap_rel, rep, deadline, sec)
    return env, U, G, rep, {"prepass": pre, "simplify": sinfo, "optimize": oinfo, "tighten": tinfo}


def _first_envelope(opts, Vn, F, n_faces, ck, attempt, g_fine):
    """Step 1a: the envelope at offset ``ck``, on a finer grid when it has too few faces to simplify."""
    h = opts.h
    env = build_envelope(Vn, F, c=ck, h=ck if h is None else h * 2.0 ** attempt, amplify=opts.amplify,
                         r=opts.r, l=opts.l, alpha=opts.alpha, beta=opts.beta)
    # the envelope must contain the fine layer: marching cubes on a grid of spacing ~c can cut
    # through sharp features of a coarse input; and it should have the fine layer's genus (paper
    # Sec. 3.1: the amplified field separates nearly-touching parts only where the grid resolves
    # the amplified iso-level c / alpha; its "Limitation": finite SDF resolution). Refine the
    # grid (same c, at most twice) before giving up; a genus still wrong is reported.
    hk = ck if h is None else h * 2.0 ** attempt
    if h is None and len(env.F) < ENVELOPE_OVER_TARGET * n_faces:
        # a target close to the envelope's own resolution leaves few collapses, and the marching
        # cubes' slivers stay in the cage (85k-face input, 21k-face cage from a 30k-face envelope:
        # 140 faces under 1 degree, min 0.006): a finer grid, ~ENVELOPE_OVER_TARGET x the target
        # (faces ~ 1 / h^2), at most 4x finer
        h2 = hk * max(0.25, float(np.sqrt(len(env.F) / (ENVELOPE_OVER_TARGET * n_faces))))
        env2 = build_envelope(Vn, F, c=ck, h=h2, amplify=opts.amplify, r=opts.r, l=opts.l, alpha=opts.alpha,
                              beta=opts.beta)
        # ... unless the finer grid resolves a merge of two parts the coarse one did not (a handle:
        # gargo subdivided twice, genus 0 at h = c, 1 at 0.59 c): the genus comes first
        g0 = genus(env.V, env.F)
        if genus(env2.V, env2.F) == g0 or g0 != g_fine:
            env, hk = env2, h2
            env.info["refined_for_target"] = True
        else:
            env.info["refined_for_target"] = False
    return env, hk


def _envelope_step(opts, Vn, F, n_faces, ck, attempt, g_fine):
    """Step 1: an envelope that contains the fine layer, grids refined for its genus (SimplifyStuck: none)."""
    env, hk = _first_envelope(opts, Vn, F, n_faces, ck, attempt, g_fine)
    k_cross = len(cross_intersection_pairs(env.V, env.F, Vn, F))
    g_env = genus(env.V, env.F)
    tried_env = [{"h": hk, "crossings": k_cross, "genus": g_env}]
    envs = [env]
    refine = 0
    while (k_cross or g_env != g_fine) and refine < 2:
        hk *= 0.5
        refine += 1
        env = build_envelope(Vn, F, c=ck, h=hk, amplify=opts.amplify, r=opts.r, l=opts.l, alpha=opts.alpha,
                             beta=opts.beta)
        k_cross = len(cross_intersection_pairs(env.V, env.F, Vn, F))
        g_env = genus(env.V, env.F)
        tried_env.append({"h": hk, "crossings": k_cross, "genus": g_env})
        envs.append(env)
    pick = _pick_envelope(tried_env, g_fine)
    if pick is not None:
        # genus not repaired by the finer grids: the clean envelope whose genus is closest to the
        # fine layer's (the coarsest of those: fewer faces to simplify)
        env, k_cross = envs[pick], 0
        tried_env[pick]["kept"] = True
    env.info["grid_refinements"] = refine
    env.info["grids_tried"] = tried_env
    if k_cross:
        raise SimplifyStuck(f"envelope crosses the fine layer ({k_cross} pairs) even at h={hk:.3g}")
    return env


def _simplify_step(opts, env, Vn, F, n_faces, ck, sec):
    """Step 2: the envelope down to exactly ``n_faces`` faces (plain-QEM pre-pass, constrained collapses; no
    batch of collapses starts past the call's ``cage_time_budget``: the budget's up-front estimate missed a
    CAD assembly by 15x and more, the repaired box_parts.stl's 12.8k-face layer ran past 20 minutes)."""
    import igl

    U, G = env.V, env.F
    while len(G) < n_faces:  # the envelope is coarser than the target: subdivide (same surface)
        U, G = igl.upsample(U, G)
        U, G = np.asarray(U, float), np.asarray(G, np.int64)
    t = time.perf_counter()
    pre = []
    if opts.prepass:
        U, G, pre = _prepass(U, G, Vn, F, n_faces, clear=float(opts.min_gap))
    sec["prepass"] = time.perf_counter() - t
    t = time.perf_counter()
    if len(G) > n_faces:
        U, G, sinfo = constrained_simplify(U, G, Vn, F, n_faces, env.sdf,
                                           margin=max(opts.margin * ck, 2 * float(opts.min_gap)),
                                           edge_clear=float(opts.min_gap), deadline=opts.budget_deadline)
    else:
        sinfo = {"batches": 0, "collapses": 0}
    sec["simplify"] = time.perf_counter() - t
    return U, G, pre, sinfo


def _optimize_step(opts, U, G, Vn, F, ck, gap_rel, rep, hug_cache, sec):
    """Step 3: barrier-protected optimisation (spacing, MIPS, pull, flips), kept only if certified."""
    min_gap = opts.min_gap
    oinfo: dict = {"ran": False}
    h_local = None
    if opts.optimize and opts.hug > 0 and opts.amplify:
        if "points" not in hug_cache:
            hug_cache["points"] = Vn[active_points(Vn, F, opts.r, opts.l)]
        hug_pts = hug_cache["points"]
        if len(hug_pts):
            h_local = (hug_pts, opts.hug * ck, opts.hug_radius * opts.r)
    dh = min(opts.dhat, opts.hug_dhat) if h_local is not None else opts.dhat
    if opts.optimize:
        t = time.perf_counter()
        try:
            # the CCD keeps min_gap (+5%) and the barrier acts beyond it, so the optimised cage
            # can pass the same certificate as the simplified one
            U2, G2, oinfo = optimize_cage(U, G, Vn, F, h=opts.spacing * ck, dhat=max(dh * ck, 2 * min_gap),
                                          iters=opts.opt_iters, flip_rounds=opts.flip_rounds,
                                          time_limit=opts.opt_time_limit, w_p=opts.pull, pull_target=ck,
                                          min_distance=1.05 * float(min_gap), h_local=h_local)
            oinfo["ran"] = True
            if h_local is not None:
                oinfo["hug_points"] = len(h_local[0])
            rep2 = verify_nesting([(Vn, F), (U2, G2)], min_gap=gap_rel)
            oinfo["certified"] = bool(rep2.ok)
            if rep2.ok:
                U, G, rep = U2, G2, rep2
            else:  # keep the certified simplified cage
                oinfo["rejected_reason"] = rep2.pairs[0].reason
        except RuntimeError as exc:
            oinfo = {"ran": True, "certified": False, "rejected_reason": str(exc)}
        sec["optimize"] = time.perf_counter() - t
    return U, G, rep, oinfo


def _tighten_step(opts, U, G, Vn, F, env, ck, gap_rel, rep, deadline, sec):
    """Step 4: the tightening pass into the concavities the envelope bridged (not in the paper)."""
    tinfo: dict = {"ran": False}
    if opts.tighten > 0 and opts.tighten_rounds > 0:
        t = time.perf_counter()
        pull, min_gap = opts.pull, opts.min_gap
        U, G, tinfo, trep = tighten_cage(U, G, Vn, F, env.sdf, c=ck, target=opts.tighten * ck,
                                         rounds=opts.tighten_rounds, pull=pull if pull > 0 else 50.0,
                                         spacing=opts.spacing * ck,
                                         margin=max(opts.margin * ck, 2 * float(min_gap)),
                                         min_gap=float(min_gap), gap_rel=gap_rel, iters=opts.opt_iters,
                                         time_limit=opts.opt_time_limit, deadline=deadline)
        tinfo["ran"] = True
        if trep is not None:  # a kept round: its verify_nesting report certifies the returned cage
            rep = trep
        sec["tighten"] = time.perf_counter() - t
    return U, G, rep, tinfo


def _layer_info(U, G, Vn, F, n_faces, ck, attempts, env, steps, g_fine, rep, sec, t0) -> dict:
    """The layer's JSON-serialisable figures (``info`` of :func:`sdf_cage_layer`)."""
    import igl

    m = mips(U, G)
    return {
        "target": n_faces,
        "n_faces": len(G),
        "n_vertices": len(U),
        "c_used": ck,
        "attempts": attempts,
        "envelope": env.info,
        "prepass": steps["prepass"],
        "simplify": steps["simplify"],
        "optimize": {k: v for k, v in steps["optimize"].items()},
        "tighten": steps["tighten"],
        "genus_fine": g_fine,
        "genus_envelope": genus(env.V, env.F),
        "genus": genus(U, G),
        "min_angle_deg": _min_angle_deg(U, G),
        "mips_mean": float(m.mean()),
        "mips_max": float(m.max()),
        "hausdorff_relative": float(igl.hausdorff(U, G, Vn, F)),
        "volume_ratio": _signed_volume(U, G) / _signed_volume(Vn, F),
        "verification": rep.to_dict(),
        "seconds": {**sec, "total": time.perf_counter() - t0},
    }


def _bridge_retry(call, Uo, G, info, Vn, F, U, env, ck, target, t0, deadline):
    """``sdf_cage_layer``'s ``bridge_retry``: the layer again at a smaller offset where the envelope bridged."""
    from .tighten import input_to_cage

    dc = input_to_cage(Vn, F, U, G)[0]
    de = input_to_cage(Vn, F, env.V, env.F)[0]
    far = dc > target
    d_cage = float(dc.max())
    # the envelope bridged where the cage is too far: at some input vertex beyond the target from the cage,
    # the envelope is too (a layer whose misses come from its face count has the envelope within ~c there)
    d_env = float(de[far].max()) if far.any() else 0.0
    rec: dict = {"c": ck, "target": target, "input_to_cage": d_cage, "input_to_envelope_where_far": d_env,
                 "n_far": int(far.sum()), "n_far_bridged": int((far & (de > target)).sum()), "ran": False,
                 "kept": False}
    info["bridge_retry"] = rec
    if d_cage <= target or d_env <= target:
        rec["why_not"] = "within target" if d_cage <= target else "the envelope does not bridge there"
        return Uo, G, info
    c2 = ck * float(call["bridge_retry"])
    min_gap = float(call["min_gap"])
    if 4.0 * min_gap > c2:
        # the simplification keeps max(margin c, 2 min_gap) from the input: with an envelope at c2 < 4 min_gap
        # that leaves almost no feasible collapse (nestmg's TetWild clearance 2.5e-3 against c / 2 = 5e-3:
        # bunny's two layers took 204 s instead of 20 s and kept the first cages)
        rec["why_not"] = f"clearance: c * bridge_retry = {c2:.3g} < 4 min_gap = {4 * min_gap:.3g}"
        return Uo, G, info
    first = time.perf_counter() - t0
    left = np.inf if deadline is None else deadline - time.perf_counter()
    if 3.0 * first > left:
        rec["why_not"] = f"time: 3 x {first:.0f} s does not fit in the {left:.0f} s left"
        return Uo, G, info
    t = time.perf_counter()
    rec["ran"] = True
    rec["c_retry"] = c2
    # c is relative to `unit`: pass the same unit (the first call's default is V's own diagonal)
    unit = call["unit"] if call["unit"] is not None else bbox_diagonal(np.asarray(call["V"], float))
    args = {**call, "c": c2, "unit": unit, "bridge_retry": 0.0, "check_input": False,
            "cage_time_budget": None,
            "deadline": deadline, "max_retries": 0}
    try:
        U2o, G2, info2 = sdf_cage_layer(**args)
    except (CageError, RuntimeError) as exc:
        rec.update(reason=f"retry failed: {exc}", seconds=time.perf_counter() - t)
        info["seconds"].update(bridge_retry=rec["seconds"], total=time.perf_counter() - t0)
        return Uo, G, info
    d2 = float(input_to_cage(np.asarray(call["V"], float), F, U2o, G2)[0].max()) / unit  # both in user units
    h1, h2 = info["hausdorff_relative"], info2["hausdorff_relative"]
    rec.update(input_to_cage_retry=d2, genus_retry=info2["genus"], hausdorff=h1, hausdorff_retry=h2,
               seconds=time.perf_counter() - t)
    # certified inside the call; kept only if it keeps the first cage's genus and is tighter both ways (the
    # symmetric Hausdorff distance: a smaller offset can leave faces farther out elsewhere on a coarse cage)
    if info2["genus"] == info["genus"] and d2 < d_cage and h2 < h1:
        rec["kept"] = True
        info2["bridge_retry"] = rec
        info2["seconds"]["bridge_retry_first_build"] = first
        info2["seconds"]["total"] = time.perf_counter() - t0
        return U2o, G2, info2
    rec["reason"] = (f"genus {info2['genus']} != {info['genus']}" if info2["genus"] != info["genus"]
                     else "not tighter")
    # the layer's time includes the retry it did not keep
    info["seconds"].update(bridge_retry=rec["seconds"], total=time.perf_counter() - t0)
    return Uo, G, info


def sdf_schedule(V: np.ndarray, F: np.ndarray, face_counts, *, t0: float,
                 cage_time_budget: float | None = DEFAULT_TIME_BUDGET, **layer_opts) -> list[dict]:
    """The ``"sdf"`` backend's run plan (registry ``schedule``): checked before any layer is built.

    The face counts must be even; the whole run's estimate (:func:`estimate_layer_seconds` of each layer's
    input) must fit ``cage_time_budget`` (else :class:`CageError`, ``reason="time budget"``, in milliseconds).
    Each layer then runs without a budget of its own but with a deadline after which no tightening round
    starts: the run's budget less the estimates of the layers after it (the layers themselves always
    run: the budget was checked first).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        The audited input.
    face_counts : sequence of int
        Exact (even) face counts of the cages, finest first.
    t0 : float
        ``time.perf_counter()`` at the start of the run.
    cage_time_budget : float or None
        Wall-clock seconds for all the layers (None: no limit).
    **layer_opts
        The other options (each layer's; unused here).

    Returns
    -------
    list of dict
        Per layer, the keywords of :func:`sdf_cage_layer` the run sets (``deadline``, ``cage_time_budget``,
        ``check_input``).
    """
    counts = [_check_target(m) for m in face_counts]
    budget_check(len(F), counts, cage_time_budget=cage_time_budget)
    later = [sum(estimate_layer_seconds(n) for n in counts[k:-1]) for k in range(len(counts))]
    # check_input False: build_cages audited the input once, the later layers are certified cages
    return [{"cage_time_budget": None, "check_input": False,
             "deadline": None if cage_time_budget is None else t0 + float(cage_time_budget) - rest}
            for rest in later]
