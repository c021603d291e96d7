"""One-off study (issue 27, item 3): the deflation probe's goal against the factor it must deliver.

``nestmg solve MESH --levels 3``'s default hierarchy is built ``--runs`` times (TetWild gives a different
mesh each run); on each, every problem of ``--problems`` is solved with the cycle of ``Problem.multigrid()``
under each probe goal ``deflate_goal = margin x FACTOR_GOALS[problem]`` of ``--margins``: stationary
V-cycle factor, MG-PCG iterations, set-up CPU seconds and the probes' reports. Writes one JSON.

    OMP_NUM_THREADS=1 python benchmarks/archive/deflation_goal.py ZOO_DIR/idler_riser.stl --runs 8 \
        --problems poisson-dirichlet --goals 0.3 0.2 --out OUT.json      # the study of 8c7c925
    OMP_NUM_THREADS=1 python benchmarks/archive/deflation_goal.py ZOO_DIR/lucy.ply --runs 3 \
        --problems poisson-neumann diffusion-neumann --margins 1.0 0.9 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _measure(p, goal: float) -> dict:
    t = time.process_time()
    ml = p.multigrid(deflate_goal=goal)
    setup = time.process_time() - t
    t = time.process_time()
    ml.probe()  # the finest level's probe, deferred to the first stationary solve
    probe = time.process_time() - t
    _, info = ml.solve(p.b, tol=1e-10, maxiter=60, return_info=True)
    _, cg = ml.solve(p.b, tol=1e-8, accel="cg", return_info=True)
    return {"goal": goal, "factor": info["factor"], "cycles": info["iterations"],
            "pcg_iterations": cg["iterations"], "setup_cpu_seconds": setup, "fine_probe_cpu_seconds": probe,
            "stationary_cpu_seconds": info["seconds"],
            "deflation": [{k: d.get(k) for k in ("level", "probe_factor", "vectors", "local_solve", "reverted")}
                          for d in ml.deflation]}


def one_run(mesh: str, problems: list[str], goals: dict[str, list[float]]) -> dict:
    from corpus import _cli_args  # the corpus' own `nestmg solve` arguments: the defaults

    from nestmg.bodies import file_frame
    from nestmg.cli import _hierarchy, _load
    from nestmg.problems import setup_problem

    args = _cli_args("solve", Path(mesh), [])
    V, F, _ = _load(mesh)
    h = _hierarchy(V, F, args)
    center, scale = file_frame(V)  # posed as `nestmg solve` poses them (diffusion's lambda is not scale-free)
    tets = [((Vt - center) / scale, T) for Vt, T in h.tets]
    rec = {"tets": [len(T) for _, T in h.tets], "certified": h.certified, "problems": {}}
    for name in problems:
        p = setup_problem(tets, h.P, name)
        rec["problems"][name] = [_measure(p, g) for g in goals[name]]
    return rec


def main() -> int:
    from nestmg.problems import FACTOR_GOALS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--problems", nargs="+", default=["poisson-dirichlet"], choices=sorted(FACTOR_GOALS))
    ap.add_argument("--goals", nargs="+", type=float, help="absolute probe goals (one list for every problem)")
    ap.add_argument("--margins", nargs="+", type=float, default=[1.0, 0.9],
                    help="probe goals as fractions of each problem's FACTOR_GOALS (unless --goals)")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    goals = {p: a.goals or [round(m * FACTOR_GOALS[p], 6) for m in a.margins] for p in a.problems}
    args = " ".join(sys.argv[2:]).replace(str(a.out), "OUT.json")
    runs = []
    for i in range(a.runs):
        runs.append(one_run(a.mesh, a.problems, goals))
        r = runs[-1]
        print(i, r["tets"], {p: [(m["goal"], round(m["factor"], 3), m["pcg_iterations"],
                                  round(m["setup_cpu_seconds"], 2)) for m in ms]
                             for p, ms in r["problems"].items()}, flush=True)
        a.out.write_text(json.dumps({"command": f"python benchmarks/archive/deflation_goal.py ZOO_DIR/"
                                                f"{Path(a.mesh).name} {args}", "goals": goals, "runs": runs},
                                    indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
