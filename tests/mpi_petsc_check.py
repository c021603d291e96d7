"""MPI driver for tests/test_petsc.py: run solvers.petsc on every rank, print one JSON line on rank 0.

Usage (from the repository root; ``solvers`` must be importable, e.g. ``PYTHONPATH=.``)::

    PYTHONPATH=. mpirun -n 2 python tests/mpi_petsc_check.py --n 16 --levels 3 --out OUT/petsc_check.npz

Every rank builds the same Kuhn cube hierarchy (deterministic), the Dirichlet and Neumann P1 Poisson
problems and a seeded right-hand side, and takes its rows. Rank 0 prints
``{"ranks": ..., "runs": {name: {iterations, factor, final_residual, converged, ...}}}`` on stdout and
writes every run's global solution to ``--out`` (``x_<name>``) for the test to compare with the
in-process :class:`solvers.MultigridSolver`. The problem builders are imported by the test as well, so
both sides solve the very same systems.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import scipy.sparse as sp

from solvers.fem import boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.multilevel import restrict_prolongations


def dirichlet_problem(n: int, levels: int, seed: int = 0) -> dict:
    """Interior-node P1 Poisson on the Kuhn cube; Galerkin-ready Ps and re-discretised coarse operators.

    Returns
    -------
    dict with ``A`` (m_0, m_0), ``Ps`` (support-restricted, for Galerkin), ``Ps_int`` and ``coarse``
    (coarse interior nodes only, re-discretised stiffness), ``b`` (m_0,), ``z`` (m_0,) fine z coordinates.
    """
    meshes, Ps = kuhn_cube_hierarchy(n, levels)
    V, T = meshes[0]
    free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    A = stiffness_matrix(V, T)[free][:, free]
    Pg, _ = restrict_prolongations(Ps, free)
    interiors = [np.setdiff1d(np.arange(len(Vk)), boundary_nodes(Tk)) for Vk, Tk in meshes[1:]]
    Pi, frees = restrict_prolongations(Ps, free, coarse_free=interiors)
    coarse = [sp.csr_matrix(stiffness_matrix(Vk, Tk)[f][:, f]) for (Vk, Tk), f in zip(meshes[1:], frees[1:])]
    b = np.random.default_rng(seed).standard_normal(A.shape[0])
    return {"A": sp.csr_matrix(A), "Ps": Pg, "Ps_int": Pi, "coarse": coarse, "b": b, "xyz": V[free]}


def neumann_problem(n: int, levels: int, seed: int = 1) -> dict:
    """Pure Neumann P1 Poisson on the Kuhn cube (singular, constants in the null space), zero-sum ``b``."""
    meshes, Ps = kuhn_cube_hierarchy(n, levels)
    V, T = meshes[0]
    b = np.random.default_rng(seed).standard_normal(len(V))
    b -= b.mean()
    return {"A": stiffness_matrix(V, T), "Ps": Ps, "b": b}


def permuted(prob: dict, seed: int = 5) -> dict:
    """The same system with its fine unknowns in random order (what an unordered mesh looks like)."""
    p = np.random.default_rng(seed).permutation(prob["A"].shape[0])
    Ps = [sp.csr_matrix(prob["Ps"][0][p])] + list(prob["Ps"][1:])
    return {"A": sp.csr_matrix(prob["A"][p][:, p]), "Ps": Ps, "b": prob["b"][p], "perm": p}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16, help="cells per side of the finest Kuhn mesh")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--out", required=True, help=".npz file for the solutions (written by rank 0)")
    ap.add_argument("--cage", nargs="*", default=[],
                    help="only solve these .npz hierarchies (solvers.petsc.save_operators, with a 'neumann' flag "
                         "array), e.g. the cage hierarchies of the tests, by MG-PCG with the default options")
    args, petsc_args = ap.parse_known_args(argv)

    import petsc4py

    petsc4py.init([sys.argv[0], *petsc_args])
    from petsc4py import PETSc

    from solvers.petsc import PetscMultigrid, petsc_amg_solve

    comm = PETSc.COMM_WORLD
    size = comm.getSize()
    if args.cage:
        return _cage_runs(args, PETSc, comm)
    D = dirichlet_problem(args.n, args.levels)
    N = neumann_problem(args.n, args.levels)
    R = permuted(D)
    # a non-contiguous partition: slabs along x although the numbering runs along z (renumbering path)
    by_x = np.minimum((D["xyz"][:, 0] * size).astype(np.int64), size - 1)

    nat = {"partition": "natural"}
    rich = {"krylov": "richardson"}
    runs = {
        "rich_V": (D, {**rich, **nat}),
        "cg_V": (D, {"krylov": "cg", **nat}),
        "rich_W": (D, {**rich, "cycle": "W", **nat}),
        "rich_V22": (D, {**rich, "presmooth": 2, "postsmooth": 2, **nat}),
        "rich_given": (D, {**rich, "given": True, **nat}),
        "rich_neumann": (N, {**rich, "nullspace": "constant", **nat}),
        "cg_auto": (D, {"krylov": "cg"}),  # default partition: PT-Scotch on several ranks
        "rich_byx": (D, {**rich, "partition": by_x}),
        "direct": (D, {"levels": 1, **nat}),
        "rich_perm_natural": (R, {**rich, **nat}),
        "rich_perm_ptscotch": (R, {**rich, "partition": "ptscotch"}),
        "rich_perm_rcm": (R, {**rich, "partition": "rcm"}),
    }
    out = {"ranks": size, "n": int(D["A"].shape[0]), "runs": {}}
    xs = {}
    for name, (prob, kw) in runs.items():
        if kw.pop("levels", None) == 1:
            Ps, extra = [], {}  # one level: PCMG's coarse solver alone (redundant LU in parallel)
        elif not kw.pop("given", False):
            Ps, extra = prob["Ps"], {}
        else:
            Ps, extra = prob["Ps_int"], {"coarse": prob["coarse"]}
        with PetscMultigrid(prob["A"], Ps, **extra, **kw) as mg:
            x, info = mg.solve(prob["b"], tol=args.tol, maxiter=100)
        xs[f"x_{name}"] = x
        out["runs"][name] = {k: info[k] for k in ("iterations", "factor", "final_residual", "converged", "reason",
                                                  "residuals", "setup_seconds", "solve_seconds",
                                                  "ghosts_per_rank", "rows_per_rank", "partition")}
        out["runs"][name]["levels"] = info["levels"]
    for kind in ("gamg", "hypre"):
        x, info = petsc_amg_solve(D["A"], D["b"], kind, tol=args.tol)
        xs[f"x_{kind}"] = x
        out["runs"][kind] = {k: info[k] for k in ("iterations", "factor", "final_residual", "converged", "reason")}
    # the solution must be identical on every rank: compare a checksum across ranks
    check = sum(float(np.abs(v).sum()) for v in xs.values())
    vec = PETSc.Vec().createMPI((1, size), comm=comm)
    vec.setValue(comm.getRank(), check)
    vec.assemble()
    scatter, allc = PETSc.Scatter.toAll(vec)
    scatter.scatter(vec, allc)
    spread = np.ptp(allc.getArray())
    out["checksum_spread"] = float(spread)
    if comm.getRank() == 0:
        np.savez(args.out, **xs)
        print(json.dumps(out), flush=True)
    return 0


def _cage_runs(args, PETSc, comm) -> int:
    """MG-PCG on saved hierarchies (every rank loads the same file), default partition and coarse solve."""
    from solvers.petsc import PetscMultigrid, load_operators

    out = {"ranks": comm.getSize(), "runs": {}}
    xs = {}
    for k, path in enumerate(args.cage):
        h = load_operators(path)
        ns = "constant" if bool(h.get("neumann", np.zeros(1))[0]) else None
        with PetscMultigrid(h["A"], h["Ps"], nullspace=ns, coarse_solver="auto") as mg:
            x, info = mg.solve(h["b"], tol=args.tol, maxiter=100)
        xs[f"x_{k}"] = x
        out["runs"][str(k)] = {key: info[key] for key in ("iterations", "final_residual", "converged", "setup_seconds",
                                                          "partition")}
    if comm.getRank() == 0:
        np.savez(args.out, **xs)
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
