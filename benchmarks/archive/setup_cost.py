"""``setup_problem`` against libigl's cotmatrix on one large fine tet mesh (issue 15, item 3).

    nice -n 10 python benchmarks/archive/setup_cost.py ZOO_DIR/bunny.off --fine-tets 1150000 \
        --out benchmarks/results/setup_cost

Meshes the input with TetGen (opt-in extra, for the measurement only; minratio 1.5, volume bound from
``--fine-tets``), then times ``igl.cotmatrix`` and ``nestmg.problems.setup_problem`` (single level:
stiffness, mass, boundary nodes, Dirichlet elimination) for Dirichlet and Neumann Poisson, best of
``--repeat`` in CPU (process) time -- all kernels are single-threaded, so the ratio is robust to other
jobs on a shared machine. Prints and writes ``setup_cost.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--fine-tets", type=int, default=1_150_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench_out/setup_cost"))
    args = ap.parse_args(argv)

    import igl
    import tetgen
    from exp_common import best_cpu_time as best
    from exp_common import edge_for_tets

    from nestmg.io import load_mesh, normalize
    from nestmg.problems import setup_problem

    V, F = load_mesh(args.mesh)
    V, _, _ = normalize(V)
    h = edge_for_tets(V, F, args.fine_tets)
    t0 = time.perf_counter()
    Vt, Tt = tetgen.TetGen(V, F).tetrahedralize(minratio=1.5, maxvolume=h**3 / (6 * np.sqrt(2)), fixedvolume=True,
                                                steinerleft=-1)[:2]
    t_mesh = time.perf_counter() - t0
    Vt = np.ascontiguousarray(Vt, dtype=np.float64)
    Tt = np.ascontiguousarray(Tt, dtype=np.int64)
    t_cot = best(lambda: igl.cotmatrix(Vt, Tt), args.repeat)
    doc = {"benchmark": "setup_cost", "mesh": args.mesh.name, "tets": len(Tt), "nodes": len(Vt),
           "tetgen_seconds": t_mesh, "cotmatrix_cpu_seconds": t_cot}
    for prob in ("poisson-dirichlet", "poisson-neumann"):
        t = best(lambda: setup_problem([(Vt, Tt)], [], prob), args.repeat)  # noqa: B023 -- called at once
        doc[prob] = {"setup_problem_cpu_seconds": t, "ratio_to_cotmatrix": t / t_cot}
    print(json.dumps(doc, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "setup_cost.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
