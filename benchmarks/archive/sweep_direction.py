"""Gauss-Seidel sweep times per level and direction on saved user-mesh cases (issue 31, item 2).

pyamg's backward sweep reads a CSR matrix row by row downwards; on the Galerkin coarse operators of a
user hierarchy (50-100 entries per row) it measured 2-4x its forward sweep. For every level of
``MultigridSolver(A, P)`` (the defaults) on the cases of ``benchmarks/user_mesh_solvers.py build``, this
times (CPU, median of ``--repeats``) two sweeps of each: forward, pyamg's backward, and the backward sweep
the smoother runs now (a forward sweep on ``J A J``, :func:`solvers.smoothing.reversed_order`, vectors
reversed in and out), plus one SpMV; and checks that the two backward sweeps agree to round-off.

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
    """Two sweeps each way on ``A`` (CPU ms) and one SpMV."""
    from pyamg.relaxation import relaxation

    from solvers.smoothing import reversed_order

    n = A.shape[0]
    rng = np.random.default_rng(0)
    x0, b = rng.standard_normal((2, n))
    Ar = reversed_order(A)

    def forward():
        relaxation.gauss_seidel(A, x0.copy(), b, iterations=2, sweep="forward")

    def backward():
        x = x0.copy()
        relaxation.gauss_seidel(A, x, b, iterations=2, sweep="backward")
        return x

    def reversed_forward():
        xr = x0[::-1].copy()
        relaxation.gauss_seidel(Ar, xr, np.ascontiguousarray(b[::-1]), iterations=2, sweep="forward")
        return xr[::-1].copy()

    xb, xr = backward(), reversed_forward()
    return {"unknowns": n, "nnz_per_row": A.nnz / n, "forward_ms": _cpu_ms(forward, repeats),
            "backward_ms": _cpu_ms(backward, repeats),
            "reversed_forward_ms": _cpu_ms(reversed_forward, repeats),
            "spmv_ms": _cpu_ms(lambda: A @ b, repeats),
            "reversed_build_ms": _cpu_ms(lambda: reversed_order(A), 3),
            "relative_difference": float(np.abs(xb - xr).max() / np.abs(xb).max())}


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
                      f"{r['reversed_forward_ms']:.2f} (SpMV {r['spmv_ms']:.2f}; difference "
                      f"{r['relative_difference']:.1e})", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
