"""One-off study (issue 27, item 3): the Dirichlet deflation goal, 0.3 against 0.2, on the same hierarchies.

``nestmg solve MESH --levels 3``'s default hierarchy is built ``--runs`` times (TetWild gives a different
mesh each run); on each, the Dirichlet V-cycle factor and MG-PCG iterations are measured with the
cycle of ``Problem.multigrid()`` under both goals (``deflate_goal``). Writes one JSON.

    OMP_NUM_THREADS=1 python benchmarks/archive/deflation_goal.py ZOO_DIR/idler_riser.stl --runs 8 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def one_run(mesh: str) -> dict:
    from corpus import _cli_args  # the corpus' own `nestmg solve` arguments: the defaults

    from nestmg.cli import _hierarchy, _load
    from nestmg.problems import setup_problem

    args = _cli_args("solve", Path(mesh), [])
    V, F, _ = _load(mesh)
    h = _hierarchy(V, F, args)
    p = setup_problem(h.tets, h.P, "poisson-dirichlet")
    rec = {"tets": [len(T) for _, T in h.tets], "certified": h.certified}
    for goal in (0.3, 0.2):
        t = time.process_time()
        ml = p.multigrid(deflate_goal=goal)
        setup = time.process_time() - t
        _, info = ml.solve(p.b, tol=1e-10, maxiter=60, return_info=True)
        _, cg = ml.solve(p.b, tol=1e-8, accel="cg", return_info=True)
        rec[f"goal_{goal}"] = {"factor": info["factor"], "pcg_iterations": cg["iterations"],
                               "setup_cpu_seconds": setup,
                               "deflation": [{k: d[k] for k in ("level", "probe_factor", "vectors")}
                                             for d in ml.deflation]}
    return rec


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    runs = []
    for i in range(a.runs):
        runs.append(one_run(a.mesh))
        r = runs[-1]
        print(i, r["tets"], {g: round(r[f"goal_{g}"]["factor"], 3) for g in (0.3, 0.2)}, flush=True)
        a.out.write_text(json.dumps({"command": f"python benchmarks/archive/deflation_goal.py ZOO_DIR/"
                                                f"{Path(a.mesh).name} --runs {a.runs}", "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
