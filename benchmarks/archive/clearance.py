"""How the nested backend builds the TetWild clearance: seconds per mode, each mode in its own process.

Modes (``cagegen.nested.backend.nest_pair(clearance=...)``), all with ``min_gap = 2.5e-3`` of the
diagonal (2.5 x TetWild's default envelope) except ``none``:

* ``none``: no clearance (the reference cost);
* ``reinflate`` (default): flow and re-inflate the surface itself, then one last reverse step moves
  it out to its offset, the barrier pushing the cage ahead;
* ``flow``: flow and re-inflate the *offset* surface (the way before issue 14);
* ``offset``: tight cage, then the cage pushed out along its normals (CCD-bounded), ``reinflate``
  when blocked.

    python benchmarks/archive/clearance.py MESH [MESH ...] --modes none reinflate flow offset \\
        --json benchmarks/results/scale/clearance.json [--timeout 1500]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import run_child  # noqa: E402

_CHILD = r"""
import json, sys, time
from nestmg.io import load_mesh, normalize
import cagegen
a = json.loads(sys.argv[1])
V, F = load_mesh(a["mesh"]); V, _, _ = normalize(V)
t = time.perf_counter()
extra = {} if a["mode"] == "none" else {"clearance": a["mode"]}
layers, info = cagegen.build_cages(V, F, a["levels"], method="nested", return_info=True,
                                   min_gap=0.0 if a["mode"] == "none" else a["gap"], **extra)
out = {"seconds": time.perf_counter() - t, "faces": [len(f) for _, f in layers],
       "certified": info["certified"], "verify_seconds": info["seconds"]["verify"],
       "min_gap": [L["min_gap_relative"] for L in info["backend"]["layers"]],
       "layer_seconds": [L["seconds"] for L in info["backend"]["layers"]],
       "reinflate": [{k: L["reinflate"].get(k) for k in ("reverse_steps", "newton_iterations", "collision_builds",
                                                          "ccd_calls")} for L in info["backend"]["layers"]],
       "clearance_fallback": [L.get("clearance", {}).get("fallback") for L in info["backend"]["layers"]]}
print("RESULT " + json.dumps(out))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--modes", nargs="+", default=["none", "reinflate", "flow", "offset"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--gap", type=float, default=2.5e-3)
    ap.add_argument("--timeout", type=float, default=1500.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = []
    if args.json and Path(args.json).exists():
        rows = json.loads(Path(args.json).read_text())["runs"]
    for mesh in args.meshes:
        for mode in args.modes:
            res = run_child(_CHILD, {"mesh": mesh, "mode": mode, "levels": args.levels, "gap": args.gap},
                            timeout=args.timeout)
            r = {"mesh": Path(mesh).name, "mode": mode, **res}
            rows = [x for x in rows if not (x["mesh"] == r["mesh"] and x["mode"] == mode)] + [r]
            print(json.dumps({k: r.get(k) for k in ("mesh", "mode", "seconds", "faces", "min_gap", "error")}),
                  flush=True)
            if args.json:
                Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                Path(args.json).write_text(json.dumps({"runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
