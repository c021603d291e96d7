"""Diffusion V-cycle factor on fresh default hierarchies: reverse steps with ipctk's Hessian or Gauss-Newton.

Issue 27, item 2 (``nestmg cages`` against the reference wheel): ``cagegen.nested.reinflate.REVERSE_HESSIAN``
selects the Newton matrix of the re-inflation's reverse steps (the final phase keeps ipctk's projected
Hessian). The cages then differ at ~1e-5 of their volume, and a cage change can move a mesh's V-cycle
factor, so this study builds the default ``nestmg solve MESH`` hierarchy (the corpus's ``case_solve``
call, ``--levels 3``, no cache) from scratch once per mode, interleaved per mesh and repeat, in child
processes on one OpenMP thread, and records the ``diffusion-neumann`` V-cycle factor (no Krylov
acceleration), the cycles, the face and tet counts, the fallbacks and the hierarchy's seconds.

The modes set ``_Problem.hessian_kind`` right after construction, so they also run on a tree from before
``REVERSE_HESSIAN`` existed (there ``ipctk`` is that tree's own behaviour)::

    python benchmarks/archive/reverse_hessian_factor.py ZOO_DIR --tree CHECKOUT \\
        --meshes homer.obj pepper.ply decimated-max.obj --repeats 2 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

MODES = ("ipctk", "gauss_newton")

_CHILD = r"""
import importlib, json, os, sys, time
from dataclasses import replace
from pathlib import Path
rf = importlib.import_module("cagegen.nested.reinflate")
mode = sys.argv[2]
init = rf._Problem.__init__
def patched(self, *a, **k):
    init(self, *a, **k)
    self.hessian_kind = mode
rf._Problem.__init__ = patched
sys.path.insert(0, os.path.join(sys.argv[3], "benchmarks"))
from corpus import _cli_args
from nestmg.cli import _hierarchy, _load, _solve
mesh = Path(sys.argv[1])
args = _cli_args("solve", mesh, [])
V, F, _ = _load(str(mesh))
t = time.perf_counter()
h = _hierarchy(V, F, args)
seconds = time.perf_counter() - t
args.problem = "diffusion-neumann"
args.solver = replace(args.solver, accel=None)
r = _solve(h, args)
print(json.dumps({"hierarchy_seconds": seconds, "faces": [len(Fk) for _, Fk in h.surfaces],
                  "tets": [len(T) for _, T in h.tets], "fallbacks": h.fallbacks, "certified": h.certified,
                  "factor": r["factor"], "cycles": r["iterations"], "converged": r["converged"]}))
"""


def run(tree: Path, mesh: Path, mode: str) -> dict:
    """One fresh hierarchy and diffusion solve of ``mesh`` from ``tree`` with the reverse-step ``mode``."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(mesh), mode, str(tree)], env=env,
                          capture_output=True, text=True, cwd=str(tree))
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or [""])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--tree", type=Path, required=True, help="checkout imported by the children")
    ap.add_argument("--label", help="the tree's commit")
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    out = {"command": "python benchmarks/archive/reverse_hessian_factor.py ZOO_DIR --tree CHECKOUT --meshes "
                      + " ".join(args.meshes) + f" --repeats {args.repeats}",
           "tree": args.label, "load_before": os.getloadavg()[0], "runs": []}
    for rep in range(args.repeats):
        for name in args.meshes:
            for mode in MODES:
                row = {"mesh": name, "mode": mode, "repeat": rep + 1}
                row.update(run(args.tree, args.folder / name, mode))
                out["runs"].append(row)
                print(name, mode, row.get("factor"), row.get("error", ""), flush=True)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
