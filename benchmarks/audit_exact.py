"""CPU seconds of the input audit (``cagegen.check_mesh``, exact self-intersection test) on inputs with
many exactly coplanar faces: a CAD part (fandisk) and zoo meshes subdivided by ``igl.upsample`` (every
face split in four in its plane), where the floating-point filter of ``orient3d`` cannot decide and the
exact fallback runs.

Usage::

    OMP_NUM_THREADS=1 taskset -c 0 python benchmarks/audit_exact.py ZOO_DIR \\
        --cases fandisk.obj:0 fandisk.obj:1 gargo.off:2 --out benchmarks/results/audit/audit_exact.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from exp_common import read_mesh


def main(argv=None) -> dict:
    import igl

    import cagegen
    from cagegen import MeshInputError, check_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", type=Path)
    ap.add_argument("--cases", nargs="+", default=["fandisk.obj:0", "fandisk.obj:1", "gargo.off:2"],
                    help="MESH:SUBDIVISIONS")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = []
    for case in args.cases:
        name, up = case.rsplit(":", 1)
        V, F = read_mesh(args.zoo / name)
        V, F = np.asarray(V, float), np.asarray(F, np.int64)
        for _ in range(int(up)):
            V, F = igl.upsample(V, F)
        t = time.process_time()
        try:
            rep = check_mesh(V, F)
            ok, error = bool(getattr(rep, "ok", True)), None
        except MeshInputError as exc:  # a refused input is a result too (its time and the first reason)
            ok, error = False, str(exc).splitlines()[-1].strip(" -")
        rows.append({"mesh": name, "subdiv": int(up), "faces": len(F), "audit_cpu_seconds": time.process_time() - t,
                     "ok": ok, "error": error})
        print(json.dumps(rows[-1]), flush=True)
    out = {"cagegen": str(Path(cagegen.__file__).parent), "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
