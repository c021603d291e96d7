"""SuperLU settings for the coarse levels of a Galerkin hierarchy (issue 15: per-step set-up cost).

    OPENBLAS_NUM_THREADS=1 python benchmarks/archive/coarse_factor.py ZOO_DIR/gargo.off \
        --edge-length 0.0067 --out benchmarks/results/reuse

Loads (or builds, through the cache) the reuse benchmarks' 3-level TetWild hierarchy, forms the Galerkin
operators of a diffusion step ``M + Δt K`` (Δt = 1e-3 diag²) on every coarse level and factors each with

``scipy_default``  ``splu(A)``: COLAMD column ordering, threshold partial pivoting;
``mmd_pivot``      ``splu(A, permc_spec="MMD_AT_PLUS_A")``: the project's setting before this change;
``symmetric``      :func:`solvers.coarse.sparse_lu`: minimum degree on ``A + Aᵀ``, SuperLU's symmetric mode,
                   no pivoting (what the coarsest-level solver now uses for symmetric operators).

Per setting: factorisation seconds (best of ``--repeat``), nonzeros of ``L + U``, one solve's seconds and
its relative residual. ``--max-seconds``: a factorisation slower than that is timed once, not
``--repeat`` times.
Prints JSON and writes ``coarse_factor_<mesh>.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import cached_hierarchy, environment  # noqa: E402

SETTINGS = ("scipy_default", "mmd_pivot", "symmetric")


def factor(A: sp.csc_matrix, setting: str):
    from solvers.coarse import sparse_lu

    if setting == "scipy_default":
        return spla.splu(A)
    if setting == "mmd_pivot":
        return spla.splu(A, permc_spec="MMD_AT_PLUS_A")
    return sparse_lu(A, symmetric=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--edge-length", type=float, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/reuse"))
    a = ap.parse_args(argv)
    from nestmg.timestepping import diffusion_stepper

    h, _ = cached_hierarchy(a.mesh, edge_length=a.edge_length)
    V0 = h.tets[0][0]
    diag = float(np.linalg.norm(V0.max(axis=0) - V0.min(axis=0)))
    st = diffusion_stepper(h.tets, h.P)
    ops = st.family.operators(1.0, 1e-3 * diag**2)
    doc: dict = {"benchmark": "coarse_factor", "mesh": a.mesh.name, "edge_length": a.edge_length,
                 "tets": [len(T) for _, T in h.tets], "environment": environment(),
                 "command": " ".join(["benchmarks/archive/coarse_factor.py"] + (argv if argv is not None else sys.argv[1:])),
                 "levels": []}
    for k, Ak in enumerate(ops[1:], start=1):
        A = sp.csc_matrix(Ak)
        b = np.random.default_rng(k).standard_normal(A.shape[0])
        rec: dict = {"level": k, "n": int(A.shape[0]), "nnz": int(A.nnz)}
        for s in SETTINGS:
            best, lu = np.inf, None
            for _ in range(a.repeat):
                t0 = time.perf_counter()
                lu = factor(A, s)
                best = min(best, time.perf_counter() - t0)
                if best > a.max_seconds:
                    break
            t0 = time.perf_counter()
            x = lu.solve(b)
            t_solve = time.perf_counter() - t0
            rec[s] = {"factor_seconds": best, "lu_nnz": int(lu.L.nnz + lu.U.nnz), "solve_seconds": t_solve,
                      "relative_residual": float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))}
            print(f"level {k} (n={A.shape[0]}, nnz={A.nnz}) {s:13s}: factor {best:8.3f} s, LU nnz {rec[s]['lu_nnz']:,},"
                  f" solve {t_solve:.4f} s, residual {rec[s]['relative_residual']:.1e}", file=sys.stderr, flush=True)
        doc["levels"].append(rec)
    a.out.mkdir(parents=True, exist_ok=True)
    out = a.out / f"coarse_factor_{a.mesh.stem}.json"
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(json.dumps(doc, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
