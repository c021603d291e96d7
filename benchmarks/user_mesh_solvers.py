"""nestmg vs pyamg SA vs PETSc GAMG on a user's own mesh and matrix (issue 31).

The path a user's matrix takes: a tet mesh file from the user's mesher (TetGen or TetWild stand in),
:func:`nestmg.load_tet_mesh` (meshio), :func:`nestmg.hierarchy_from_tets`, a P1 matrix assembled on the
user's nodes (libigl cotangent stiffness + lumped mass), then ``MultigridSolver(A, P)`` with its defaults
and MG-PCG, against pyamg smoothed aggregation + CG and PETSc GAMG + CG (1 rank) on the same matrix and
right-hand side, to ``--tol``. Two stages::

    # once per case: mesh, write the file, read it, build and save the hierarchy (under WORK, not the repo)
    python benchmarks/user_mesh_solvers.py build ZOO_DIR/bunny.off --mesher tetgen --fine-tets 1000000 \\
        --work WORK/bunny-tetgen
    # the solver comparison on saved cases: setup + solve, interleaved repeats, medians
    OMP_NUM_THREADS=1 python benchmarks/user_mesh_solvers.py run WORK/bunny-tetgen WORK/spot-tetwild ... \\
        --repeats 3 --json benchmarks/results/user_mesh/solvers.json

``build`` writes ``user_mesh.vtu`` (the user's file) and ``hierarchy/`` (:func:`nestmg.save_hierarchy`) in
its work directory and is skipped when they exist.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def build(args) -> dict:
    """Mesh the surface (the user's mesher), write + read the file, build and save the hierarchy."""
    import trimesh

    from nestmg import hierarchy_from_tets, load_mesh, load_tet_mesh, save_hierarchy, save_tet_mesh, tetrahedralize

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    mesh_file = work / "user_mesh.vtu"
    info: dict = {"surface": Path(args.surface).name, "mesher": args.mesher, "fine_tets_target": args.fine_tets}
    if not mesh_file.exists():
        V, F = load_mesh(args.surface)
        vol = trimesh.Trimesh(V, F, process=False).volume
        # TetGen's quality meshes come out ~1.8x denser than regular tets of edge h; TetWild's ~1x
        fill = 1.8 if args.mesher == "tetgen" else 1.0
        h = float((6 * np.sqrt(2) * vol * fill / args.fine_tets) ** (1 / 3))
        t = time.perf_counter()
        Vu, Tu = tetrahedralize(V, F, mesher=args.mesher, edge_length=h, time_limit=None)
        info["user_mesher_seconds"] = time.perf_counter() - t
        save_tet_mesh(mesh_file, Vu, Tu)
    t = time.perf_counter()
    V0, T0 = load_tet_mesh(mesh_file)
    info.update(read_seconds=time.perf_counter() - t, nodes=len(V0), tets=len(T0))
    if not (work / "hierarchy" / "hierarchy.npz").exists():
        t = time.perf_counter()
        H = hierarchy_from_tets(V0, T0, levels=args.levels, mesher=args.coarse_mesher, progress=True)
        info["hierarchy_seconds"] = time.perf_counter() - t
        save_hierarchy(work / "hierarchy", H)
        info["hierarchy"] = {"tets": [len(T) for _, T in H.tets], "n_outside": H.n_outside,
                             "certified": H.certified}
    (work / "build.json").write_text(json.dumps(info, indent=1))
    print(json.dumps(info))
    return info


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="make one case: user mesh file + saved hierarchy")
    b.add_argument("surface", type=Path)
    b.add_argument("--mesher", choices=("tetgen", "tetwild"), default="tetgen", help="the user's mesher")
    b.add_argument("--coarse-mesher", choices=("tetgen", "tetwild"), default="tetgen")
    b.add_argument("--fine-tets", type=int, default=1_000_000)
    b.add_argument("--levels", type=int, default=4)
    b.add_argument("--work", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.cmd == "build":
        return build(args)
    return None


if __name__ == "__main__":
    main()
