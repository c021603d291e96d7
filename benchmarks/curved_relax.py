"""Interior relaxation of curved P2: scaled Jacobians, facet distance and accuracy, with and without a floor.

For every MESH: the hierarchy and the manufactured problems of ``benchmarks/curved.py`` (level 1 curved
onto the input surface, P2 on it has the unknowns of P1 on level 0). Level 1 is curved these ways:

* ``projected``: boundary nodes projected, nothing else (the default of :func:`nestmg.curved.curve_mesh`);
* ``floor F`` (``--floors``): the same, then the scaled-Jacobian floor ``F`` (boundary nodes backed off);
* ``relaxed``: the interior relaxation (``relax=--relax``: interior edge nodes moved by
  :func:`nestmg.curved_fit.jacobian_spread_energy`, boundary nodes untouched);
* ``relaxed, floor F``: the relaxation, then the floor.

Recorded per curving: scaled Jacobian min / mean (sampled, and the certified bound), tets below each
floor, edge nodes backed off, facet distance to the input, CPU seconds of the curving; per problem
(Dirichlet; Neumann with the smooth normal) the L2 error of curved P2 against ``u`` and MG-PCG
iterations, beside P1 on level 0 and straight P2.

Run from the repository root::

    OMP_NUM_THREADS=1 python benchmarks/curved_relax.py ZOO_DIR/bunny.off \\
        --json benchmarks/results/curved/relax_bunny.json   # and gargo_1000.off, fandisk.obj: one JSON each
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path


from curved import _hierarchy, p1_case, p2_case  # benchmarks/ is sys.path[0]
from exp_common import git_commit, write_json
from nestmg.curved import curve_mesh, scaled_jacobians, surface_projector


def _curving(h, proj, relax, floor) -> tuple:
    """Curve level 1; the report plus CPU seconds and the count below each floor."""
    t0 = time.process_time()
    cm = curve_mesh(*h.tets_in("normalized")[1], proj, relax=relax, sj_floor=floor)
    rep = cm.report | {"cpu_seconds": time.process_time() - t0}
    sj, lb = scaled_jacobians(cm.X, cm.T10), scaled_jacobians(cm.X, cm.T10, bound=True)
    rep["below"] = {f"{f:g}": {"sampled": int((sj < f).sum()), "bound": int((lb < f).sum())}
                    for f in (0.9, 0.955, 0.96, 0.97)}
    return cm, rep


def run_mesh(path: str, args) -> dict:
    h, n_faces, t_h = _hierarchy(path, args)
    Vs, Fs = h.surfaces_in("normalized")[0]
    proj = surface_projector(Vs, Fs, normals="smooth")
    variants = [("projected", None, None)] + [(f"floor {f:g}", None, f) for f in args.floors] \
        + [("relaxed", args.relax, None)] + [(f"relaxed, floor {f:g}", args.relax, f) for f in args.floors]
    cms, out = {}, {"mesh": Path(path).name, "input_faces": n_faces,
                    "hierarchy": {"tets": [len(T) for _, T in h.tets], "seconds": t_h}, "curvings": {}}
    for label, relax, floor in variants:
        cm, rep = _curving(h, proj, relax, floor)
        cms[label], out["curvings"][label] = cm, rep
        sj = rep["scaled_jacobian"]
        print(f"{out['mesh']} {label}: SJ min {sj['min']:.3f} (bound {sj['bound_min']:.3f}) mean "
              f"{sj['mean']:.4f}, below 0.955 {rep['below']['0.955']['sampled']}, facet max "
              f"{rep['surface_distance']['curved_max']:.2e}, {rep['cpu_seconds']:.1f} s CPU", flush=True)
    Vp = cms["projected"].X  # P1 on level 0: its nodes are the projected curving's nodes
    out["problems"] = {}
    for name in ("poisson-dirichlet", "poisson-neumann"):
        r = {"P1": p1_case(h, Vp, name, proj, args.tol),
             "P2_straight": p2_case(h, None, name, proj, args.tol),
             "P2_curved": {label: p2_case(h, cm, name, proj, args.tol) for label, cm in cms.items()}}
        out["problems"][name] = r
        print(f"{out['mesh']} {name}: P1 {r['P1']['l2_error']:.3e}, straight "
              f"{r['P2_straight']['l2_error']:.3e}, " + ", ".join(
                  f"{k} {v['l2_error']:.3e} ({v['iterations']} it)" for k, v in r["P2_curved"].items()),
              flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("meshes", nargs="+", help="closed surface meshes (e.g. ZOO_DIR/bunny.off)")
    p.add_argument("--json", required=True, help="output JSON")
    p.add_argument("--levels", type=int, default=4)
    p.add_argument("--method", default="nested")
    p.add_argument("--edge-length", type=float, default=0.015, help="fine edge / bbox diagonal")
    p.add_argument("--relax", type=float, default=0.97, help="threshold of the interior relaxation")
    p.add_argument("--floors", type=float, nargs="+", default=[0.96])
    p.add_argument("--tol", type=float, default=1e-8)
    args = p.parse_args(argv)
    zoo = " ".join(f"ZOO_DIR/{Path(m).name}" for m in args.meshes)
    res = {"command": f"python benchmarks/curved_relax.py {zoo} --levels {args.levels} --method {args.method}"
           f" --edge-length {args.edge_length} --relax {args.relax:g} --floors "
           + " ".join(f"{f:g}" for f in args.floors),
           "commit": git_commit(), "machine": platform.machine(), "solution": "sin(6x) exp(2y) cos(4z)",
           "results": [run_mesh(m, args) for m in args.meshes]}
    write_json(res, Path(args.json))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
