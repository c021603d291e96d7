"""Mesh quality and multigrid: TetWild (the default) beside TetGen with its quality switches.

For each mesher configuration the normalised input is tet-meshed at the edge that gives about
``--tets`` tets (:func:`exp_common.edge_for_tets`); the mesh is then red-refined (``nestmg.refine``),
and the refined mesh over the mesher's mesh is a same-domain two-grid pair with an exact ``P``. Its
two-grid factors (Dirichlet and Neumann Poisson; the plain V(1,1) and the pipeline's default cycle,
exact coarse solve) isolate what the mesher's elements cost the smoother. Reported per
configuration: mesher seconds, tets, min / 1st-percentile dihedral angle, slivers (< 5 degrees) of
the mesher's mesh and of the refined one, and the factors.

TetGen is AGPL: it is imported here only because the benchmark names it (``pip install tetgen``).

    python benchmarks/archive/mesher_quality.py MESH [MESH ...] --tets 60000 \\
        --json benchmarks/results/scale/mesher_quality.json --png benchmarks/results/scale/mesher_quality.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import edge_for_tets, environment, save_figure, write_json  # noqa: E402

# (mesher, options): TetGen's radius-edge bound ``minratio`` (-q) and dihedral bound ``mindihedral``
CONFIGS = {
    "tetwild": ("tetwild", {}),
    "tetgen_q2.0": ("tetgen", {"minratio": 2.0, "mindihedral": 0.0}),
    "tetgen_q1.5": ("tetgen", {"minratio": 1.5, "mindihedral": 0.0}),
    "tetgen_q1.5_d10": ("tetgen", {"minratio": 1.5, "mindihedral": 10.0}),
    "tetgen_q1.5_d18": ("tetgen", {"minratio": 1.5, "mindihedral": 18.0}),
}


def mesh_one(V, F, mesher: str, opts: dict, h: float):
    """Tet mesh of the normalised surface; TetGen called directly so its switches are the ones named."""
    from nestmg.tetmesh import orient_tets, tetrahedralize

    if mesher == "tetwild":
        return tetrahedralize(V, F, mesher="tetwild", edge_length_abs=h)
    import tetgen  # AGPL, opt-in: this benchmark is the explicit request

    Vt, T, _, _ = tetgen.TetGen(V, F.astype(np.int32)).tetrahedralize(
        quality=True, minratio=opts["minratio"], mindihedral=opts["mindihedral"], fixedvolume=True,
        maxvolume=h**3 / (6 * np.sqrt(2)), steinerleft=-1, nomergefacet=True, nomergevertex=True)
    Vt = np.asarray(Vt, dtype=np.float64)
    return Vt, orient_tets(Vt, np.asarray(T, dtype=np.int64))


def two_grid(Vc, Tc) -> dict:
    """Two-grid factors of refine(mesh) over mesh: plain V(1,1) and the default cycle."""
    from nestmg.problems import setup_problem
    from nestmg.refine import refine_tets
    from solvers import convergence_factor

    Vf, Tf, P = refine_tets(Vc, Tc)
    out = {"fine_tets": len(Tf)}
    for name in ("poisson-dirichlet", "poisson-neumann"):
        prob = setup_problem([(Vf, Tf), (Vc, Tc)], [P], name)
        for label, kw in (("plain", {"local": False}), ("default", {})):
            ml = prob.multigrid(presmoother="symmetric_gauss_seidel", **kw)
            res: list = []
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # a stalled factor is a result here
                ml.solve(prob.b, tol=1e-10, maxiter=25, residuals=res)
            out[f"{name}_{label}"] = round(convergence_factor(res), 4)
    return out


def run(mesh: str, tets: int, configs: list[str]) -> list[dict]:
    from nestmg.io import load_mesh, normalize
    from nestmg.tetmesh import TetMeshError, tet_quality

    V, F = load_mesh(mesh)
    V, _, _ = normalize(V)
    h = edge_for_tets(V, F, tets)
    rows = []
    for c in configs:
        mesher, opts = CONFIGS[c]
        t0 = time.perf_counter()
        try:
            Vt, T = mesh_one(V, F, mesher, opts, h)
        except (RuntimeError, ValueError, TetMeshError) as exc:  # a mesher failure is a result
            rows.append({"mesh": Path(mesh).name, "config": c, "error": str(exc)[:300]})
            continue
        sec = time.perf_counter() - t0
        q = tet_quality(Vt, T)
        row = {"mesh": Path(mesh).name, "config": c, "mesher": mesher, **opts, "edge_length": h,
               "seconds": round(sec, 2), "tets": len(T),
               "min_dihedral_deg": round(q["min_dihedral_deg"], 2),
               "p01_min_dihedral_deg": round(q["p01_min_dihedral_deg"], 2), "n_slivers": q["n_slivers"]}
        row.update(two_grid(Vt, T))
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error" not in r]
    fig, ax = plt.subplots(figsize=(9, 4))
    labels = [f"{Path(r['mesh']).stem}\n{r['config']}" for r in ok]
    x = np.arange(len(ok))
    for i, (k, lab) in enumerate((("poisson-neumann_plain", "Neumann, plain V(1,1)"),
                                  ("poisson-neumann_default", "Neumann, default cycle"),
                                  ("poisson-dirichlet_plain", "Dirichlet, plain V(1,1)"))):
        ax.bar(x + 0.27 * (i - 1), [r[k] for r in ok], 0.27, label=lab)
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("two-grid factor (refined mesh over the mesher's mesh)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--tets", type=int, default=60000, help="target tets of the mesher's mesh (refined: 8x)")
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument("--json", default=None)
    ap.add_argument("--png", default=None)
    a = ap.parse_args(argv)
    rows = [r for m in a.meshes for r in run(m, a.tets, a.configs)]
    out = {"command": " ".join(["python", "benchmarks/archive/mesher_quality.py", *sys.argv[1:]]),
           "environment": environment(), "runs": rows}
    print(json.dumps(out, indent=1, default=float))
    if a.json:
        write_json(out, Path(a.json))
    if a.png:
        plot(rows, Path(a.png))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
