"""How small a relative residual round-off allows on one elasticity system, and what the regularised
coarsest solve does there (issue 32, docs/elasticity.md).

A sparse direct solve (SuperLU, symmetric mode) of the clamped elasticity problem on a cached nested
hierarchy's fine level, one step of iterative refinement, and the estimate ``eps ||A||_1 ||x|| / ||b||``
that :func:`solvers.pcg` reports when it stagnates. Then the default multigrid solver's coarsest operator:
its smallest eigenvalues (relative to the largest), and, over the coarse right-hand sides of 30 MG-PCG
iterations with the W-cycle, the relative difference of the regularised (``A + 1e-9 diag A``) and the
pivoted-Cholesky corrections against the pseudo-inverse's. Run from ``benchmarks/``'s parent::

    OMP_NUM_THREADS=1 python benchmarks/archive/attainable_accuracy.py ZOO_DIR/spot.obj --max-tets 300000 \\
        --nu 0.45 --out benchmarks/results/elasticity/attainable_spot_clamped_045.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--max-tets", type=int, default=300_000)
    ap.add_argument("--nu", type=float, default=0.45)
    ap.add_argument("--problem", default="elasticity-clamped")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)

    from elasticity import load_surface
    from exp_common import environment, git_commit, relres, write_json

    import nestmg
    from nestmg.elasticity import setup_elasticity
    from solvers.coarse import sparse_lu

    V, F = load_surface(str(a.mesh))
    h = nestmg.build_hierarchy(V, F, 3, "nested", sizing=nestmg.SizingOptions(max_tets=a.max_tets),
                               cache=True, progress=False)
    pr = setup_elasticity(h.tets_in("normalized"), h.P, a.problem, nu=a.nu)
    A, b = sp.csr_matrix(pr.A), pr.b
    t0 = time.process_time()
    lu = sparse_lu(A, symmetric=True)
    x = lu.solve(b)
    cpu = time.process_time() - t0
    x1 = x + lu.solve(b - A @ x)
    norm_a = float(abs(A).sum(axis=0).max())
    out = {"command": "benchmarks/archive/attainable_accuracy.py " + " ".join(
               [a.mesh.name, "--max-tets", str(a.max_tets), "--nu", str(a.nu), "--problem", a.problem]),
           "commit": git_commit(), "environment": environment(), "mesh": a.mesh.name,
           "tets": [len(T) for _, T in h.tets_in("normalized")], "unknowns": int(A.shape[0]),
           "problem": a.problem, "nu": a.nu, "superlu_cpu_seconds": cpu,
           "direct_relative_residual": relres(A, b, x), "refined_relative_residual": relres(A, b, x1),
           "eps_normA_normx_over_normb": float(np.finfo(float).eps * norm_a * np.linalg.norm(x1)
                                               / np.linalg.norm(b))}
    out.update(coarse_study(pr))
    write_json(out, a.out)
    print({k: v for k, v in out.items() if k != "environment"})
    return 0


def coarse_study(pr) -> dict:
    """Spectrum of the coarsest operator; the coarse solvers' corrections on a W-cycle's right-hand sides."""
    import scipy.linalg as sla

    from solvers.coarse import _CoarseSolver

    ml = pr.multigrid(cycle="W")
    Ac = sp.csr_matrix(ml.levels[-1].A)
    w = sla.eigh(Ac.toarray(), eigvals_only=True)
    solvers = {m: _CoarseSolver(Ac, None, len(ml.levels) - 1, m, symmetric=True)
               for m in ("pinv", "pivoted", "regularized")}
    diffs = {m: [] for m in ("pivoted", "regularized")}
    used = ml._coarse_solver

    def compare(bc):
        ref = solvers["pinv"](bc)
        for m in diffs:
            diffs[m].append(float(np.linalg.norm(solvers[m](bc) - ref) / np.linalg.norm(ref)))
        return used(bc)

    ml._coarse_solver = compare
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ml.solve(pr.b, tol=1e-30, maxiter=30, accel="cg")
    return {"coarsest_unknowns": int(Ac.shape[0]), "coarsest_solver_default": used.method,
            "coarsest_eigenvalues_over_max": [float(v) for v in w[:10] / w[-1]],
            "coarsest_nullity": {m: int(c.nullity) for m, c in solvers.items()},
            "coarse_correction_rel_diff_vs_pinv": {m: {"median": float(np.median(v)), "max": float(np.max(v)),
                                                       "solves": len(v)} for m, v in diffs.items()}}


if __name__ == "__main__":
    raise SystemExit(main())
