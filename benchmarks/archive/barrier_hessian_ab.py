"""Re-inflation's barrier Newton matrix: numpy Gauss-Newton against ipctk's PSD-projected Hessian.

Issue 27 (bounded cage cost): ipctk's ``BarrierPotential.hessian(..., CLAMP)`` was 0.6 of the 0.7 s of a
re-inflation Newton iteration on homer.obj. ``cagegen.nested.reinflate.BARRIER_HESSIAN`` selects the
Newton matrix; this study runs ``nestmg cages MESH --levels 3`` with the defaults (the same call as
``benchmarks/corpus.py``'s cages column) once with each, interleaved per mesh and repeat, in child
processes on one thread, and records per run: CPU and wall seconds, certification, face counts, and per
layer the phase seconds and the Newton iterations of the re-inflation and of the final phase. Run from
a checkout (the children import it through ``PYTHONPATH``)::

    PYTHONPATH=CHECKOUT OMP_NUM_THREADS=1 python benchmarks/archive/barrier_hessian_ab.py ZOO_DIR \\
        --out OUT.json --meshes homer.obj fandisk.obj --repeats 2
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

KINDS = ("ipctk", "gauss_newton")

_CHILD = r"""
import importlib, json, sys, tempfile, time
rf = importlib.import_module("cagegen.nested.reinflate")
rf.BARRIER_HESSIAN = sys.argv[2]
from nestmg.cli import _cage_options, _load, _typed_options, build_parser
from nestmg.hierarchy import build_cage_surfaces
args = build_parser().parse_args(["cages", sys.argv[1], "--levels", "3", "--no-cache", "--quiet", "--out",
                                  tempfile.mkdtemp(), "--method", "nested"])
_typed_options(args)
V, F, _ = _load(sys.argv[1])
t = time.perf_counter()
layers, info = build_cage_surfaces(V, F, args.levels, "nested", meshing=args.meshing, cache=False,
                                   progress=False, cages=_cage_options(args, "nested"))
rows = []
for L in (info.get("backend") or {}).get("layers", []):
    r = L.get("reinflate") or {}
    rows.append({"seconds": {k: v for k, v in L["seconds"].items() if k != "verify"},
                 "newton": r.get("newton_iterations"), "final": r.get("final_iterations"),
                 "failed_attempts": [a.get("reason") for a in L.get("failed_attempts", [])]})
print(json.dumps({"wall_in_process": time.perf_counter() - t,
                  "certified": bool((info.get("verification") or {}).get("ok")),
                  "faces": [len(Fk) for _, Fk in layers], "layers": rows}))
"""


def run_one(mesh: Path, kind: str, timeout: float) -> dict:
    """One child process: ``nestmg cages`` with the barrier Newton matrix ``kind``; CPU = user + system."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    env = dict(os.environ, OMP_NUM_THREADS="1")
    try:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(mesh), kind], capture_output=True, text=True,
                             timeout=timeout, env=env, cwd=tempfile.gettempdir())
    except subprocess.TimeoutExpired:
        return {"kind": kind, "error": f"timeout {timeout} s"}
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    rec = {"kind": kind, "wall_seconds": time.perf_counter() - t,
           "cpu_seconds": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
           "load_average_1min": os.getloadavg()[0]}
    lines = out.stdout.strip().splitlines()
    if out.returncode or not lines:
        rec["error"] = (out.stderr.strip().splitlines() or ["no output"])[-1]
    else:
        rec.update(json.loads(lines[-1]))
    return rec


def summary(runs: list) -> dict:
    """Per mesh and kind: median CPU and wall seconds, all certified, Newton iterations (first run)."""
    import numpy as np

    out: dict = {}
    for r in runs:
        if "error" in r:
            continue
        e = out.setdefault(r["mesh"], {}).setdefault(r["kind"], {"cpu": [], "wall": [], "certified": True,
                                                                  "newton": None, "final": None})
        e["cpu"].append(r["cpu_seconds"])
        e["wall"].append(r["wall_seconds"])
        e["certified"] &= bool(r.get("certified"))
        if e["newton"] is None:
            e["newton"] = [L["newton"] for L in r["layers"]]
            e["final"] = [L["final"] for L in r["layers"]]
    for kinds in out.values():
        for e in kinds.values():
            e["median_cpu"] = float(np.median(e.pop("cpu")))
            e["median_wall"] = float(np.median(e.pop("wall")))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    doc = {"command": "python benchmarks/archive/barrier_hessian_ab.py ZOO_DIR --meshes "
                      f"{' '.join(a.meshes)} --repeats {a.repeats} --out OUT.json",
           "date": time.strftime("%Y-%m-%d"), "runs": []}
    for rep in range(a.repeats):
        for name in a.meshes:
            for kind in (KINDS if rep % 2 == 0 else KINDS[::-1]):  # alternate who runs first
                rec = {"mesh": name, "repeat": rep, **run_one(Path(a.folder) / name, kind, a.timeout)}
                print(json.dumps({k: rec.get(k) for k in ("mesh", "kind", "cpu_seconds", "wall_seconds",
                                                          "certified", "error")}), flush=True)
                doc["runs"].append(rec)
                doc["summary"] = summary(doc["runs"])
                Path(a.out).write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
