"""TetWild's passes on the cage levels: fTetWild's 80 against ``MeshingOptions.coarse_max_opt_iter`` (20).

A cage's long thin triangles can leave a few tets just above fTetWild's stop energy; fTetWild then halves
its sizing field around them every few passes and its working mesh doubles, until its 80 passes are spent
(decimated-knight.off: 560-810 s on a 250-face cage layer in about one run of three). The cages differ
between runs (ipctk's parallel sums), so each repeat builds the default hierarchy from scratch
(``build_hierarchy(V, F, levels=3, cache=False)``) with one cap and then the other, alternating, under a
per-call time limit (``$NESTMG_MESH_TIME_LIMIT``): a call past it is recorded as a runaway. Recorded per
run: wall seconds of each TetWild call (in its worker process), tets per level, certified.

    python benchmarks/archive/cage_tetwild_passes.py ZOO_DIR/decimated-knight.off --repeats 6 \\
        --limit 120 --out FILE.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import nestmg.hierarchy as hh  # noqa: E402
from nestmg import MeshingOptions, build_hierarchy, load_mesh  # noqa: E402


def one_run(V, F, cap: int) -> dict:
    """The default hierarchy with ``coarse_max_opt_iter=cap``: seconds per TetWild call, tets, outcome."""
    calls = []
    real = hh.tetrahedralize

    def timed(Vs, Fs, **kw):
        t = time.perf_counter()
        try:
            return real(Vs, Fs, **kw)
        finally:
            calls.append({"faces": len(Fs), "passes": kw.get("max_opt_iter"),
                          "seconds": time.perf_counter() - t})

    hh.tetrahedralize = timed
    t = time.perf_counter()
    try:
        H = build_hierarchy(V, F, 3, meshing=MeshingOptions(coarse_max_opt_iter=cap), cache=False,
                            progress=False)
        out = {"ok": True, "certified": bool(H.certified), "tets": [len(T) for _, T in H.tets]}
    except Exception as exc:  # noqa: BLE001 - a timeout is a result here
        out = {"ok": False, "error": f"{type(exc).__name__}: {str(exc)[:200]}"}
    finally:
        hh.tetrahedralize = real
    return {"cap": cap, "seconds": time.perf_counter() - t, "calls": calls, **out}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--limit", type=float, default=120.0, help="seconds per TetWild call")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    os.environ["NESTMG_MESH_TIME_LIMIT"] = str(args.limit)
    V, F = load_mesh(args.mesh)[:2]
    runs = []
    for rep in range(args.repeats):
        for cap in ((80, 20) if rep % 2 == 0 else (20, 80)):
            runs.append(dict(one_run(V, F, cap), repeat=rep))
            r = runs[-1]
            print(rep, cap, f"{r['seconds']:.1f} s", [round(c["seconds"], 1) for c in r["calls"]],
                  r.get("tets", r.get("error")), flush=True)
            args.out.write_text(json.dumps({"command": "benchmarks/archive/cage_tetwild_passes.py",
                                            "mesh": args.mesh.name, "limit": args.limit, "runs": runs},
                                           indent=1))


if __name__ == "__main__":
    main()
