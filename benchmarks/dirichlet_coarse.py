"""Dirichlet's first coarse level with and without its nodes at fine Dirichlet nodes, on the same hierarchy.

    OMP_NUM_THREADS=1 python benchmarks/dirichlet_coarse.py [--zoo ZOO_DIR --meshes a.obj b.stl ...] --out FILE.json

``nestmg.setup_problem(..., "poisson-dirichlet")`` drops the first coarse level's nodes that sit at fine
Dirichlet nodes (the conforming coarse space) when they are at least
``nestmg.problems.CONFORMING_MIN_FRACTION`` of that level. This measures both choices on each default
hierarchy (``build_hierarchy(V, F, 3)``, the same one for both): the fraction, operator complexity, V-cycle
factor (stationary, to 1e-10), MG-PCG iterations to 1e-8, set-up and solve CPU seconds (median of
``--repeats``). The two thin-walled parts of ``csg_parts.py`` are always run: ``cup`` (a cylinder cup,
wall 1% of its height) and ``shell`` (a sphere shell 2.7% of its radius thick with a square window);
``--zoo`` adds files.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def thin_parts() -> dict:
    """The thin-walled solids of :mod:`csg_parts` (``cup``, ``shell``) as (V, F) (millimetres)."""
    from csg_parts import _parts

    out = {}
    for name, solid in _parts().items():
        if name in ("cup", "shell"):
            mesh = solid.to_mesh()
            out[name] = (np.asarray(mesh.vert_properties, dtype=float)[:, :3],
                         np.asarray(mesh.tri_verts, np.int64))
    return out


def measure(V: np.ndarray, F: np.ndarray, repeats: int) -> dict:
    """Both choices on one default hierarchy."""
    from nestmg import build_hierarchy, problems, setup_problem
    from solvers.fem import boundary_nodes
    from solvers.multilevel import convergence_factor

    t = time.perf_counter()
    H = build_hierarchy(V, F, 3, cache=False, progress=False)
    rec = {"hierarchy_seconds": time.perf_counter() - t, "tets": [len(T) for _, T in H.tets],
           "certified": H.certified}
    tets = H.tets_in("normalized")
    bnd = boundary_nodes(tets[0][1])
    on = problems._coarse_at_dirichlet(H.P[0].tocsr(), bnd)
    rec["fraction_at_dirichlet"] = on.size / H.P[0].shape[1]
    rule = problems.CONFORMING_MIN_FRACTION
    for label, frac in (("kept", np.inf), ("dropped", 0.0)):
        problems.CONFORMING_MIN_FRACTION = frac
        try:
            pr = setup_problem(tets, H.P, "poisson-dirichlet")
        finally:
            problems.CONFORMING_MIN_FRACTION = rule
        ml = pr.multigrid()
        _, info = ml.solve(pr.b, tol=1e-10, maxiter=80, accel=None, return_info=True)
        setups, solves, its = [], [], []
        for _ in range(repeats):
            t = time.process_time()
            ml = pr.multigrid()
            setups.append(time.process_time() - t)
            t = time.process_time()
            _, ci = ml.solve(pr.b, tol=1e-8, accel="cg", return_info=True)
            solves.append(time.process_time() - t)
            its.append(ci["iterations"])
        rec[label] = {"levels": [P.shape for P in pr.P], "operator_complexity": ml.operator_complexity(),
                      "factor": convergence_factor(info["residuals"]), "cycles": info["iterations"],
                      "pcg_iterations": max(its), "setup_cpu_seconds": statistics.median(setups),
                      "solve_cpu_seconds": statistics.median(solves)}
    rec["default"] = "dropped" if rec["fraction_at_dirichlet"] >= rule else "kept"
    return rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--zoo", type=Path, help="folder of closed surface meshes")
    ap.add_argument("--meshes", nargs="*", default=[], help="file names in --zoo")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    from exp_common import git_commit, write_json

    from nestmg import load_mesh
    from nestmg.problems import CONFORMING_MIN_FRACTION

    inputs = dict(thin_parts())
    for name in a.meshes:
        inputs[name] = tuple(load_mesh(a.zoo / name)[:2])
    cmd = "python benchmarks/dirichlet_coarse.py" + (" --zoo ZOO_DIR --meshes " + " ".join(a.meshes)
                                                      if a.meshes else "") + f" --repeats {a.repeats} --out FILE"
    doc = {"command": cmd, "commit": git_commit(), "rule": CONFORMING_MIN_FRACTION, "cases": {}}
    for name, (V, F) in inputs.items():
        doc["cases"][name] = rec = measure(V, F, a.repeats)
        k, d = rec["kept"], rec["dropped"]
        print(f"{name}: {rec['fraction_at_dirichlet']:.2f} at Dirichlet nodes (default: {rec['default']}); "
              f"complexity {k['operator_complexity']:.2f} -> {d['operator_complexity']:.2f}, factor "
              f"{k['factor']:.3f} -> {d['factor']:.3f}, MG-PCG {k['pcg_iterations']} -> {d['pcg_iterations']}, "
              f"CPU {k['setup_cpu_seconds'] + k['solve_cpu_seconds']:.3f} -> "
              f"{d['setup_cpu_seconds'] + d['solve_cpu_seconds']:.3f} s", flush=True)
        write_json(doc, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
