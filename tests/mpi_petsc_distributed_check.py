"""MPI driver for tests/test_petsc_distributed.py: ``PetscMultigrid.from_distributed`` on every rank.

Usage (from the repository root, ``PYTHONPATH=.``)::

    mpirun -n 2 python tests/mpi_petsc_distributed_check.py --n 16 --levels 3 --out OUT

Every rank builds the Kuhn cube's interior-node Dirichlet problem (tests/mpi_petsc_check.py), keeps only
its own block of rows of ``A`` (a deliberately uneven split: rank r owns a share proportional to r+1), the
coordinates of those unknowns, the first coarse tet mesh and the coarser prolongations, and solves with
MG-PCG, once with the coarse levels as arrays and once streamed from a ``save_coarse_levels`` file
(each rank reading its crop and its rows only).
Then rank 1 moves one of its points out of the coarse mesh: every rank must raise
``OutsideCoarseMeshError``. Each rank writes ``OUT/rank<r>.json`` (rows, iterations, the error it saw)
and ``OUT/rank<r>.npy``, ``OUT/rank<r>_file.npy`` (its part of the two solutions).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _load_base():
    """tests/mpi_petsc_check.py (its problem builders) as a module."""
    spec = importlib.util.spec_from_file_location("mpi_petsc_check", HERE / "mpi_petsc_check.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def problem(n: int, levels: int) -> dict:
    """The interior-node Kuhn cube Dirichlet problem of tests/mpi_petsc_check.py, with its tet meshes."""
    from solvers.gallery import kuhn_cube_hierarchy

    prob = _load_base().dirichlet_problem(n, levels)
    meshes, Ps = kuhn_cube_hierarchy(n, levels)
    prob["coarse_mesh"], prob["coarse_Ps"] = meshes[1], Ps[1:]
    return prob


def uneven_offsets(n: int, size: int) -> np.ndarray:
    """Row offsets with rank r owning a share proportional to r + 1 (any ownership must work)."""
    w = np.arange(1, size + 1, dtype=float)
    return np.concatenate([[0], np.round(np.cumsum(w) / w.sum() * n).astype(np.int64)])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    import petsc4py

    petsc4py.init([sys.argv[0]])
    from petsc4py import PETSc

    from solvers.errors import OutsideCoarseMeshError
    from solvers.petsc import PetscMultigrid, save_coarse_levels

    comm = PETSc.COMM_WORLD
    rank, size = comm.getRank(), comm.getSize()
    prob = problem(args.n, args.levels)
    off = uneven_offsets(prob["A"].shape[0], size)
    lo, hi = int(off[rank]), int(off[rank + 1])
    local = prob["A"][lo:hi].tocsr()
    local.sort_indices()
    it = PETSc.IntType
    N = prob["A"].shape[0]
    A = PETSc.Mat().createAIJ(size=((hi - lo, N), (hi - lo, N)), comm=comm,
                              csr=(local.indptr.astype(it), local.indices.astype(it), local.data))
    A.assemble()
    points = prob["xyz"][lo:hi]
    rec = {"rank": rank, "rows": [lo, hi]}
    with PetscMultigrid.from_distributed(A, points, prob["coarse_mesh"], prob["coarse_Ps"],
                                         krylov="cg") as mg:
        x, info = mg.solve(prob["b"][lo:hi], tol=1e-8)
        rec.update(iterations=info["iterations"], converged=info["converged"], levels=info["levels"],
                   location=mg.location, rows_per_rank=mg.rows_per_rank)
    np.save(Path(args.out) / f"rank{rank}.npy", x)
    # the same solve with the coarse levels streamed from a file: each rank reads its crop and its rows
    path = Path(args.out) / "coarse.npz"
    if rank == 0:
        save_coarse_levels(path, *prob["coarse_mesh"], prob["coarse_Ps"])
    comm.barrier()
    with PetscMultigrid.from_distributed(A, points, path, krylov="cg") as mg:
        xf, info = mg.solve(prob["b"][lo:hi], tol=1e-8)
        rec.update(file_iterations=info["iterations"], file_location=mg.location)
    np.save(Path(args.out) / f"rank{rank}_file.npy", xf)
    bad = points.copy()
    if rank == min(1, size - 1):
        bad[0] = [2.0, 2.0, 2.0]  # outside the unit cube
    try:
        PetscMultigrid.from_distributed(A, bad, prob["coarse_mesh"], prob["coarse_Ps"]).destroy()
        rec["error"] = None
    except OutsideCoarseMeshError as e:
        rec["error"] = {"n_outside": e.n_outside, "message": str(e)}
    A.destroy()
    (Path(args.out) / f"rank{rank}.json").write_text(json.dumps(rec))
    return 0


if __name__ == "__main__":
    sys.exit(main())
