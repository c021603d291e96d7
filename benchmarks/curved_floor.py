"""What the scaled-Jacobian floor of curved P2 costs on analytic shapes: rates, accuracy, facet distance.

The procedural unit ball (``shapes.ball_tets(4)``) and solid torus (``shapes.torus_tets(3, segments=12)``)
with their exact closest points. For each floor (``none`` and every ``--floors`` value), curved P2
(:func:`nestmg.curved.curve_mesh` with ``sj_floor``) on the 1,280 / 1,728-tet and the 10,240 /
13,824-tet levels, p-multigrid onto the P1 levels below, MG-PCG to 1e-10; P1 on the red refinement of
the finer level (the same unknowns) with the boundary vertices on the true surface. Recorded: L2 errors
(Dirichlet ``u = (1 - r²) eˣ`` on the ball, the harmonic ``u = eˣ cos y`` elsewhere, Neumann flux on the
true surface), the L2 rate, P1 / curved P2 at equal unknowns, iterations, scaled Jacobian min / mean
(all tets), edge nodes backed off, largest facet distance to the surface. The tests
(``tests/test_nestmg_curved.py``) require rate >= 2.7 and P1 / curved >= 10.

Run from the repository root::

    OMP_NUM_THREADS=1 python benchmarks/curved_floor.py --floors 0.7 0.8 0.955 \\
        --json benchmarks/results/curved/floor_rates.json
    OMP_NUM_THREADS=1 python benchmarks/curved_floor.py --relax 0.97 --floors 0.96 \\
        --json benchmarks/results/curved/floor_rates_relax.json   # every curving relaxed first
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

from nestmg import setup_problem, shapes
from nestmg.curved import curve_mesh, p2_nodes, p2_prolongation, sphere_projector, torus_projector
from nestmg.tetmesh import orient_tets
from solvers import MultigridSolver, restrict_prolongations, stiffness_matrix
from solvers.fem_p2 import p2_boundary_facets, p2_l2_error, p2_load, p2_neumann_load

from exp_common import git_commit, write_json  # benchmarks/ is sys.path[0]


def _harmonic(x):
    return np.exp(x[:, 0]) * np.cos(x[:, 1])


def _harmonic_grad(x):
    e = np.exp(x[:, 0])
    return np.c_[e * np.cos(x[:, 1]), -e * np.sin(x[:, 1]), np.zeros(len(x))]


def _ball_u(x):
    return (1 - (x**2).sum(1)) * np.exp(x[:, 0])


def _ball_f(x):
    return np.exp(x[:, 0]) * (6 + 4 * x[:, 0] - (1 - (x**2).sum(1)))


def _zero(x):
    return np.zeros(len(x))


def _data(name, proj):
    if name == "poisson-dirichlet":
        return lambda u: {"boundary_values": lambda x: u(proj(x)[0])}
    return lambda u: {"flux": lambda x, n: np.einsum("ij,ij->i", _harmonic_grad(proj(x)[0]), proj(x)[1])}


_CURVED: dict = {}  # (tets id, floor, relax) -> CurvedMesh: the curving does not depend on the problem


def p2_error(tets, P, name, proj, f, u, floor, relax=None):
    """Curved P2 on ``tets[0]``: L2 error, MG-PCG iterations and the curving report."""
    key = (id(tets[0][1]), floor, relax)
    if key not in _CURVED:
        _CURVED[key] = curve_mesh(*tets[0], proj, sj_floor=floor, relax=relax)
    cm = _CURVED[key]
    pr = setup_problem(tets, P, name, element="P2", curved=cm, f=f, **_data(name, proj)(u))
    x, info = pr.multigrid().solve(pr.b, tol=1e-10, accel="cg", return_info=True)
    err = p2_l2_error(pr.mesh.X, pr.mesh.T10, pr.expand(x), u, remove_mean=name == "poisson-neumann")
    return err, int(info["iterations"]), cm.report


def p1_error(tets, P, name, proj, f, u):
    """P1 on ``tets[0]`` (boundary vertices on the surface), loads by P2 quadrature, the same hierarchy."""
    V, T = tets[0]
    T = orient_tets(V, T)
    X, T10, E = p2_nodes(V, T)
    Pp = p2_prolongation(len(V), E)
    K, b, n = stiffness_matrix(V, T), Pp.T @ p2_load(X, T10, f), len(V)
    F6 = p2_boundary_facets(T10)[0]
    bnd, uh = np.unique(F6[:, :3]), np.zeros(n)
    if name == "poisson-dirichlet":
        free = np.setdiff1d(np.arange(n), bnd)
        uh[bnd] = u(V[bnd])
        A, rhs = K[free][:, free], b[free] - K[free][:, bnd] @ uh[bnd]
    else:
        b = b + Pp.T @ p2_neumann_load(X, F6, _data(name, proj)(u)["flux"])
        free = np.arange(1, n)
        A, rhs = K[1:, 1:], (b - b.mean())[1:]
    ml = MultigridSolver(A.tocsr(), restrict_prolongations(P, free)[0])
    uh[free] = ml.solve(rhs, tol=1e-11, accel="cg")
    return p2_l2_error(X, T10, Pp @ uh, u, remove_mean=name != "poisson-dirichlet")


def _curving(rep: dict) -> dict:
    sj, fl = rep["scaled_jacobian"], rep.get("sj_floor") or {}
    return {"tets": rep["tets"], "sj_min": sj["min"], "sj_mean_all": sj["mean_all"], "sj_mean": sj["mean"],
            "sj_bound_min": sj["bound_min"], "curved_edge_nodes": fl.get("curved_edge_nodes"),
            "backed_off": fl.get("backed_off", 0), "straightened_nodes": fl.get("straightened", 0),
            "boundary_backed_off": fl.get("boundary_backed_off", 0),
            "facet_distance_max": rep["surface_distance"]["curved_max"],
            "facet_distance_straight_max": rep["surface_distance"]["straight_max"]}


def run_shape(shape: str, floors: list, relax: float | None = None) -> list:
    _CURVED.clear()  # keys are array ids: valid for one shape's arrays only
    if shape == "ball":
        (tets, P), proj, end = shapes.ball_tets(4), sphere_projector(), 4
    else:
        (tets, P), proj = shapes.torus_tets(3, segments=12), torus_projector()
        end = len(tets)
    rows = []
    for name in ("poisson-dirichlet", "poisson-neumann"):
        f, u = (_ball_f, _ball_u) if shape == "ball" and name == "poisson-dirichlet" else (_zero, _harmonic)
        e_p1 = p1_error(tets[:end], P[:end - 1], name, proj, f, u)
        for floor in floors:
            t0 = time.perf_counter()
            res = [p2_error(tets[j:end], P[j:end - 1], name, proj, f, u, floor, relax) for j in (2, 1)]
            (e0, i0, r0), (e1, i1, r1) = res
            rows.append({"shape": shape, "problem": name, "sj_floor": floor, "relax": relax,
                         "l2_error": [e0, e1],
                         "rate": float(np.log2(e0 / e1)), "p1_l2_error": e_p1, "p1_over_curved": e_p1 / e1,
                         "unknowns_p1": int(len(tets[0][0])), "iterations": [i0, i1],
                         "curving": [_curving(r0), _curving(r1)], "seconds": time.perf_counter() - t0})
            print(f"{shape} {name} floor {floor}: L2 {e0:.3e} -> {e1:.3e} (rate {rows[-1]['rate']:.2f}), "
                  f"P1 / curved {e_p1 / e1:.1f}, SJ min {r1['scaled_jacobian']['min']:.3f}", flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--floors", type=float, nargs="+", default=[0.7, 0.8, 0.955])
    p.add_argument("--relax", type=float, default=None,
                   help="threshold of the interior relaxation (curve_mesh relax=) in every curving")
    p.add_argument("--json", required=True, help="output JSON")
    args = p.parse_args(argv)
    commit = git_commit()
    floors = [None, *args.floors]
    res = {"command": "python benchmarks/curved_floor.py --floors " + " ".join(f"{f:g}" for f in args.floors)
           + ("" if args.relax is None else f" --relax {args.relax:g}"),
           "commit": commit, "machine": platform.machine(),
           "results": [row for shape in ("ball", "torus") for row in run_shape(shape, floors, args.relax)]}
    write_json(res, Path(args.json))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
