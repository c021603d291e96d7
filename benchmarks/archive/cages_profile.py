"""Where ``nestmg cages MESH --levels 3`` (nested, defaults) spends its CPU seconds: a cProfile breakdown.

Issue 27, item 2 (bounded cage cost). Each mesh runs in its own child process (``PYTHONPATH`` names the
checkout, one OpenMP/BLAS thread) under ``cProfile`` with ``time.process_time`` as its clock; the JSON
records per mesh the total CPU seconds under the profiler (its overhead included: Python-heavy parts
read high), the self time of ipctk's three hot calls (barrier Hessian, collision-set build, CCD) and the
cumulative time of the stages (re-inflation, flow, envelope target, decimation, verification, input
audit), and per layer the backend's own phase seconds, Newton iterations and failed attempts::

    PYTHONPATH=CHECKOUT OMP_NUM_THREADS=1 python benchmarks/archive/cages_profile.py ZOO_DIR \\
        --meshes homer.obj pepper.ply --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = r"""
import cProfile, json, pstats, sys, time
from pathlib import Path
from nestmg.cli import main
mesh, out = sys.argv[1], Path(sys.argv[2])
prof = cProfile.Profile(time.process_time)
prof.enable()
main(["cages", mesh, "--levels", "3", "--method", "nested", "--out", str(out), "--no-cache", "--quiet"])
prof.disable()
st = pstats.Stats(prof).stats
builtin = {"hessian": "<built-in method ipctk.hessian>", "collision_build": "<built-in method ipctk.build>",
           "ccd": "<built-in method ipctk.compute_collision_free_stepsize>"}
stages = {"reinflate": ("reinflate.py", "reinflate"), "flow": ("flow.py", "flow_inside"),
          "envelope_target": ("backend.py", "_envelope_target"),
          "decimate": ("decimate.py", "decimate_surface"),
          "verify": ("verify.py", "verify_nesting"), "audit": ("audit.py", "check_mesh")}
row = {"cpu_seconds_profiled": max(v[3] for v in st.values())}
for key, name in builtin.items():
    row[key] = sum(v[2] for k, v in st.items() if k[2] == name)
for key, (fn, name) in stages.items():
    row[key] = max([v[3] for k, v in st.items() if k[0].endswith(fn) and k[2] == name] or [0.0])
rep = json.loads((out / "report.json").read_text())
row["layers"] = [{"layer": L["layer"], "n_faces": L["n_faces"], "source": L["decimation"].get("source"),
                  "seconds": L["seconds"], "newton_iterations": L["reinflate"].get("newton_iterations"),
                  "final_iterations": L["reinflate"].get("final_iterations"),
                  "failed_attempts": [{k: f.get(k) for k in ("action", "stage", "reason", "seconds")}
                                      for f in L.get("failed_attempts", [])]}
                 for L in rep["backend"]["layers"]]
print(json.dumps(row))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--label", help="the commit profiled")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = {"command": "python benchmarks/archive/cages_profile.py ZOO_DIR --meshes " + " ".join(args.meshes),
           "commit": args.label, "load_before": os.getloadavg()[0], "meshes": {}}
    for name in args.meshes:
        with tempfile.TemporaryDirectory(prefix="cages-prof-") as tmp:
            proc = subprocess.run([sys.executable, "-c", _CHILD, str(args.folder / name), tmp], env=env,
                                  capture_output=True, text=True, cwd=tmp)
        if proc.returncode != 0:
            out["meshes"][name] = {"error": (proc.stderr.strip().splitlines() or [""])[-1]}
        else:
            out["meshes"][name] = json.loads(proc.stdout.strip().splitlines()[-1])
        r = out["meshes"][name]
        print(name, {k: round(v, 2) for k, v in r.items() if isinstance(v, float)}, flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
