"""Elasticity V-cycle factors on procedural nested hierarchies (issue 32): what limits them.

Clamped elasticity (``setup_elasticity(..., "elasticity-clamped")``: boundary nodes within 5 % of the x
extent from the lowest x fixed, E = 1) on hierarchies built without cages or meshers:

``ball``          ``nestmg.shapes.ball_tets(4)``, its three finest levels (82k / 10k / 1.3k tets): a thick
                  shape every level resolves. Prolongations barycentric (see below).
``ball_midpoint`` the same meshes with the helper's own prolongations: red refinement's midpoint rule, which
                  is *not* exact for linear fields once the new boundary nodes are projected onto the
                  sphere, so ``P ⊗ I₃`` does not reproduce rotations at the boundary.
``torus``         ``torus_tets(3, segments=16)``, three finest levels (147k / 18k / 2.3k tets; the coarsest
                  has two tets across the tube's radius), barycentric prolongations.
``torus_4levels`` the same plus the 288-tet level (one tet across the radius).
``torus_coarse``  ``torus_tets(3, segments=8)``, three finest levels (74k / 9k / 1.2k tets: the coarsest
                  has 16 prisms around the ring).
``cube``          ``solvers.gallery.kuhn_cube_hierarchy(16, 4)``: Kuhn cubes 16³ / 8³ / 4³ / 2³, exactly
                  nested, clamped at x = 0.

Barycentric prolongations: each fine node's barycentric coordinates in the coarse tet holding it, linearly
extrapolated for the projected boundary nodes just outside (``nestmg.prolongation``, ``"linear"``): exact
for linear fields, hence for rigid motions.

Cycles (symmetric Gauss–Seidel, point-wise; "k / m": k sweeps before and after the coarse correction on
the fine level, m on the coarser ones):

``default``   V-cycle, 1 / 2 (the pipeline's variable V-cycle; ``ElasticityProblem.multigrid()`` until the
              F-cycle with forward / backward sweeps became elasticity's default, issue 32 item 2)
``V2``        V-cycle, 2 / 2          ``V2c8``  V-cycle, 2 / 8          ``W2``  W-cycle, 2 / 2
``twogrid1``  two levels, 1 sweep, exact coarse solve of level 1 (the limit of any cycle with 1 fine sweep)
``twogrid2``  the same with 2 sweeps

Per case: the stationary factor (energy norm, ``A e = 0`` from a seeded random start, geometric mean of
the last 10 of 40 cycles: the slowest mode's rate), MG-PCG iterations to ``1e-8`` (right-hand side: the
problem's gravity load) and CPU seconds per cycle (``time.process_time``, median of 5 cycles)::

    OMP_NUM_THREADS=1 python benchmarks/elasticity_factor.py \\
        --out benchmarks/results/elasticity/factor_procedural.json
    python benchmarks/elasticity_factor.py --table benchmarks/results/elasticity/factor_procedural.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HIERARCHIES = ("ball", "ball_midpoint", "torus", "torus_4levels", "torus_coarse", "cube")
CYCLES = ("default", "V2", "V2c8", "W2", "twogrid1", "twogrid2")


def _sgs(n: int) -> tuple[str, dict]:
    return ("symmetric_gauss_seidel", {"iterations": n})


#: cycle name -> (smoother specs per level or None for the problem's default, cycle, levels used or None)
CYCLE_SPECS = {"default": ([_sgs(1), _sgs(2)], "V", None), "V2": ([_sgs(2)], "V", None),
               "V2c8": ([_sgs(2), _sgs(8)], "V", None), "W2": ([_sgs(2)], "W", None),
               "twogrid1": ([_sgs(1)], "V", 2), "twogrid2": ([_sgs(2)], "V", 2)}


def barycentric_prolongations(meshes: list) -> list:
    """Nodal prolongations ``meshes[k+1] -> meshes[k]`` by barycentric coordinates (linear extrapolation
    for fine nodes outside the coarse mesh): exact for every linear field, hence for rigid motions."""
    from nestmg.prolongation import prolongation

    return [prolongation(meshes[k][0], *meshes[k + 1], extrapolation="linear")[0]
            for k in range(len(meshes) - 1)]


def hierarchy(name: str) -> tuple[list, list]:
    """Tet meshes (finest first) and nodal prolongations of one procedural hierarchy (module docstring)."""
    from nestmg.shapes import ball_tets, torus_tets
    from solvers.gallery import kuhn_cube_hierarchy

    if name == "cube":
        return kuhn_cube_hierarchy(16, 4)
    if name.startswith("ball"):
        meshes, P = ball_tets(4)
    else:
        meshes, P = torus_tets(3, segments=8 if name == "torus_coarse" else 16)
    n = 4 if name == "torus_4levels" else 3
    meshes, P = meshes[:n], P[:n - 1]
    return meshes, (P if name == "ball_midpoint" else barycentric_prolongations(meshes))


def stationary_factor(ml, cycle: str, cycles: int = 40, last: int = 10) -> float:
    """Energy-norm error reduction per cycle on ``A e = 0`` (seeded random start), geometric mean of the
    ``last`` of ``cycles`` cycles."""
    A = ml.levels[0].A
    e = np.random.default_rng(0).standard_normal(A.shape[0])
    zero = np.zeros_like(e)
    norms = []
    for _ in range(cycles):
        ml._cycle(0, e, zero, cycle)
        norms.append(float(np.sqrt(max(e @ (A @ e), 0.0))))
    return float((norms[-1] / norms[-1 - last]) ** (1.0 / last))


def run_cycle(pr, name: str) -> dict:
    """Factor, MG-PCG iterations and CPU seconds per cycle of one cycle variant on problem ``pr``."""
    from solvers import MultigridSolver

    spec, cycle, levels = CYCLE_SPECS[name]
    if levels is None:
        ml = pr.multigrid() if spec is None else pr.multigrid(presmoother=spec)
    else:
        ml = MultigridSolver(pr.A, pr.P[:levels - 1], presmoother=spec)
    x = np.zeros_like(pr.b)
    secs = []
    for _ in range(5):
        t0 = time.process_time()
        ml._cycle(0, x, pr.b, cycle)
        secs.append(time.process_time() - t0)
    _, info = ml.solve(pr.b, tol=1e-8, maxiter=300, cycle=cycle, accel="cg", return_info=True)
    return {"factor": stationary_factor(ml, cycle), "pcg_iterations": int(info["iterations"]),
            "converged": bool(info["converged"]), "cycle_cpu_seconds": float(np.median(secs)),
            "levels": [L.A.shape[0] for L in ml.levels], "smoother": ml.levels[0].presmoother.params}


def run(names, nus, cycles) -> list[dict]:
    from nestmg.elasticity import setup_elasticity

    out = []
    for name in names:
        meshes, P = hierarchy(name)
        rec = {"hierarchy": name, "tets": [len(T) for _, T in meshes], "cases": []}
        for nu in nus:
            pr = setup_elasticity(meshes, P, "elasticity-clamped", nu=nu)
            case = {"nu": nu, "unknowns": int(pr.A.shape[0]), "cycles": {}}
            for c in cycles:
                case["cycles"][c] = r = run_cycle(pr, c)
                print(f"{name} nu={nu} {c}: factor {r['factor']:.3f}, MG-PCG {r['pcg_iterations']} it",
                      file=sys.stderr, flush=True)
            rec["cases"].append(case)
        out.append(rec)
    return out


def table(res: dict) -> str:
    """Markdown table: per hierarchy and ν, each cycle's stationary factor (MG-PCG iterations)."""
    cycles = res["params"]["cycles"]
    head = "| hierarchy | tets per level | ν | " + " | ".join(cycles) + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for rec in res["hierarchies"]:
        tets = " / ".join(f"{t:,}" for t in rec["tets"])
        for c in rec["cases"]:
            cells = [f"{c['cycles'][k]['factor']:.3f} ({c['cycles'][k]['pcg_iterations']})" for k in cycles]
            lines.append(f"| {rec['hierarchy']} | {tets} | {c['nu']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hierarchies", nargs="+", default=list(HIERARCHIES), choices=HIERARCHIES)
    ap.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.45])
    ap.add_argument("--cycles", nargs="+", default=list(CYCLES), choices=CYCLES)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--table", type=Path, default=None, help="only print the Markdown table of this JSON")
    a = ap.parse_args(argv)
    if a.table is not None:
        import json

        print(table(json.loads(a.table.read_text())))
        return 0
    if a.out is None:
        ap.error("--out is required (or --table JSON)")
    from exp_common import environment, git_commit, write_json

    res = {"params": {"nus": a.nu, "cycles": a.cycles, "problem": "elasticity-clamped", "tol": 1e-8,
                      "factor": "energy norm, A e = 0, last 10 of 40 cycles",
                      "command": " ".join(["benchmarks/elasticity_factor.py", *sys.argv[1:]]),
                      "commit": git_commit()},
           "environment": environment(), "hierarchies": run(a.hierarchies, a.nu, a.cycles)}
    res["table"] = table(res)
    write_json(res, a.out)
    print(res["table"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
