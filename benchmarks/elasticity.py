"""Linear elasticity (issue 32): nestmg MG-PCG against the AMG setups elasticity users tune.

For every mesh, Poisson ratio and problem (``elasticity-clamped``: lowest-x band fixed, gravity;
``elasticity-free``: pure traction, balanced body force, six rigid-body modes in the kernel) the fine
system is assembled once (:func:`nestmg.elasticity.setup_elasticity`, E = 1, normalised shape, P1 vector,
interleaved dofs) and solved from zero to ``||b - A x|| <= tol ||b||`` by CG with:

``nestmg``        the project's default: the hierarchy's prolongations restricted to the free nodes,
                  ``P ⊗ I₃``, Galerkin coarse operators, ``SolverOptions.resolved``'s smoothing and cycle
                  (since issue 32 item 2: the F-cycle with two forward / backward Gauss–Seidel sweeps on
                  the fine level, three from ν = 0.4, and four below; before, files up to
                  ``default_cycle_fandisk_173k.json``: the V-cycle with one symmetric sweep on the fine
                  level and two below, today's ``nestmg_v``, with a W-cycle rule at ν >= 0.4 for a while
                  in between); the free problem projects the rigid modes (``NullspaceMultigridSolver``).
                  Setup = restriction + ``P ⊗ I₃`` + ``multigrid()``; the cycle run is recorded (``cycle``).
``nestmg_block``  the same with nodal 3x3 block Gauss–Seidel (multicolour; ``multigrid(block=True)``).
``nestmg_point``  (not run by default) the same configuration as ``nestmg``; in
                  ``elasticity_300k.json`` it ran beside it (a measure of run-to-run spread) and ``--table``
                  leaves it out.
``nestmg_no_deflation``, ``nestmg_deflate_all``, ``nestmg_deflate_all16``  (not run by default) ``nestmg``
                  with ``deflate=0`` (no deflation probe), and with every level probed, the finest
                  included (``probe_finest=True``, ``deflate=8`` / ``16`` slow modes at most per level;
                  :mod:`solvers.deflation`); their records hold the probe reports (``deflation``).
                  ``--factor`` adds every nestmg variant's stationary V-cycle factor (first repeat).
``nestmg_v``      (not run by default) the V-cycle with one symmetric sweep on the fine level and two
                  below at every ν.
``nestmg_v02``    (not run by default) ``nestmg_v`` with the clamped problem's coarse nodes pruned at column
                  sum 0.2 instead of ``CLAMPED_PRUNE`` = 0.35: ``nestmg`` before issue 32 item 2.
``nestmg_w``, ``nestmg_w2``, ``nestmg_w24``  (not run by default) ``nestmg`` preconditioned by a W-cycle
                  with given symmetric Gauss–Seidel smoothers: one sweep on the fine level and two below,
                  two on every level, and two on the fine level and four below (what ``cycle="W"`` got at
                  ν >= 0.4 before issue 32 item 2).
``nestmg_v24``    (not run by default) the V-cycle with two symmetric sweeps on the fine level and four below.
``nestmg_f24``, ``nestmg_f34``  (not run by default) the F-cycle with two / three forward Gauss–Seidel
                  sweeps on the fine level and four below (backward after the coarse correction): the
                  default below / from ν = 0.4.
``pyamg_sa_rbm``  pyamg smoothed aggregation on the BSR (3x3) matrix with the six rigid-body modes of the
                  free nodes as ``B`` (pyamg's defaults otherwise: symmetric strength, standard aggregation,
                  Jacobi-smoothed prolongation, block Gauss–Seidel smoothing, pinv coarse solve).
``pyamg_sa``      pyamg SA on the CSR matrix without ``B`` (constants per dof), for reference.
``gamg_rbm``      PETSc CG + GAMG (smoothed aggregation, PETSc's defaults), block size 3 and the near
                  null space ``MatNullSpaceCreateRigidBody`` of the free nodes' coordinates; the free
                  problem also attaches it as the null space. 1 rank; matrix copy counted as setup.
``gamg_rbm_thr``  the same with ``-pc_gamg_threshold 0.01`` (drop weak graph edges: the usual tuning;
                  fewer iterations and a cheaper setup than the default on a 77k-tet torus).
``hypre_nodal``   (not run by default) PETSc CG + hypre BoomerAMG with nodal coarsening (``nodal_coarsen
                  6``) and the rigid modes as interpolation vectors (``vec_interp_variant 2``), block size
                  3. Measured on a 77k-tet torus (45k unknowns): 10 s setup and 60 s solve (43 iterations);
                  with ``strong_threshold 0.6`` and ``agg_nl 1``, 2 + 18 s (64): far behind the others.

For the singular free problem, pyamg's cycle preconditions the project's CG (``solvers.krylov.pcg``) with
its input and output projected off the rigid modes, as nestmg's; solutions are compared after the same
projection. Each method is run ``--repeat`` times (interleaved; ``--once`` methods on the first repeat
only); the wall (``time.perf_counter``) and CPU (``time.process_time``) seconds of its setup and solve in
every run are kept (``setup_seconds``, ``setup_cpu_seconds``, ...) with their medians (``median_total``,
``median_total_cpu``, ...). Tables compare CPU seconds (a file without them: wall): on the 2 shared cores
the wall seconds of one single-threaded process swing with the load (2.5x its CPU seconds at load 6), the
CPU seconds much less. The hierarchy (cages, tet meshing) is geometry reused from the cache: its build
time is recorded but not counted (AMG needs none). Run with ``OMP_NUM_THREADS=1``::

    OMP_NUM_THREADS=1 python benchmarks/elasticity.py shape:torus ZOO_DIR/bunny.off ZOO_DIR/spot.obj \\
        --max-tets 300000 --nu 0.3 0.45 --out benchmarks/results/elasticity/elasticity_300k.json

Prints one line per run and a table; writes the JSON (``--out``). ``--table JSON`` only prints the
Markdown table of a result file (docs/elasticity.md).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

#: multigrid() keywords of the deflation variants of ``nestmg`` (issue 32)
DEFLATION_VARIANTS = {"nestmg_no_deflation": {"deflate": 0},
                      "nestmg_deflate_all": {"deflate": 8, "probe_finest": True},
                      "nestmg_deflate_all16": {"deflate": 16, "probe_finest": True}}
_SGS = "symmetric_gauss_seidel"
#: (multigrid() keywords, cycle) of the cycle variants of ``nestmg`` (issue 32, ν = 0.45): smoothers and
#: cycle given, independent of the defaults (``nestmg_v``, ``nestmg_w``: one fine sweep, two below)
CYCLE_VARIANTS = {"nestmg_v": ({"presmoother": [(_SGS, {"iterations": 1}), (_SGS, {"iterations": 2})]}, "V"),
                  "nestmg_w": ({"presmoother": [(_SGS, {"iterations": 1}), (_SGS, {"iterations": 2})]}, "W"),
                  "nestmg_w2": ({"presmoother": [("symmetric_gauss_seidel", {"iterations": 2})]}, "W"),
                  "nestmg_w24": ({"presmoother": [("symmetric_gauss_seidel", {"iterations": 2}),
                                                  ("symmetric_gauss_seidel", {"iterations": 4})]}, "W"),
                  "nestmg_v24": ({"presmoother": [("symmetric_gauss_seidel", {"iterations": 2}),
                                                  ("symmetric_gauss_seidel", {"iterations": 4})]}, "V")}
CYCLE_VARIANTS["nestmg_v02"] = CYCLE_VARIANTS["nestmg_v"]
_GS = "gauss_seidel"  # forward before the coarse correction, backward after it (the adjoint)
CYCLE_VARIANTS.update({f"nestmg_f{k}4": ({"presmoother": [(_GS, {"iterations": k}),
                                                          (_GS, {"iterations": 4})]}, "F") for k in (2, 3)})
#: clamped-problem prune (``min_column_sum``) of variants that do not use the problem's own
PRUNE_VARIANTS = {"nestmg_v02": 0.2}
METHODS = ("nestmg", "nestmg_block", "nestmg_point", *DEFLATION_VARIANTS, *CYCLE_VARIANTS, "pyamg_sa_rbm",
           "pyamg_sa",
           "gamg_rbm", "gamg_rbm_thr", "hypre_nodal")
DEFAULT_METHODS = ("nestmg", "nestmg_block", "pyamg_sa_rbm", "pyamg_sa", "gamg_rbm", "gamg_rbm_thr")
#: references run once (first repeat only): they are far from the others and slow
ONCE = ("pyamg_sa",)
#: PETSc options of the variants beyond block size and near null space
PETSC_VARIANTS = {"gamg_rbm": ("gamg", {}), "gamg_rbm_thr": ("gamg", {"pc_gamg_threshold": 0.01}),
                  "hypre_nodal": ("hypre", {})}
PROBLEMS = ("elasticity-clamped", "elasticity-free")


def load_surface(spec: str) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface: ``shape:NAME`` (:data:`nestmg.shapes.SHAPES`, as the CLI) or a mesh file."""
    from nestmg.io import load_mesh
    from nestmg.shapes import SHAPES

    if spec.startswith("shape:"):
        return SHAPES[spec.split(":", 1)[1]](res=24)
    return load_mesh(Path(spec))


class _clocks:
    """Wall (``time.perf_counter``) and CPU (``time.process_time``) seconds of consecutive phases:
    ``lap(name)`` stores ``times[name]`` (wall) and ``times[name + "_cpu"]`` since the previous lap."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self._wall, self._cpu = time.perf_counter(), time.process_time()

    def lap(self, name: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.times[name], self.times[name + "_cpu"] = wall - self._wall, cpu - self._cpu
        self._wall, self._cpu = wall, cpu


def _projector(Z: np.ndarray | None):
    """``v -> v - Q Qᵀ v`` for an orthonormal basis ``Q`` of ``span Z`` (identity for ``Z`` None)."""
    if Z is None:
        return lambda v: v
    Q = np.linalg.qr(Z)[0]
    return lambda v: v - Q @ (Q.T @ v)


def run_nestmg(pr, h_P, block: bool, tol: float, mg_kwargs: dict | None = None, factor: bool = False,
               cycle: str | None = None, prune: float | None = None) -> dict:
    """Setup (restriction + ``P ⊗ I₃`` + ``multigrid(**mg_kwargs)``) and MG-PCG of the assembled problem
    ``pr`` preconditioned by one ``cycle`` (None: the solver's default, ``ml.cycle``); with ``factor`` also
    the stationary factor of that cycle (:func:`vcycle_factor`, not timed). ``prune``: the clamped
    problem's ``min_column_sum`` instead of its own (the free problem keeps 0)."""
    from solvers import block_prolongation, restrict_prolongations

    t = _clocks()
    if prune is None or pr.modes is not None:
        prune = pr.params["prune"]
    Pr, _ = restrict_prolongations(h_P, pr.free[0], min_column_sum=prune)
    pr.P = [block_prolongation(P) for P in Pr]  # the same matrices as setup_elasticity's, rebuilt and timed
    ml = pr.multigrid(block=block, **(mg_kwargs or {}))
    t.lap("setup")
    cycle = ml.cycle if cycle is None else cycle
    x, info = ml.solve(pr.b, tol=tol, maxiter=500, cycle=cycle, accel="cg", return_info=True)
    t.lap("solve")
    out = {"x": x, **t.times, "iterations": info["iterations"], "cycle": cycle,
           "residuals": info["residuals"],  # relative, per CG iteration (the last: the true one)
           "operator_complexity": ml.operator_complexity(), "levels": [L.A.shape[0] for L in ml.levels],
           "prune": prune, "coarse_solver": getattr(ml._coarse_solver, "method", None),
           "smoother": ml.levels[0].presmoother.params,
           "deflation": [{k: d[k] for k in ("level", "probe_factor", "vectors", "factors", "cycles")}
                         | {k: d[k] for k in ("probe_after", "slow_modes_found", "reverted") if k in d}
                         for d in ml.deflation]}
    if factor:
        out["vcycle_factor"] = vcycle_factor(ml, cycle=cycle)
    return out


def vcycle_factor(ml, cycles: int = 20, last: int = 5, cycle: str = "V") -> float:
    """Stationary factor of ``cycle`` (default the V-cycle): energy-norm error reduction per cycle on
    ``A e = 0`` from a random start, geometric mean of the ``last`` of ``cycles`` cycles (kernel of a free
    problem projected out)."""
    A = ml.levels[0].A
    Q = getattr(ml, "nullspace_bases", [None])[0]
    e = np.random.default_rng(0).standard_normal(A.shape[0])
    zero = np.zeros_like(e)
    norms = []
    for _ in range(cycles):
        if Q is not None:
            e -= Q @ (Q.T @ e)
        ml._cycle(0, e, zero, cycle)
        norms.append(float(np.sqrt(max(e @ (A @ e), 0.0))))
    return float((norms[-1] / norms[-1 - last]) ** (1.0 / last))


def run_pyamg(A, b, B: np.ndarray | None, Z: np.ndarray | None, tol: float) -> dict:
    """pyamg SA + CG: with ``B`` (the rigid modes) on the BSR matrix, or plain on the CSR one (``B`` None).
    ``Z``: the kernel of a singular ``A`` (projected off the preconditioner's input and output), or None."""
    import pyamg

    from solvers.krylov import pcg

    proj = _projector(Z)
    t = _clocks()
    ml = (pyamg.smoothed_aggregation_solver(A.tobsr(blocksize=(3, 3)), B=B) if B is not None
          else pyamg.smoothed_aggregation_solver(A))
    M = ml.aspreconditioner(cycle="V")
    t.lap("setup")
    Mp = M if Z is None else _projected_operator(M, proj)
    r = pcg(A, b, M=Mp, tol=tol, maxiter=500)
    t.lap("solve")
    return {"x": proj(r.x), **t.times, "iterations": r.iterations,
            "operator_complexity": float(ml.operator_complexity()),
            "levels": [L.A.shape[0] for L in ml.levels]}


def _projected_operator(M, proj):
    import scipy.sparse.linalg as spla

    return spla.LinearOperator(M.shape, matvec=lambda v: proj(M.matvec(proj(np.asarray(v).ravel()))),
                               dtype=np.float64)


def run_petsc(A, b, coords: np.ndarray, free_problem: bool, kind: str, tol: float,
              extra: dict | None = None) -> dict:
    """PETSc CG + GAMG or hypre BoomerAMG with block size 3 and the rigid-body near null space
    (``extra``: more PETSc options, without the prefix)."""
    from solvers.petsc_common import _petsc

    PETSc = _petsc()
    it = PETSc.IntType
    t = _clocks()
    csr = (A.indptr.astype(it), A.indices.astype(it), A.data)
    mat = PETSc.Mat().createAIJ(size=A.shape, bsize=3, csr=csr, comm=PETSc.COMM_SELF)
    mat.assemble()
    xyz = PETSc.Vec().createWithArray(np.ascontiguousarray(coords).ravel(), bsize=3, comm=PETSc.COMM_SELF)
    ns = PETSc.NullSpace().createRigidBody(xyz)
    mat.setNearNullSpace(ns)
    if free_problem:
        mat.setNullSpace(ns)
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOptionsPrefix(f"el_{kind}_")
    ksp.setOperators(mat)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setTolerances(rtol=tol, atol=1e-300, max_it=500)
    pc = ksp.getPC()
    opts = PETSc.Options()
    if kind == "gamg":
        pc.setType("gamg")
        pc.setGAMGType(PETSc.PC.GAMGType.AGG)
        if free_problem:  # the coarsest operator is singular too: shift zero pivots of its LU
            opts[f"el_{kind}_mg_coarse_sub_pc_factor_shift_type"] = "nonzero"
    else:
        pc.setType("hypre")
        pc.setHYPREType("boomeramg")
        opts[f"el_{kind}_pc_hypre_boomeramg_nodal_coarsen"] = 6
        opts[f"el_{kind}_pc_hypre_boomeramg_vec_interp_variant"] = 2
    for k, v in (extra or {}).items():
        opts[f"el_{kind}_{k}"] = v
    ksp.setFromOptions()
    ksp.setUp()
    t.lap("setup")
    xv, bv = mat.createVecs()
    bv.setArray(b)
    xv.set(0.0)
    ksp.solve(bv, xv)
    x = xv.getArray().copy()
    t.lap("solve")
    its, reason = ksp.getIterationNumber(), int(ksp.getConvergedReason())
    for k in list(opts.getAll()):
        if k.startswith(f"el_{kind}_"):
            del opts[k]
    for obj in (xv, bv, pc, ksp, mat, ns, xyz):  # the PC too: without it GAMG's hierarchy outlived every run
        obj.destroy()
    return {"x": x, **t.times, "iterations": int(its), "reason": reason}


_RUN_KEYS = ("setup", "solve", "setup_cpu", "solve_cpu", "iterations", "final_residual", "converged")


def run_case(pr, h_P, coords, methods, tol: float, repeat: int, factor: bool = False,
             once=ONCE) -> dict:
    """All methods on one assembled problem, ``repeat`` interleaved runs each (``once``: first only)."""
    # benchmarks/ is sys.path[0]; imported late so doc_tables can load this file
    from exp_common import relres

    from solvers import rigid_body_modes

    free_problem = pr.modes is not None
    Z = pr.modes[0] if free_problem else None
    B = rigid_body_modes(coords)
    proj = _projector(Z)
    runs: dict = {m: [] for m in methods}
    sols: dict = {}
    for r in range(repeat):
        for m in methods:
            if r and m in once:
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if m.startswith("nestmg"):
                    kw, cyc = CYCLE_VARIANTS.get(m, (DEFLATION_VARIANTS.get(m), None))
                    out = run_nestmg(pr, h_P, m == "nestmg_block", tol, kw, factor=factor and r == 0,
                                     cycle=cyc, prune=PRUNE_VARIANTS.get(m))
                elif m in ("pyamg_sa_rbm", "pyamg_sa"):
                    out = run_pyamg(pr.A, pr.b, B if m == "pyamg_sa_rbm" else None, Z, tol)
                else:
                    kind, extra = PETSC_VARIANTS[m]
                    out = run_petsc(pr.A, pr.b, coords, free_problem, kind, tol, extra)
            x = proj(out.pop("x"))
            out["final_residual"] = relres(pr.A, pr.b, x)
            out["converged"] = out["final_residual"] <= tol * 1.01
            runs[m].append(out)
            sols[m] = x
            print(f"    {m:<13} rep {r}: setup {out['setup']:.2f} s (CPU {out['setup_cpu']:.2f}), solve "
                  f"{out['solve']:.2f} s (CPU {out['solve_cpu']:.2f}), "
                  f"{out['iterations']} it, residual {out['final_residual']:.1e}"
                  + (f", V-cycle factor {out['vcycle_factor']:.3f}" if "vcycle_factor" in out else ""),
                  file=sys.stderr, flush=True)
    ref = sols[methods[0]]
    res = {}
    for m in methods:
        setup, solve = ([o[k] for o in runs[m]] for k in ("setup", "solve"))
        setup_cpu, solve_cpu = ([o[k] for o in runs[m]] for k in ("setup_cpu", "solve_cpu"))
        last = runs[m][-1]
        res[m] = {"setup_seconds": setup, "solve_seconds": solve,
                  "median_setup": float(np.median(setup)), "median_solve": float(np.median(solve)),
                  "median_total": float(np.median(np.add(setup, solve))),
                  "setup_cpu_seconds": setup_cpu, "solve_cpu_seconds": solve_cpu,
                  "median_setup_cpu": float(np.median(setup_cpu)),
                  "median_solve_cpu": float(np.median(solve_cpu)),
                  "median_total_cpu": float(np.median(np.add(setup_cpu, solve_cpu))),
                  "iterations": last["iterations"], "final_residual": last["final_residual"],
                  "converged": all(o["converged"] for o in runs[m]),
                  "max_diff_vs_first_rel": float(np.abs(sols[m] - ref).max() / np.abs(ref).max()),
                  **{k: v for k, v in last.items() if k not in _RUN_KEYS},
                  **{k: runs[m][0][k] for k in ("vcycle_factor",) if k in runs[m][0]}}  # first repeat only
    return res


def run_mesh(spec: str, max_tets: int, edge: float | None, levels: int, nus, problems, methods, tol: float,
             repeat: int, factor: bool = False, once=ONCE) -> dict:
    from exp_common import peak_rss_mb

    import nestmg
    from nestmg.elasticity import setup_elasticity

    V, F = load_surface(spec)
    t0 = time.perf_counter()
    h = nestmg.build_hierarchy(V, F, levels, "nested", sizing=nestmg.SizingOptions(max_tets=max_tets,
                                                                                   edge_length=edge),
                               cache=True, progress=False)
    load_s = time.perf_counter() - t0
    tets = h.tets_in("normalized")
    rec = {"mesh": Path(spec).name if not spec.startswith("shape:") else spec, "max_tets": max_tets,
           "edge_length": edge,
           "tets": [len(T) for _, T in tets], "nodes": [len(Vk) for Vk, _ in tets], "certified": h.certified,
           "n_outside": h.n_outside, "hierarchy_seconds": h.timings, "hierarchy_load_seconds": load_s,
           "cases": []}
    print(f"{rec['mesh']}: tets {rec['tets']}", file=sys.stderr, flush=True)
    for nu in nus:
        for name in problems:
            t0 = time.perf_counter()
            pr = setup_elasticity(tets, h.P, name, nu=nu)
            t_asm = time.perf_counter() - t0
            coords = np.asarray(tets[0][0])[pr.free[0]]
            print(f"  {name} nu={nu}: {pr.A.shape[0]} unknowns, nnz {pr.A.nnz}", file=sys.stderr, flush=True)
            rec["cases"].append({"problem": name, "nu": nu, "unknowns": int(pr.A.shape[0]),
                                 "nnz": int(pr.A.nnz),
                                 "assembly_seconds": t_asm, "clamped_nodes": int(len(pr.fixed)),
                                 "methods": run_case(pr, h.P, coords, methods, tol, repeat, factor, once),
                                 "peak_rss_mb_so_far": peak_rss_mb()})
    return rec


def table(res: dict) -> str:
    """Markdown table: median setup + solve seconds (iterations) per method, and the best AMG / nestmg
    (and / every cycle variant run). CPU seconds when the file has them, else wall seconds (older files).

    A run whose true residual is above ``tol`` (CG's recursive residual reached it: round-off on an
    ill-conditioned system) is marked ``*``, one above ``10 tol`` (not converged) ``✗``; the ratio takes
    the AMG runs below ``10 tol``. The reference is ``nestmg`` (in files where ``nestmg`` was the block
    variant, ``nestmg_point``); a ``nestmg_point`` column that repeats a point-wise ``nestmg`` is left out.
    """
    methods = res["params"]["methods"]
    tol = res["params"]["tol"]
    first = res["meshes"][0]["cases"][0]["methods"]
    block_ref = "nestmg_point" in first and "blocksize" in first["nestmg"].get("smoother", {})
    ref = "nestmg_point" if block_ref else "nestmg"
    if ref == "nestmg":  # a "nestmg_point" run beside a point-wise "nestmg" repeats the same configuration
        methods = [m for m in methods if m != "nestmg_point"]
    sfx = _clock(res)
    refs = [ref] + [m for m in methods if m in CYCLE_VARIANTS]  # a ratio column for every cycle variant too
    head = ("| mesh | fine tets | unknowns | problem | ν | " + " | ".join(methods)
            + "".join(f" | best AMG / {r}{' (CPU s)' if sfx else ''}" for r in refs) + " |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for rec in res["meshes"]:
        for c in rec["cases"]:
            ms = c["methods"]
            cells = [f"{ms[m]['median_setup' + sfx]:.2f} + {ms[m]['median_solve' + sfx]:.2f} "
                     f"({ms[m]['iterations']})" + _mark(ms[m]["final_residual"], tol) for m in methods]
            amg = [ms[m]["median_total" + sfx] for m in methods
                   if not m.startswith("nestmg") and ms[m]["final_residual"] <= 10 * tol]
            ratios = [f"{min(amg) / ms[r]['median_total' + sfx]:.2f}" if amg and r in ms else "–"
                      for r in refs]
            lines.append(f"| {rec['mesh']} | {rec['tets'][0]:,} | {c['unknowns']:,} | {c['problem'][11:]} | "
                         f"{c['nu']} | " + " | ".join(cells + ratios) + " |")
    return "\n".join(lines)


def cycles_table(res: dict) -> str:
    """Markdown table of the cycle variants (``--methods nestmg nestmg_w nestmg_w2 gamg_rbm ... --factor``):
    per case and nestmg variant, median setup + solve seconds (MG-PCG iterations), the stationary factor of
    its cycle, its total against ``nestmg`` and the best AMG's total against it (same run)."""
    variants = [m for m in res["params"]["methods"] if m == "nestmg" or m in CYCLE_VARIANTS]
    amgs = [m for m in res["params"]["methods"] if not m.startswith("nestmg")]
    tol = res["params"]["tol"]
    sfx = _clock(res)
    head = ("| mesh | fine tets | problem | ν | variant | setup + solve s (it) | cycle factor "
            "| total / nestmg | best AMG s (it) | best AMG / variant |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for rec in res["meshes"]:
        for c in rec["cases"]:
            ms = c["methods"]
            ok = [m for m in amgs if ms[m]["final_residual"] <= 10 * tol]
            tot = "median_total" + sfx
            best = min(ok, key=lambda m: ms[m][tot]) if ok else None
            cell = (f"{ms[best][tot]:.2f} ({ms[best]['iterations']}, {best})" if best else "–")
            for m in variants:
                o = ms[m]
                ratio = f"{ms[best][tot] / o[tot]:.2f}" if best else "–"
                lines.append(f"| {rec['mesh']} | {rec['tets'][0]:,} | {c['problem'][11:]} | {c['nu']} "
                             f"| {m} | {o['median_setup' + sfx]:.2f} + {o['median_solve' + sfx]:.2f} "
                             f"({o['iterations']}){_mark(o['final_residual'], tol)} | "
                             f"{o['vcycle_factor']:.3f} | "
                             f"{o[tot] / ms['nestmg'][tot]:.2f} | {cell} | {ratio} |")
    return "\n".join(lines)


def _clock(res: dict) -> str:
    """Key suffix of the seconds a table compares: ``"_cpu"`` (CPU seconds) when the file has them (runs
    since CPU seconds were recorded), else ``""`` (wall seconds of older files)."""
    ms = res["meshes"][0]["cases"][0]["methods"]
    return "_cpu" if all("median_total_cpu" in o for o in ms.values()) else ""


def _mark(residual: float, tol: float) -> str:
    return "" if residual <= 1.01 * tol else (" *" if residual <= 10 * tol else " ✗")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="*", help="closed surface files or shape:NAME")
    ap.add_argument("--table", type=Path, default=None, help="only print the Markdown table of this JSON")
    ap.add_argument("--max-tets", type=int, nargs="+", default=[300_000],
                    help="fine tets of the hierarchy, one value or one per mesh (default 300000)")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.45], help="Poisson ratios")
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=METHODS)
    ap.add_argument("--edge-length", type=float, nargs="+", default=None,
                    help="fine edge / bounding-box diagonal, one per mesh (overrides --max-tets' sizing)")
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--factor", action="store_true",
                    help="also the nestmg variants' stationary V-cycle factor")
    ap.add_argument("--once", nargs="+", default=list(ONCE), choices=METHODS,
                    help=f"methods run on the first repeat only (default {' '.join(ONCE)})")
    ap.add_argument("--out", type=Path, default=None, help="JSON file (required unless --table)")
    a = ap.parse_args(argv)
    if a.table is not None:
        import json

        print(table(json.loads(a.table.read_text())))
        return 0
    if not a.meshes or a.out is None:
        ap.error("give at least one mesh and --out (or --table JSON)")
    if len(a.max_tets) not in (1, len(a.meshes)):
        raise SystemExit(f"--max-tets needs one value or one per mesh ({len(a.meshes)})")
    if a.edge_length is not None and len(a.edge_length) != len(a.meshes):
        raise SystemExit(f"--edge-length needs one value per mesh ({len(a.meshes)})")
    from exp_common import environment, git_commit, write_json

    from solvers.petsc_common import petsc_available

    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("warning: OMP_NUM_THREADS is not 1: CPU seconds then add up several threads' work",
              file=sys.stderr)
    methods = [m for m in a.methods if petsc_available() or m not in PETSC_VARIANTS]
    res = {"params": {"tol": a.tol, "repeat": a.repeat, "once": a.once, "levels": a.levels,
                      "methods": methods,
                      "command": " ".join(["benchmarks/elasticity.py"]
                                          + [Path(x).name if Path(x).exists() else x for x in sys.argv[1:]]),
                      "commit": git_commit(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
                      "seconds": "CPU (time.process_time, *_cpu keys) and wall (time.perf_counter) per "
                                 "phase; median of the repeats; the table compares CPU seconds"},
           "environment": environment(), "meshes": []}
    mt = a.max_tets * len(a.meshes) if len(a.max_tets) == 1 else a.max_tets
    edges = a.edge_length or [None] * len(a.meshes)
    for spec, n, edge in zip(a.meshes, mt, edges):
        res["meshes"].append(run_mesh(spec, n, edge, a.levels, a.nu, a.problems, methods, a.tol, a.repeat,
                                      a.factor, a.once))
        write_json(res, a.out)  # after every mesh: a cut-off run keeps what it measured
    res["environment_end"] = environment()
    res["table"] = table(res)
    write_json(res, a.out)
    print(res["table"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
