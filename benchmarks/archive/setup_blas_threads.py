"""One-off study: the multigrid set-up with OpenBLAS's threads against one BLAS thread.

Interleaved A/B in one process, 5 repeats after a warm-up, medians: ``Problem.multigrid()`` plus its deferred
finest probe (the stationary set-up of ``nestmg solve``) and ``MultigridSolver(A, P)`` on saved hierarchies
(``nestmg.save_hierarchy``), and ``MultigridSolver(A, P)`` on user-mesh cases of ``user_mesh_solvers.py
build``. Variant ``loaded``: the BLAS libraries as loaded (no ``OMP_NUM_THREADS``); ``one``: under
``solvers._threads.one_blas_thread()``. Run it on a tree from before 1305e30 (whose set-up takes the BLAS
threads as they are; from 1305e30 on both variants run on one thread):

    PYTHONPATH=BEFORE_TREE python benchmarks/archive/setup_blas_threads.py SAVED_HIERARCHY... \
        user:WORK/bunny-tetwild --out OUT.json

CPU seconds leak from one variant into the next (OpenBLAS's threads spin on after a call): compare wall
seconds on an idle machine.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _cases(paths: list[str]) -> list:
    from solvers import MultigridSolver

    out = []
    for arg in paths:
        if arg.startswith("user:"):
            from user_mesh_solvers import load_case

            c = load_case(Path(arg[5:]))
            for prob in ("dirichlet", "neumann"):
                A, _b, Ps, ns = c[prob]
                out.append((f"{Path(arg[5:]).name}/{prob}/ctor",
                            lambda A=A, Ps=Ps, ns=ns: MultigridSolver(A, Ps, nullspace=ns)))
            continue
        from nestmg import load_hierarchy
        from nestmg.problems import setup_problem

        H = load_hierarchy(arg)
        for prob in ("poisson-dirichlet", "poisson-neumann"):
            pr = setup_problem(H.tets, H.P, prob)

            def stationary(pr=pr):
                pr.multigrid().probe()

            out.append((f"{Path(arg).name}/{prob}/problem_multigrid+probe", stationary))
            out.append((f"{Path(arg).name}/{prob}/ctor", lambda pr=pr: MultigridSolver(
                pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace)))
    return out


def main() -> int:
    from threadpoolctl import threadpool_info

    from solvers._threads import one_blas_thread

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="saved hierarchies, or user:WORK_DIR of user_mesh_solvers.py")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    rows = {}
    for name, make in _cases(a.cases):
        make()  # warm-up
        raw = {"loaded": [], "one": []}
        for _ in range(a.repeats):
            for v, runs in raw.items():
                ctx = one_blas_thread() if v == "one" else contextlib.nullcontext()
                t, c = time.perf_counter(), time.process_time()
                with ctx:
                    make()
                runs.append([time.perf_counter() - t, time.process_time() - c])
        med = {v: {"wall": float(np.median([x[0] for x in r])), "cpu": float(np.median([x[1] for x in r]))}
               for v, r in raw.items()}
        rows[name] = {"raw": raw, "median": med}
        print(f"{name:<48} wall {med['loaded']['wall']:.3f} -> {med['one']['wall']:.3f}  "
              f"cpu {med['loaded']['cpu']:.3f} -> {med['one']['cpu']:.3f}", flush=True)
    blas = [(i["internal_api"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]
    a.out.write_text(json.dumps({"command": "python benchmarks/archive/setup_blas_threads.py "
                                            + " ".join(Path(c).name for c in a.cases), "blas": blas,
                                 "repeats": a.repeats, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
