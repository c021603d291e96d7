"""Does an exact local solve at a mesh's Neumann slow mode remove it? (issue 27, docs/pipeline.md limits)

On fresh default hierarchies of one mesh: the pure-Neumann two-grid pair of the two finest levels
(:func:`factor_spread.neumann_two_grid`), its asymptotic energy contraction, then the same with one exact
solve on the fine nodes within ``--radius`` of the slowest error's centre after every two-grid application
(``e <- e - A_RR^-1 (A e)_R``). A study of the cause, not a smoother the package offers. Run from
``benchmarks/``'s parent::

    python benchmarks/archive/local_solve_slow_mode.py ZOO_DIR/decimated-knight.off --runs 3 \\
        --out benchmarks/results/corpus/local_solve_knight.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from corpus import _cli_args  # noqa: E402
from factor_spread import contraction, neumann_two_grid  # noqa: E402


def one_run(mesh: Path, radius: float) -> dict:
    from nestmg.cli import _hierarchy, _load

    args = _cli_args("solve", mesh, [])
    V, F, _ = _load(str(mesh))
    h = _hierarchy(V, F, args)
    tets = h.tets_in("normalized")
    A, M = neumann_two_grid(tets, h.P)
    A = A.tocsr()
    plain, e = contraction(A, lambda e: e - M @ (A @ e))
    local = np.abs(e * (A @ e))
    X = tets[0][0]
    centre = X[np.argsort(-local)[: max(1, A.shape[0] // 100)]].mean(axis=0)
    R = np.flatnonzero(np.linalg.norm(X - centre, axis=1) < radius)
    lu = spla.splu(A[R][:, R].tocsc())

    def with_local(e):
        e = e - M @ (A @ e)
        e[R] -= lu.solve((A @ e)[R])
        return e

    return {"tets": [len(T) for _, T in tets], "centre": centre.tolist(), "local_nodes": int(len(R)),
            "contraction": plain, "contraction_with_local_solve": contraction(A, with_local)[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--radius", type=float, default=0.03, help="of the unit-diagonal shape")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    doc = {"command": (f"python benchmarks/archive/local_solve_slow_mode.py ZOO_DIR/{args.mesh.name} "
                       f"--runs {args.runs} --radius {args.radius} --out OUT/{args.out.name}"), "runs": []}
    for i in range(args.runs):
        doc["runs"].append(one_run(args.mesh, args.radius))
        r = doc["runs"][-1]
        print(f"run {i + 1}: contraction {r['contraction']:.3f} -> {r['contraction_with_local_solve']:.3f} "
              f"({r['local_nodes']} local nodes)", flush=True)
        args.out.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
