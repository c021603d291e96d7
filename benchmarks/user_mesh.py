"""Bring-your-own-mesh pipeline (issue 16): a user tet mesh file -> hierarchy -> scikit-fem matrix -> MG-PCG.

    nice -n 10 python benchmarks/user_mesh.py ZOO_DIR/gargo.off --fine-tets 150000 \
        --json benchmarks/results/user_mesh/gargo.json

Stands in for the user's own mesher: TetGen (opt-in here, AGPL; the ``tetgen`` extra) meshes the surface to
about ``--fine-tets`` tets, written with meshio to a gmsh 2.2 file (a temporary file, removed once read;
``--tmp FILE`` writes and keeps it there; never committed). Then, timed stage by stage:
:func:`nestmg.load_tet_mesh`, :func:`nestmg.hierarchy_from_tets` (default: nested cages, TetWild coarse layers),
scikit-fem P1 assembly (``laplace``, ``mass``), multigrid setup (Galerkin) and MG-PCG to ``--tol`` for Dirichlet
and Neumann Poisson. Prints one JSON document (and writes it to ``--json``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("surface", type=Path)
    ap.add_argument("--fine-tets", type=int, default=150_000)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--tmp", type=Path, default=None,
                    help="write the user mesh file here and keep it (default: a temporary file, removed)")
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    import meshio
    import trimesh
    from skfem import Basis, ElementTetP1, MeshTet, asm
    from skfem.models.poisson import laplace, mass

    from nestmg import hierarchy_from_tets, load_mesh, load_tet_mesh, tetrahedralize
    from nestmg.io import json_default
    from solvers import MultigridSolver, restrict_prolongations

    sec: dict = {}
    out: dict = {"surface": args.surface.name, "fine_tets_target": args.fine_tets, "levels": args.levels}
    # --- the user's mesh (made here with TetGen, then written to a file as any mesher would)
    V, F = load_mesh(args.surface)
    vol = trimesh.Trimesh(V, F, process=False).volume
    h = float((6 * np.sqrt(2) * vol / args.fine_tets) ** (1 / 3))  # regular tets of edge h fill it
    t = time.perf_counter()
    Vu, Tu = tetrahedralize(V, F, mesher="tetgen", edge_length_abs=h)
    sec["make_user_mesh_tetgen"] = time.perf_counter() - t
    tmp_dir = None
    if args.tmp is None:
        tmp_dir = tempfile.TemporaryDirectory(prefix="nestmg_user_mesh_")
        args.tmp = Path(tmp_dir.name) / "user_mesh.msh"
    meshio.write(str(args.tmp), meshio.Mesh(Vu, [("tetra", Tu)]), file_format="gmsh22", binary=True)

    # --- the pipeline, from the file
    t = time.perf_counter()
    V0, T0 = load_tet_mesh(args.tmp)
    sec["read_file"] = time.perf_counter() - t
    if tmp_dir is not None:
        tmp_dir.cleanup()
    out.update(user_nodes=len(V0), user_tets=len(T0), same_as_written=bool(np.array_equal(T0, Tu)))
    t = time.perf_counter()
    H = hierarchy_from_tets(V0, T0, args.levels, cache=not args.no_cache, progress=False)
    sec["hierarchy"] = time.perf_counter() - t
    sec["hierarchy_stages"] = {k: v for k, v in H.timings.items() if isinstance(v, float)}
    out["hierarchy"] = {"tets": [len(T) for _, T in H.tets], "nodes": [len(Vk) for Vk, _ in H.tets],
                        "surface_faces": [len(Fk) for _, Fk in H.surfaces], "n_outside": H.n_outside,
                        "certified": H.certified, "fallbacks": H.fallbacks,
                        "fine_is_user_mesh": bool(np.array_equal(H.tets[0][0], V0) and np.array_equal(H.tets[0][1], T0))}

    t = time.perf_counter()
    mesh = MeshTet(V0.T, T0.T)
    basis = Basis(mesh, ElementTetP1())
    K = asm(laplace, basis).tocsr()
    M = asm(mass, basis).tocsr()
    sec["skfem_assembly"] = time.perf_counter() - t
    f = 1.0 + np.sin(3 * V0[:, 0] / H.frame["scale"]) + V0[:, 2] / H.frame["scale"]
    b = M @ f
    out["solves"] = {}
    interior = basis.complement_dofs(mesh.boundary_nodes())
    for name in ("dirichlet", "neumann"):
        t = time.perf_counter()
        if name == "dirichlet":
            Pf, _ = restrict_prolongations(H.P, interior)
            ml = MultigridSolver(K[interior][:, interior], Pf)
            rhs = b[interior]
        else:
            ml = MultigridSolver(K, H.P, nullspace="constant")
            rhs = b - M @ np.full(len(V0), b.sum() / M.sum())
        t_setup = time.perf_counter() - t
        _, r = ml.solve(rhs, tol=args.tol, accel="cg", return_info=True)  # MG-PCG
        out["solves"][name] = {"unknowns": len(rhs), "setup_seconds": t_setup, "solve_seconds": r["seconds"],
                               "iterations": r["iterations"], "final_residual": float(r["residuals"][-1]),
                               "operator_complexity": ml.operator_complexity()}
    out["seconds"] = sec
    text = json.dumps(out, indent=1, default=json_default)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text)
    return out


if __name__ == "__main__":
    main()
