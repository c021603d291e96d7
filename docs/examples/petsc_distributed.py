"""Distributed solve: your tet mesh partitioned by PETSc, P1 Poisson assembled per rank, cages below.

Run it under MPI (as root add ``--allow-run-as-root``)::

    mpirun -n 4 python docs/examples/petsc_distributed.py [--mesh part.msh] [--refine 1] [--levels 3]

1. Rank 0 reads your tet mesh (any format :func:`nestmg.load_tet_mesh` reads; default a TetWild mesh of a
   procedural torus) and builds the coarse levels once with :func:`nestmg.hierarchy_from_tets`: cages of
   the mesh's boundary, tet-meshed, certified nested, and writes them to one file (``--coarse``,
   :func:`solvers.petsc.save_coarse_levels`) on a file system every rank sees.
2. PETSc's DMPlex takes the mesh from rank 0 and distributes it with its partitioner (PT-Scotch here;
   ``-petscpartitioner_type parmetis`` etc. from the command line), then refines it ``--refine`` times *in
   parallel* (each rank splits its own tets): the fine level exists only in pieces.
3. Each rank assembles its tets' P1 stiffness and lumped load for ``-Δu = f``, ``u = 0`` on the boundary
   (boundary vertices carry no unknown) into one MPI matrix, and passes the coordinates of its owned
   unknowns and the coarse levels' file to :meth:`solvers.petsc.PetscMultigrid.from_distributed`, which
   reads the rank's crop of the first coarse tet mesh (here the input mesh itself) and its rows of the
   coarse prolongations, builds the rank's rows of ``P₀``, and PCMG-CG solves.

``main()`` returns a dict with the iteration count, residual and level sizes; ``--out DIR`` writes each
rank's owned coordinates and solution to ``DIR/rank<r>.npz``, for comparing runs on different rank counts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


CHUNK = 1 << 16  # tets per assembly chunk


def source(X: np.ndarray) -> np.ndarray:
    """The right-hand side f(x, y, z) = 1 + sin(3x) cos(2y) + z at points ``X`` (n,3)."""
    return 1.0 + np.sin(3 * X[:, 0]) * np.cos(2 * X[:, 1]) + X[:, 2]


def coarse_levels(mesh: str | None, levels: int, edge_length: float = 0.08) -> tuple:
    """Rank 0: the user's tet mesh and its coarse levels ``(V, T, [P_1, ...])``; the mesh is level 1.

    Without ``mesh``, a TetWild mesh of a procedural torus with edge length ``edge_length`` (relative to
    its bounding-box diagonal).
    """
    from nestmg import hierarchy_from_tets, load_tet_mesh, shapes, tetrahedralize

    if mesh is None:
        Vs, Fs = shapes.torus(res=16)
        V, T = tetrahedralize(Vs, Fs, edge_length=edge_length)  # stands in for the user's own mesh
    else:
        V, T = load_tet_mesh(mesh)
    H = hierarchy_from_tets(V, T, levels, progress=False)
    if not H.certified:
        raise SystemExit("the coarse levels are not certified nested (n_outside > 0 on some level)")
    return V, T, [P.tocsr() for P in H.P]  # H.P[k] maps level k+1 to level k of the user's mesh's hierarchy


def distribute(PETSc, V: np.ndarray, T: np.ndarray, refine: int):
    """DMPlex of the mesh on rank 0, boundary faces labelled, distributed by the partitioner, refined."""
    comm = PETSc.COMM_WORLD
    dm = PETSc.DMPlex().createFromCellList(3, np.asarray(T, dtype=PETSc.IntType), np.asarray(V, float),
                                           interpolate=True, comm=comm)
    dm.createLabel("boundary")
    dm.markBoundaryFaces("boundary", 1)  # on the whole mesh, before distribution: no partition faces
    part = dm.getPartitioner()
    part.setType("ptscotch" if PETSc.Sys.hasExternalPackage("ptscotch") else "simple")
    part.setFromOptions()
    dm.distribute()
    dm.setRefinementUniform(True)
    for _ in range(refine):  # regular (red) refinement, in parallel; labels follow
        dm = dm.refine()
    return dm


def _cones(dm, start: int, end: int, width: int) -> np.ndarray:
    out = np.empty((end - start, width), dtype=np.int64)  # filled row by row: no list of small arrays
    for i, p in enumerate(range(start, end)):
        out[i] = dm.getCone(p)
    return out


def local_mesh(dm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This rank's vertices (n,3), tets (t,4) in local vertex indices, and its boundary vertex mask."""
    vs, ve = dm.getDepthStratum(0)
    es, ee = dm.getDepthStratum(1)
    fs, fe = dm.getDepthStratum(2)
    cs, ce = dm.getDepthStratum(3)
    edges = _cones(dm, es, ee, 2) - vs  # cell -> faces -> edges -> vertices, vectorised per stratum
    faces = _cones(dm, fs, fe, 3) - es
    e0, e1 = edges[faces[:, 0]], edges[faces[:, 1]]  # two edges of every face
    third = np.where((e1[:, 0] == e0[:, 0]) | (e1[:, 0] == e0[:, 1]), e1[:, 1], e1[:, 0])
    fverts = np.column_stack([e0, third])  # the face's 3 vertices
    del edges, faces, e0, e1, third
    cells = _cones(dm, cs, ce, 4) - fs
    f0, f1 = fverts[cells[:, 0]], fverts[cells[:, 1]]
    shared = (f1[:, :, None] == f0[:, None, :]).any(axis=2)  # which of face 1's vertices are in face 0
    tets = np.column_stack([f0, f1[np.arange(len(cells)), np.argmin(shared, axis=1)]])
    del fverts, cells, f0, f1, shared
    X = dm.getCoordinatesLocal().getArray().reshape(-1, 3)
    label = dm.getLabel("boundary")
    dm.labelComplete(label)  # the closure of the boundary faces: their vertices
    pts = label.getStratumIS(1).getIndices() if label.getStratumSize(1) else np.zeros(0, dtype=np.int64)
    bnd = np.zeros(ve - vs, dtype=bool)
    bnd[pts[(pts >= vs) & (pts < ve)] - vs] = True
    x0 = X[tets[:, 0]]
    vol6 = np.einsum("ij,ij->i", X[tets[:, 1]] - x0, np.cross(X[tets[:, 2]] - x0, X[tets[:, 3]] - x0))
    tets[vol6 < 0, :2] = tets[vol6 < 0, 1::-1]  # positive orientation
    return X, tets, bnd


def dof_numbering(PETSc, dm, bnd: np.ndarray):
    """One unknown per interior vertex: (local dof per vertex or -1, global index per vertex, owned mask)."""
    vs, ve = dm.getDepthStratum(0)
    sec = PETSc.Section().create(comm=dm.getComm())
    sec.setChart(*dm.getChart())
    for i, p in enumerate(range(vs, ve)):
        sec.setDof(p, 0 if bnd[i] else 1)
    sec.setUp()
    dm.setSection(sec)
    gsec = dm.getGlobalSection()
    ldof = np.full(ve - vs, -1, dtype=np.int64)
    gidx = np.full(ve - vs, -1, dtype=np.int64)
    owned = np.zeros(ve - vs, dtype=bool)
    for i, p in enumerate(range(vs, ve)):
        if not bnd[i]:
            ldof[i] = sec.getOffset(p)
            off = gsec.getOffset(p)
            owned[i] = off >= 0
            gidx[i] = off if off >= 0 else -(off + 1)
    return ldof, gidx, owned


def assemble(PETSc, dm, X, tets, ldof, owned, gidx):
    """The MPI stiffness matrix and load vector of the rank's tets; owned coordinates in row order."""
    import scipy.sparse as sp

    from solvers.fem import mass_matrix, stiffness_matrix

    K = sp.csr_matrix((len(X), len(X)))  # local vertices, this rank's tets only, in chunks: the
    for lo in range(0, len(tets), CHUNK):  # COO temporaries of one chunk, not of all tets at once
        K = K + stiffness_matrix(X, tets[lo:lo + CHUNK], check=False)
    m = mass_matrix(X, tets, check=False).diagonal()
    free = np.flatnonzero(ldof >= 0)
    order = free[np.argsort(ldof[free])]  # local dofs in section order
    Kf = sp.csr_matrix(K[order][:, order])
    A = dm.createMatrix()
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    it = PETSc.IntType
    A.setValuesLocalCSR(Kf.indptr.astype(it), Kf.indices.astype(it), Kf.data,
                        addv=PETSc.InsertMode.ADD_VALUES)
    A.assemble()
    bl = dm.createLocalVec()
    bl.setArray(m[order] * source(X[order]))
    b = dm.createGlobalVec()
    b.set(0.0)
    dm.localToGlobal(bl, b, addv=PETSc.InsertMode.ADD_VALUES)
    bl.destroy()
    mine = np.flatnonzero(owned)
    mine = mine[np.argsort(gidx[mine])]  # owned unknowns in global (row) order
    lo, hi = A.getOwnershipRange()
    if not np.array_equal(gidx[mine], np.arange(lo, hi)):
        raise RuntimeError("owned vertices do not match the matrix's row ownership")
    return A, b, X[mine]


def main(argv=None) -> dict:
    """Partition, refine, assemble and solve; returns iterations, residual and sizes (on every rank)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", help="the user's tet mesh (.msh, .mesh, .vtu...); default a procedural torus")
    ap.add_argument("--levels", type=int, default=3, help="levels of the mesh's own hierarchy (mesh + cages)")
    ap.add_argument("--refine", type=int, default=1, help="parallel uniform refinements of the mesh")
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--out", help="directory for rank<r>.npz (owned coordinates and solution)")
    ap.add_argument("--coarse", default="coarse_levels.npz",
                    help="file for the coarse levels, on a file system every rank sees")
    args, petsc_args = ap.parse_known_args(argv)
    if args.refine < 1:
        ap.error("--refine must be >= 1: the input mesh is the first coarse level")
    import petsc4py

    petsc4py.init([sys.argv[0], *petsc_args])
    from petsc4py import PETSc

    from solvers.petsc import PetscMultigrid, save_coarse_levels

    comm = PETSc.COMM_WORLD
    rank = comm.getRank()
    # the DMPlex starts from rank 0's copy of the (coarse) input mesh; other ranks start empty
    V0, T0 = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    if rank == 0:
        V0, T0, coarse_Ps = coarse_levels(args.mesh, args.levels)
        save_coarse_levels(args.coarse, V0, T0, coarse_Ps)  # every rank reads only its pieces of it
        del coarse_Ps
    comm.barrier()
    dm = distribute(PETSc, V0, T0, args.refine)
    del V0, T0
    X, tets, bnd = local_mesh(dm)
    ldof, gidx, owned = dof_numbering(PETSc, dm, bnd)
    A, b, points = assemble(PETSc, dm, X, tets, ldof, owned, gidx)
    with PetscMultigrid.from_distributed(A, points, args.coarse) as mg:
        x, info = mg.solve(b.getArray(), tol=args.tol)
        text = repr(mg)
        location = dict(mg.location)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        np.savez(Path(args.out) / f"rank{rank}.npz", points=points, x=x)
    n_tets = int(round(_sum_over_ranks(PETSc, len(tets))))
    result = {"ranks": comm.getSize(), "fine_tets": n_tets, "iterations": info["iterations"],
              "final_residual": info["final_residual"], "levels": info["levels"], "location": location}
    if rank == 0:
        print(text)
        print(f"{n_tets} fine tets on {comm.getSize()} ranks: {info['iterations']} CG iterations, "
              f"relative residual {info['final_residual']:.2e}, n_outside {location['n_outside']}")
    for obj in (A, b, dm):
        obj.destroy()
    return result


def _sum_over_ranks(PETSc, value: float) -> float:
    vec = PETSc.Vec().createMPI((1, PETSc.DECIDE), comm=PETSc.COMM_WORLD)
    vec.set(float(value))
    total = vec.sum()
    vec.destroy()
    return total


if __name__ == "__main__":
    main()
