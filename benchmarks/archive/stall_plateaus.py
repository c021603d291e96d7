"""How long a re-inflation reverse step that goes on to converge plateaus: evidence for ``STALL_NEWTON``.

A reverse step gives up (``cagegen.nested.reinflate._stalled``) when its best |F - target| has not halved
in ``STALL_NEWTON`` Newton iterations; a window longer than any converging step's plateau only costs time
on targets that fail anyway. Per mesh, ``nestmg cages MESH --levels 3`` (the corpus's ``case_cages``
call) runs in a child process on one OpenMP thread with ``_stalled`` wrapped: for every ``best`` list (one
per reverse step; a switch of the Newton matrix starts a new one) it records the longest window with no
halving (the plateau), the iterations and whether the step stalled. The JSON keeps per mesh the
histogram of the plateaus of the steps that did not stall, their maximum, and the stalled steps::

    PYTHONPATH=CHECKOUT python benchmarks/archive/stall_plateaus.py ZOO_DIR --meshes homer.obj gargo.off \\
        --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

_CHILD = r"""
import importlib, json, os, sys, time
from pathlib import Path
rf = importlib.import_module("cagegen.nested.reinflate")
recs, cur = [], {"best": None}
stalled0 = rf._stalled

def plateau(best):
    n = 0
    while n + 1 < len(best) and best[-1] > 0.5 * best[-2 - n]:
        n += 1
    return n

def stalled(best):
    if cur["best"] is not best:
        if cur["best"] is not None:
            recs.append(cur["rec"])
        cur["best"], cur["rec"] = best, {"max_plateau": 0, "iters": 0, "stalled": False}
    r = cur["rec"]
    r["iters"] += 1
    r["max_plateau"] = max(r["max_plateau"], plateau(best))
    r["stalled"] = bool(stalled0(best))
    return r["stalled"]

rf._stalled = stalled
sys.path.insert(0, os.path.join(sys.argv[2], "benchmarks"))
from corpus import case_cages
t = time.process_time()
res = case_cages(Path(sys.argv[1]), "nested")
if cur["best"] is not None:
    recs.append(cur["rec"])
ok = [r for r in recs if not r["stalled"]]
hist = {}
for r in ok:
    hist[r["max_plateau"]] = hist.get(r["max_plateau"], 0) + 1
print(json.dumps({"cpu": time.process_time() - t, "faces": res["faces"], "fallbacks": res["fallbacks"],
                  "steps": len(recs), "stalled_steps": len(recs) - len(ok),
                  "max_plateau_not_stalled": max([r["max_plateau"] for r in ok] or [0]),
                  "plateau_hist": hist, "stalled_iters": [r["iters"] for r in recs if r["stalled"]]}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--label", help="the commit measured")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    tree = Path(os.environ.get("PYTHONPATH", ".").split(os.pathsep)[0]).resolve()
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = {"command": "python benchmarks/archive/stall_plateaus.py ZOO_DIR --meshes " + " ".join(args.meshes),
           "commit": args.label, "meshes": {}}
    for name in args.meshes:
        proc = subprocess.run([sys.executable, "-c", _CHILD, str(args.folder / name), str(tree)], env=env,
                              capture_output=True, text=True, cwd=str(tree))
        out["meshes"][name] = (json.loads(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else
                               {"error": (proc.stderr.strip().splitlines() or [""])[-1]})
        print(name, out["meshes"][name].get("max_plateau_not_stalled"), flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
