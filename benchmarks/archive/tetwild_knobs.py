"""TetWild's own knobs at scale: time, peak memory, size and quality of the fine tet mesh.

Each configuration runs in a fresh subprocess (so its peak resident memory is its own) on the
normalised input (unit bounding-box diagonal). The target edge length is chosen from the wanted tet
count by :func:`nestmg.sizing.edge_length_for_tets`. Reported per run: seconds, tets, nodes, min /
1st-percentile dihedral angle, slivers (min dihedral < 5 degrees), boundary deviation from the input
(max over boundary nodes, relative to the diagonal) and peak RSS.

    python benchmarks/archive/tetwild_knobs.py MESH --tets 250000 1000000 \\
        --configs default stop30 stop30_it20 --json benchmarks/results/scale/tetwild_knobs.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import run_child  # noqa: E402

CONFIGS = {
    "default": {"epsilon": 1e-3, "stop_energy": 10.0, "max_opt_iter": 80},
    "stop30": {"epsilon": 1e-3, "stop_energy": 30.0, "max_opt_iter": 80},
    "stop30_it20": {"epsilon": 1e-3, "stop_energy": 30.0, "max_opt_iter": 20},
    "stop100_it10": {"epsilon": 1e-3, "stop_energy": 100.0, "max_opt_iter": 10},
    "eps2e-3": {"epsilon": 2e-3, "stop_energy": 10.0, "max_opt_iter": 80},
    "eps2e-3_stop30_it20": {"epsilon": 2e-3, "stop_energy": 30.0, "max_opt_iter": 20},
    "1thread_stop30_it20": {"epsilon": 1e-3, "stop_energy": 30.0, "max_opt_iter": 20, "threads": 1},
    "predec": {"epsilon": 1e-3, "stop_energy": 10.0, "max_opt_iter": 80, "predecimate": True},
    "predec_stop30_it20": {"epsilon": 1e-3, "stop_energy": 30.0, "max_opt_iter": 20, "predecimate": True},
    "predec_eps2e-3": {"epsilon": 2e-3, "stop_energy": 10.0, "max_opt_iter": 80, "predecimate": True},
    "predec_eps5e-4": {"epsilon": 5e-4, "stop_energy": 10.0, "max_opt_iter": 80, "predecimate": True},
    "predec_1thread": {"epsilon": 1e-3, "stop_energy": 10.0, "max_opt_iter": 80, "threads": 1, "predecimate": True},
}

_CHILD = r"""
import json, resource, sys, time
import numpy as np, igl
from nestmg.io import load_mesh, normalize
from nestmg.sizing import edge_length_for_tets
from nestmg.tetmesh import tetrahedralize, tet_quality
from solvers.fem import boundary_faces
args = json.loads(sys.argv[1])
V, F = load_mesh(args["mesh"])
V, _, _ = normalize(V)
h = edge_length_for_tets(V, F, args["tets"], "tetwild")
cfg = dict(args["cfg"])
n_in = len(F)
V0, F0 = V, F
if cfg.pop("predecimate", False):  # decimate the input to ~the target edge first (nestmg.hierarchy)
    from nestmg.hierarchy import predecimate
    V, F = predecimate(V, F, h, max_error=0.5 * cfg.get("epsilon", 1e-3))[:2]
t0 = time.perf_counter()
Vt, T = tetrahedralize(V, F, mesher="tetwild", edge_length_abs=h, **cfg)
sec = time.perf_counter() - t0
q = tet_quality(Vt, T)
B, _ = boundary_faces(T)
bn = np.unique(B)
d2, _, _ = igl.point_mesh_squared_distance(Vt[bn], V0, F0)
out = {"seconds": sec, "input_faces": n_in, "meshed_faces": int(len(F)), "tets": int(len(T)), "nodes": int(len(Vt)), "edge_length": h,
       "boundary_faces": int(len(B)), "max_boundary_deviation": float(np.sqrt(d2.max())),
       "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, **q}
print("RESULT " + json.dumps(out))
"""


def run_one(mesh: str, tets: int, cfg: dict) -> dict:
    """Mesh ``mesh`` once with ``cfg`` in a subprocess; returns its figures (or the error)."""
    return run_child(_CHILD, {"mesh": mesh, "tets": tets, "cfg": cfg})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--tets", type=int, nargs="+", default=[250_000, 1_000_000])
    ap.add_argument("--configs", nargs="+", default=["default", "stop30_it20"], choices=sorted(CONFIGS))
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = []
    if args.json and Path(args.json).exists():
        rows = json.loads(Path(args.json).read_text())["runs"]
    for mesh in args.meshes:
        for n in args.tets:
            for name in args.configs:
                r = {"mesh": Path(mesh).name, "target_tets": n, "config": name, **CONFIGS[name],
                     **run_one(mesh, n, CONFIGS[name])}
                rows.append(r)
                print(json.dumps(r), flush=True)
                if args.json:  # keep partial results of long sweeps
                    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                    Path(args.json).write_text(json.dumps({"runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
