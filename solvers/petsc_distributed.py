"""Distributed levels for :meth:`solvers.petsc.PetscMultigrid.from_distributed` (issue 33).

Each rank turns the coordinates of *its* fine unknowns into *its* rows of ``P₀`` (barycentric
coordinates in its crop of the first coarse tet mesh, :func:`solvers.locate.locate_in_tets`), and reads
only *its* rows of the coarse prolongations ``P_1, P_2, ...`` (:class:`solvers.coarse_levels.CoarseLevels`:
from arrays, or streamed from a file): no rank holds the fine level, the first coarse mesh or a coarse
matrix in full. What is reduced over ranks: the bounding box (6 numbers), the certification counts, and
per coarse node the rank holding most of its interpolation weight (which then owns the node's row on
its level) — a transpose by one ``VecScatter`` with ``O(n_k)`` entries per rank, leaving an ``(n_k,)``
owner array on every rank during setup (8 bytes per coarse node).
"""

from __future__ import annotations

import os
import time

import numpy as np
import scipy.sparse as sp

from .coarse_levels import CoarseLevels
from .errors import OutsideCoarseMeshError, SolverInputError
from .locate import Location, clean_weights, locate_in_tets
from .petsc_common import _allgather, _gather, _Layout, row_partition


def _allgather_array(PETSc, comm, values) -> np.ndarray:
    """Every rank's float array, concatenated in rank order, on every rank (without mpi4py)."""
    vals = np.ascontiguousarray(values, dtype=np.float64).ravel()
    vec = PETSc.Vec().createMPI((vals.size, PETSc.DECIDE), comm=comm)
    vec.setArray(vals)
    out = _gather(PETSc, vec)
    vec.destroy()
    return out


def _heaviest_rank(PETSc, comm, weight: np.ndarray) -> np.ndarray:
    """Per coarse node, the rank with the largest ``weight`` (ties: lowest rank), -1 if all are zero.

    ``weight`` (n_1,) is this rank's column sums of ``|P₀|``. Rank ``r``'s vector is scattered so that rank
    ``s`` receives all ranks' weights of its block of coarse nodes (``row_partition``), takes the argmax
    there, and the (n_1,) owners are then gathered on every rank: O(n_1) memory per rank.
    """
    size, rank, n1 = comm.getSize(), comm.getRank(), len(weight)
    offs = row_partition(n1, size)
    nblock = int(offs[rank + 1] - offs[rank])
    src = PETSc.Vec().createMPI((n1, n1 * size), comm=comm)
    dst = PETSc.Vec().createMPI((nblock * size, n1 * size), comm=comm)
    src.setArray(np.asarray(weight, dtype=np.float64))
    # entry j of rank r goes to position j * size + r: node-major, so each rank owns whole nodes
    is_from = PETSc.IS().createStride(n1, first=rank * n1, step=1, comm=comm)
    is_to = PETSc.IS().createStride(n1, first=rank, step=size, comm=comm)
    sc = PETSc.Scatter().create(src, is_from, dst, is_to)
    sc.scatter(src, dst, addv=PETSc.InsertMode.INSERT_VALUES, mode=PETSc.ScatterMode.FORWARD)
    block = dst.getArray(readonly=True).reshape(nblock, size)
    best = np.where(block.max(axis=1) > 0, np.argmax(block, axis=1), -1)
    for obj in (sc, is_from, is_to, src, dst):
        obj.destroy()
    return _allgather_array(PETSc, comm, best).astype(np.int64)


def _coarse_source(coarse_mesh, coarse_Ps) -> CoarseLevels:
    """A :class:`CoarseLevels` from a ``(V_1, T_1)`` pair (+ ``coarse_Ps``), a file path, or one as is."""
    if isinstance(coarse_mesh, (CoarseLevels, str, os.PathLike)):
        if len(coarse_Ps):
            raise SolverInputError("coarse_Ps must be empty when coarse_mesh is a file or a CoarseLevels: "
                                   "the prolongations are read from it")
        if isinstance(coarse_mesh, CoarseLevels):
            return coarse_mesh
        return CoarseLevels.from_file(coarse_mesh)
    try:
        V1, T1 = coarse_mesh
    except (TypeError, ValueError):
        raise SolverInputError("coarse_mesh must be a pair (V_1, T_1) of the first coarse tet mesh, a "
                               "CoarseLevels or the path of a save_coarse_levels file") from None
    return CoarseLevels.from_arrays(V1, T1, coarse_Ps)


def _check_inputs(PETSc, A, points, coarse_mesh, coarse_Ps):
    """Validated (points, coarse levels); collective checks raise on every rank."""
    N, M = A.getSize()
    nloc = A.getLocalSize()[0]
    if N != M:
        raise SolverInputError(f"A must be square, got {N} x {M}")
    pts = np.asarray(points, dtype=np.float64)
    if pts.size == 0:
        pts = pts.reshape(0, 3)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise SolverInputError(f"points must be an (n_local,3) array, got shape {pts.shape}")
    counts = _allgather(PETSc, A.getComm(), float(len(pts) != nloc or not np.isfinite(pts).all()))
    if counts.any():
        bad = int(np.flatnonzero(counts)[0])
        raise SolverInputError(f"rank {bad}: points must hold one finite (x,y,z) per owned row of A "
                               f"(this rank: {len(pts)} points, {nloc} rows)")
    src = _coarse_source(coarse_mesh, coarse_Ps)
    if not src.n_nodes < N:
        raise SolverInputError(f"the first coarse mesh has {src.n_nodes} nodes, not fewer than n_0 = {N}")
    d = A.getDiagonal()
    dmin = d.min()[1]
    d.destroy()
    if not dmin > 0:
        raise SolverInputError(
            f"A has a non-positive diagonal entry ({dmin:g}); the smoothers need an SPD operator")
    return pts, src


def _certify(PETSc, comm, loc) -> dict:
    """``n_outside`` / ``n_on_boundary`` summed over ranks; raise on every rank if any node is outside."""
    n_out = _allgather(PETSc, comm, len(loc.outside))
    dmax = _allgather(PETSc, comm, float(np.sqrt(loc.distance2.max())) if len(loc.outside) else 0.0)
    n_on = _allgather(PETSc, comm, loc.n_on_boundary)
    if n_out.sum() > 0:
        per_rank = ", ".join(f"rank {r}: {int(c)}" for r, c in enumerate(n_out) if c)
        raise OutsideCoarseMeshError(
            f"{int(n_out.sum())} fine nodes lie outside the first coarse tet mesh ({per_rank}; up to "
            f"{dmax.max():.3g} away): the hierarchy is not nested there, so P0 would extrapolate",
            int(n_out.sum()), float(dmax.max()))
    return {"n_outside": 0, "n_on_boundary": int(n_on.sum())}


def _locate_local(pts, src: CoarseLevels, diag: float, tol: float) -> tuple[Location, np.ndarray, tuple]:
    """This rank's points located in its crop of the first coarse mesh; (location, global cols, crop size).

    The crop keeps the tets whose bounding box meets the points' box enlarged by ``1e-6 diag`` (more than
    the on-boundary tolerance): every containing tet, and every coarse boundary face that can decide the
    on-boundary test (:mod:`solvers.coarse_levels`). If no tet is kept, every point is outside and its
    distance is reported as the margin (a lower bound).
    """
    n = len(pts)
    empty = Location(np.zeros((n, 4), dtype=np.int64), np.zeros((n, 4)), np.zeros(0, dtype=np.int64), 0,
                     np.zeros(0), np.zeros((0, 3)))
    if n == 0:
        return empty, empty.cols, (0, 0)
    margin = max(1e-6, 10 * tol) * diag
    V, T, gid = src.crop((pts.min(axis=0) - margin, pts.max(axis=0) + margin))
    if len(T) == 0:  # no coarse tet near any of this rank's points: all outside, by more than the margin
        empty.outside = np.arange(n)
        empty.distance2 = np.full(n, margin**2)
        return empty, empty.cols, (0, 0)
    loc = locate_in_tets(pts, V, T, on_boundary_tol=tol, diag=diag)
    return loc, gid[loc.cols], (len(T), len(V))


def _local_csr(PETSc, M, newcol: np.ndarray, rows: tuple[int, int], cols: tuple[int, int], comm):
    """This rank's rows ``M`` (global old column ids) as an MPI AIJ matrix with columns renumbered."""
    M = sp.csr_matrix((M.data, newcol[M.indices], M.indptr), shape=(M.shape[0], cols[1]))
    M.sort_indices()
    it = PETSc.IntType
    mat = PETSc.Mat().createAIJ(size=(rows, cols), comm=comm,
                                csr=(M.indptr.astype(it), M.indices.astype(it), M.data))
    mat.assemble()
    return mat


def _numbering(owner: np.ndarray, size: int, level: int) -> tuple[_Layout, np.ndarray]:
    """Layout of one coarse level (nodes no one reaches dropped) and the new index of every old node."""
    free = np.flatnonzero(owner >= 0)
    if free.size == 0:
        raise SolverInputError(f"level {level}: no coarse node touches a node of level {level - 1}")
    lay = _Layout(owner[free], len(free), size)
    newid = np.full(len(owner), -1, dtype=np.int64)
    newid[free] = lay.to_new(np.arange(len(free)))
    return lay, newid


def distributed_prolongations(PETSc, A, points, coarse_mesh, coarse_Ps, on_boundary_tol: float):
    """PETSc interpolations ``[P₀, P₁, ...]``, each rank holding only its own rows of every one.

    Rank r locates its points in its crop of the first coarse mesh, owns the level-1 nodes where it holds
    most interpolation weight (:func:`_heaviest_rank`), reads the rows of ``P_1`` of those nodes only
    (:meth:`CoarseLevels.rows`), and so on down the levels. Coarse nodes no finer node reaches are dropped
    on every level (the "support" rule of :func:`solvers.restrict_prolongations`, reduced over ranks).

    Returns
    -------
    interp : list of PETSc AIJ matrices, finest first (``P₀`` rows follow ``A``'s ownership)
    location : dict
        ``n_outside`` (0), ``n_on_boundary`` (summed over ranks), ``coarse_sizes`` (unknowns of every
        coarse level after dropping the nodes no fine unknown reaches), ``crop_tets`` / ``crop_nodes``
        (this rank's kept coarse tets and their nodes), ``coarse_rows`` (this rank's rows of each coarse
        prolongation), ``seconds``.
    """
    t0 = time.perf_counter()
    comm = A.getComm()
    size, rank = comm.getSize(), comm.getRank()
    pts, src = _check_inputs(PETSc, A, points, coarse_mesh, coarse_Ps)
    nloc, N = A.getLocalSize()[0], A.getSize()[0]
    box = np.concatenate([pts.min(axis=0), -pts.max(axis=0)]) if nloc else np.full(6, np.inf)
    box = _allgather_array(PETSc, comm, box).reshape(size, 6).min(axis=0)
    diag = float(np.linalg.norm(-box[3:] - box[:3]))  # the whole fine level's, as in the serial prolongation
    loc, cols, crop = _locate_local(pts, src, diag, on_boundary_tol)
    location = _certify(PETSc, comm, loc)
    W = clean_weights(loc.weights) if nloc else loc.weights
    P0 = sp.csr_matrix((W.ravel(), (np.repeat(np.arange(nloc), 4), cols.ravel())), shape=(nloc, src.n_nodes))
    P0.eliminate_zeros()
    del loc, W, cols
    owners, pieces = [_heaviest_rank(PETSc, comm, np.asarray(abs(P0).sum(axis=0)).ravel())], []
    for k in range(1, len(src.shapes) + 1):  # level k's owned rows of P_k, then level k+1's owners
        Pk = src.rows(k, np.flatnonzero(owners[-1] == rank))
        Pk.eliminate_zeros()
        pieces.append(Pk)
        owners.append(_heaviest_rank(PETSc, comm, np.asarray(abs(Pk).sum(axis=0)).ravel()))
    numbered = [_numbering(o, size, k + 1) for k, o in enumerate(owners)]
    del owners
    sizes = [(nloc, N)] + [(lay.nlocal(rank), lay.n) for lay, _ in numbered]
    interp = [_local_csr(PETSc, P, numbered[k][1], sizes[k], sizes[k + 1], comm)
              for k, P in enumerate([P0] + pieces)]
    location.update(coarse_sizes=[lay.n for lay, _ in numbered], crop_tets=crop[0], crop_nodes=crop[1],
                    coarse_rows=[P.shape[0] for P in pieces], seconds=time.perf_counter() - t0)
    return interp, location


def _bcast_floats(PETSc, comm, values, n: int, root: int) -> np.ndarray:
    """``values`` (n floats, given on ``root``) on every rank."""
    vec = PETSc.Vec().createMPI((n if comm.getRank() == root else 0, n), comm=comm)
    if comm.getRank() == root:
        vec.setArray(np.asarray(values, dtype=np.float64))
    out = _gather(PETSc, vec)
    vec.destroy()
    return out


def broadcast_arrays(comm, arrays: dict | None, root: int = 0) -> dict:
    """Numpy arrays given on rank ``root``, on every rank of ``comm`` (collective; without mpi4py).

    For the small coarse levels of :meth:`solvers.petsc.PetscMultigrid.from_distributed` (built once on
    one rank). Values travel as float64: integers must stay below 2**53 in magnitude.

    Parameters
    ----------
    comm : petsc4py ``PETSc.Comm``
    arrays : dict of str -> array_like on ``root`` (real or integer or bool); ignored on other ranks
    root : int

    Returns
    -------
    dict of str -> numpy array, the same names, dtypes and shapes on every rank.
    """
    import json

    from .petsc_common import _petsc

    PETSc = _petsc()
    header = payload = None
    if comm.getRank() == root:
        items = {k: np.asarray(v) for k, v in arrays.items()}
        for k, v in items.items():
            if v.dtype.kind not in "biuf":
                raise SolverInputError(f"broadcast_arrays: {k!r} has dtype {v.dtype}; real, int or bool only")
        spec = json.dumps([[k, v.dtype.str, list(v.shape)] for k, v in items.items()]).encode()
        header = np.frombuffer(spec, dtype=np.uint8).astype(np.float64)
        payload = np.concatenate([v.astype(np.float64).ravel() for v in items.values()] or [np.zeros(0)])
    sizes = _bcast_floats(PETSc, comm, None if header is None else [len(header), len(payload)], 2, root)
    header = _bcast_floats(PETSc, comm, header, int(sizes[0]), root)
    payload = _bcast_floats(PETSc, comm, payload, int(sizes[1]), root)
    out, pos = {}, 0
    for name, dtype, shape in json.loads(header.astype(np.uint8).tobytes().decode()):
        size = int(np.prod(shape))
        out[name] = payload[pos:pos + size].astype(np.dtype(dtype)).reshape(shape)
        pos += size
    return out
