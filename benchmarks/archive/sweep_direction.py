"""Gauss-Seidel sweep times per level, direction and row layout on saved user-mesh cases (issue 31, item 2).

pyamg's backward sweep reads a CSR matrix row by row downwards; on the Galerkin coarse operators of a
user hierarchy (50-100 entries per row) it measured 2-4x its forward sweep. For every level of
``MultigridSolver(A, P)`` (the defaults) on the cases of ``benchmarks/user_mesh_solvers.py build``, this
times (CPU, median of ``--repeats``) two sweeps of each: forward, pyamg's backward, and the backward sweep
the smoother runs on long rows (a forward sweep on ``J A J``, :func:`solvers.smoothing.reversed_order`,
vectors reversed in and out), on the canonical matrix and on the one with each row's diagonal entry first
(:func:`solvers.ordering.diagonal_first`: pyamg's kernel tests every entry for the diagonal), plus one SpMV;
and checks that the two backward sweeps agree to round-off and the two layouts' forward sweeps bit for bit.

    OMP_NUM_THREADS=1 python benchmarks/archive/sweep_direction.py WORK/bunny-tetgen WORK/bunny-tetwild \\
        ... --json benchmarks/results/user_mesh/sweep_direction.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: user_mesh_solvers is in benchmarks/
from user_mesh_solvers import load_case  # noqa: E402


def _cpu_ms(f, repeats: int) -> float:
    f()
    ts = []
    for _ in range(repeats):
        t = time.process_time()
        f()
        ts.append(time.process_time() - t)
    return 1e3 * float(np.median(ts))


def level_rows(A, repeats: int) -> dict:
    """Two sweeps each way (CPU ms) on the canonical ``A`` (sorted rows) and on ``A`` with each row's
    diagonal first (:func:`solvers.ordering.diagonal_first`), and one SpMV."""
    from pyamg.relaxation import relaxation

    from solvers.ordering import diagonal_first
    from solvers.smoothing import reversed_order

    A = A.copy()
    A.sort_indices()  # the canonical form, whatever the solver stores
    n = A.shape[0]
    rows = np.repeat(np.arange(n, dtype=A.indices.dtype), np.diff(A.indptr))
    D = diagonal_first(A, np.flatnonzero(A.indices == rows))
    rng = np.random.default_rng(0)
    x0, b = rng.standard_normal((2, n))

    def sweeps(M, sweep):
        def run():
            x = x0.copy()
            relaxation.gauss_seidel(M, x, b, iterations=2, sweep=sweep)
            return x
        return run

    def reversed_forward(M):
        Mr = reversed_order(M)

        def run():
            xr = x0[::-1].copy()
            relaxation.gauss_seidel(Mr, xr, np.ascontiguousarray(b[::-1]), iterations=2, sweep="forward")
            return xr[::-1].copy()
        return run

    xb = sweeps(A, "backward")()
    out = {"unknowns": n, "nnz_per_row": A.nnz / n, "spmv_ms": _cpu_ms(lambda: A @ b, repeats),
           "reversed_build_ms": _cpu_ms(lambda: reversed_order(A), 3),
           "relative_difference": float(np.abs(xb - reversed_forward(A)()).max() / np.abs(xb).max()),
           "diagonal_first_same_bits": bool(np.array_equal(sweeps(A, "forward")(), sweeps(D, "forward")()))}
    for label, M in (("", A), ("diagonal_first_", D)):
        out[label + "forward_ms"] = _cpu_ms(sweeps(M, "forward"), repeats)
        out[label + "backward_ms"] = _cpu_ms(sweeps(M, "backward"), repeats)
        out[label + "reversed_forward_ms"] = _cpu_ms(reversed_forward(M), repeats)
    return out


def main(argv=None) -> None:
    from solvers import MultigridSolver

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", type=Path)
    ap.add_argument("--problems", nargs="+", default=["dirichlet", "neumann"])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    words = ["WORK/" + c.name for c in args.cases]
    words += ["--problems", *args.problems, "--repeats", str(args.repeats)]
    out = {"command": "python benchmarks/archive/sweep_direction.py " + " ".join(words),
           "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "clock": "process_time", "sweeps": 2,
           "cases": []}
    for work in args.cases:
        c = load_case(work)
        for prob in args.problems:
            A, _b, Ps, ns = c[prob]
            ml = MultigridSolver(A, Ps, nullspace=ns)
            rows = [level_rows(L.A, args.repeats) for L in ml.levels[:-1]]
            out["cases"].append({"case": c["name"], "label": c["label"], "problem": prob, "levels": rows})
            for k, r in enumerate(rows):
                print(f"{c['name']} {prob} level {k}: {r['unknowns']} unknowns, {r['nnz_per_row']:.1f}/row: "
                      f"forward {r['forward_ms']:.2f} ms, backward {r['backward_ms']:.2f}, reversed "
                      f"{r['reversed_forward_ms']:.2f}; diagonal first: forward "
                      f"{r['diagonal_first_forward_ms']:.2f}, backward "
                      f"{r['diagonal_first_backward_ms']:.2f}, "
                      f"reversed {r['diagonal_first_reversed_forward_ms']:.2f} (SpMV {r['spmv_ms']:.2f})",
                      flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
