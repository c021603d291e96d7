"""One ``sdf`` cage of a large input: a dev-zoo mesh subdivided until it is large (issue 17).

The dev zoo stops at 40k faces; users bring 50k-500k. This script subdivides a zoo mesh ``--subdiv``
times (``igl.upsample``: each face into 4, the surface unchanged, so the exact coplanar pieces are a
worst case for the exact predicates) and builds one ``sdf`` layer at the 4x level with the backend's
defaults, recording the seconds per phase, the estimate the time budget uses
(:func:`cagegen.sdf.backend.estimate_layer_seconds`), distance, quality and the tightening record.

Usage::

    OMP_NUM_THREADS=1 taskset -c 0 python benchmarks/sdf_large_input.py ZOO_DIR/gargo.off \\
        --subdiv 2 --out benchmarks/results/sdf/large_gargo_x2.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np
from exp_common import read_mesh


def main(argv=None) -> dict:
    import igl

    from cagegen import default_face_counts, verify_nesting
    from cagegen.sdf.backend import estimate_layer_seconds, sdf_cage_layer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--subdiv", type=int, default=2, help="igl.upsample rounds (x4 faces each)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    V, F = read_mesh(args.mesh)
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    for _ in range(args.subdiv):
        V, F = igl.upsample(V, F)
    n = default_face_counts(len(F), 2)[0]
    t, c = time.perf_counter(), time.process_time()
    U, G, info = sdf_cage_layer(V, F, n)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    d_in = float(np.sqrt(igl.point_mesh_squared_distance(V, U, G)[0].max())) / diag
    rep = verify_nesting([(V, F), (U, G)])
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parent).stdout.strip() or None
    except OSError:
        commit = None
    out = {
        "mesh": args.mesh.name, "subdiv": args.subdiv, "input_faces": len(F), "cage_faces": len(G),
        "commit": commit, "wall_seconds": wall, "cpu_seconds": cpu,
        "estimate_seconds": estimate_layer_seconds(len(F)),
        "seconds": info["seconds"], "certified_again": bool(rep.ok),
        "input_to_cage_relative": d_in, "hausdorff_relative": info["hausdorff_relative"],
        "genus": info["genus"], "genus_fine": info["genus_fine"], "min_angle_deg": info["min_angle_deg"],
        "mips_mean": info["mips_mean"], "mips_max": info["mips_max"],
        "optimize": {k: info["optimize"].get(k) for k in ("steps", "flips", "seconds", "certified")},
        "tighten": info["tighten"], "c_used": info["c_used"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1, default=str))
    print(json.dumps({k: out[k] for k in ("input_faces", "cage_faces", "wall_seconds", "estimate_seconds",
                                          "input_to_cage_relative", "min_angle_deg", "mips_max")}))
    return out


if __name__ == "__main__":
    main()
