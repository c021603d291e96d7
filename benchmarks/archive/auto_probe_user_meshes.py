"""Which hierarchies ``MultigridSolver(deflate="auto")`` (the default) probes: the 1M-tet user meshes.

    OMP_NUM_THREADS=1 python benchmarks/archive/auto_probe_user_meshes.py WORK/bunny-tetgen WORK/spot-tetgen \
        WORK/bunny-tetwild WORK/spot-tetwild --out benchmarks/results/user_mesh/auto_probe.json

``WORK/*`` are the case folders of ``benchmarks/user_mesh_solvers.py build``. For each case and problem: the
operator complexity of the constructor's Galerkin hierarchy, the ``deflate`` it resolved to (0 above
``solvers.multilevel.AUTO_PROBE_MAX_COMPLEXITY``) and the levels probed (none expected).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from user_mesh_solvers import load_case

from solvers import MultigridSolver
from solvers.multilevel import AUTO_PROBE_MAX_COMPLEXITY


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = []
    for work in args.cases:
        case = load_case(work)
        for prob in ("dirichlet", "neumann", "diffusion"):
            A, _b, Ps, ns = case[prob]
            ml = MultigridSolver(A, Ps, nullspace=ns)
            rows.append({"case": case["label"], "tets": case["tets"], "problem": prob,
                         "operator_complexity": ml.operator_complexity(), "deflate": int(ml.deflate),
                         "probed_levels": [d["level"] for d in ml.deflation]})
            print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()
    args.out.write_text(json.dumps({"command": "OMP_NUM_THREADS=1 python benchmarks/archive/auto_probe_user_meshes.py "
                                    "WORK/bunny-tetgen WORK/spot-tetgen WORK/bunny-tetwild WORK/spot-tetwild --out FILE",
                                    "commit": commit, "bound": AUTO_PROBE_MAX_COMPLEXITY, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
