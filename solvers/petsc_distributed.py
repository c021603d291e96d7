"""Distributed fine level for :meth:`solvers.petsc.PetscMultigrid.from_distributed` (issue 33).

Each rank turns the coordinates of *its* fine unknowns into *its* rows of ``P₀`` (barycentric
coordinates in the first coarse tet mesh, :func:`solvers.locate.locate_in_tets`); nothing of size
``n_0`` is ever gathered. What is reduced over ranks is of coarse size: the bounding box (6 numbers), the
certification counts, and, per coarse node, the rank holding most of its interpolation weight (which
then owns the node's row of the coarse levels) — a transpose by one ``VecScatter`` with ``O(n_1)`` entries
per rank.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from .errors import OutsideCoarseMeshError, SolverInputError
from .locate import clean_weights, locate_in_tets
from .petsc_common import _allgather, _as_csr, _coarse_owner, _gather, _Layout, _to_petsc, row_partition
from .transfer import restrict_prolongations


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


def _check_inputs(PETSc, A, points, coarse_mesh, coarse_Ps):
    """Validated (points, V_1, T_1, coarse Ps); collective checks raise on every rank."""
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
    try:
        V1, T1 = coarse_mesh
    except (TypeError, ValueError):
        raise SolverInputError("coarse_mesh must be a pair (V_1, T_1) of the first coarse tet mesh") from None
    V1 = np.asarray(V1, dtype=np.float64)
    T1 = np.asarray(T1)
    if V1.ndim != 2 or V1.shape[1] != 3 or not 0 < len(V1) < N:
        raise SolverInputError(f"coarse_mesh nodes must be (n_1,3) with 0 < n_1 < n_0 = {N}, got {V1.shape}")
    Ps, rows = [], len(V1)
    for k, P in enumerate(coarse_Ps):
        P = _as_csr(P, f"coarse_Ps[{k}]")
        if P.shape[0] != rows or not 0 < P.shape[1] < P.shape[0]:
            raise SolverInputError(
                f"coarse_Ps[{k}] has shape {P.shape}; expected ({rows}, n) with 0 < n < {rows}")
        Ps.append(P)
        rows = P.shape[1]
    d = A.getDiagonal()
    dmin = d.min()[1]
    d.destroy()
    if not dmin > 0:
        raise SolverInputError(
            f"A has a non-positive diagonal entry ({dmin:g}); the smoothers need an SPD operator")
    return pts, V1, T1, Ps


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


def distributed_prolongations(PETSc, A, points, coarse_mesh, coarse_Ps, on_boundary_tol: float):
    """PETSc interpolations ``[P₀ (this rank's rows), P₁, ...]`` for the caller's distributed ``A``.

    Returns
    -------
    interp : list of PETSc AIJ matrices, finest first (``P₀`` rows follow ``A``'s ownership)
    location : dict
        ``n_outside`` (0), ``n_on_boundary`` (summed over ranks), ``coarse_sizes`` (unknowns of every
        coarse level after dropping the nodes no fine unknown reaches), ``seconds`` (this rank's time).
    """
    t0 = time.perf_counter()
    comm = A.getComm()
    size, rank = comm.getSize(), comm.getRank()
    pts, V1, T1, Ps = _check_inputs(PETSc, A, points, coarse_mesh, coarse_Ps)
    nloc, N = A.getLocalSize()[0], A.getSize()[0]
    box = np.concatenate([pts.min(axis=0), -pts.max(axis=0)]) if nloc else np.full(6, np.inf)
    box = _allgather_array(PETSc, comm, box).reshape(size, 6).min(axis=0)
    diag = float(np.linalg.norm(-box[3:] - box[:3]))  # the whole fine level's, as in the serial prolongation
    loc = locate_in_tets(pts, V1, T1, on_boundary_tol=on_boundary_tol, diag=diag)
    location = _certify(PETSc, comm, loc)
    W = clean_weights(loc.weights)
    P0 = sp.csr_matrix((W.ravel(), (np.repeat(np.arange(nloc), 4), loc.cols.ravel())), shape=(nloc, len(V1)))
    P0.eliminate_zeros()
    del loc, W
    # coarse nodes reached by no fine unknown would give zero rows in P^T A P: drop them on every level
    # (solvers.restrict_prolongations' "support" rule, here with the support reduced over ranks)
    owner1 = _heaviest_rank(PETSc, comm, np.asarray(abs(P0).sum(axis=0)).ravel())
    free1 = np.flatnonzero(owner1 >= 0)
    Ps = restrict_prolongations(Ps, free1)[0] if Ps else []
    owners = [owner1[free1]]
    for P in Ps:  # coarser levels: every rank computes the same owners from the same global arrays
        owners.append(_coarse_owner(P, owners[-1], size))
    layouts = [_Layout(o, len(o), size) for o in owners]
    newcol = np.full(len(V1), -1, dtype=np.int64)
    newcol[free1] = layouts[0].to_new(np.arange(len(free1)))
    P0 = sp.csr_matrix((P0.data, newcol[P0.indices], P0.indptr), shape=(nloc, len(free1)))
    P0.sort_indices()
    it = PETSc.IntType
    interp = [PETSc.Mat().createAIJ(size=((nloc, N), (layouts[0].nlocal(rank), len(free1))),
                                    csr=(P0.indptr.astype(it), P0.indices.astype(it), P0.data), comm=comm)]
    interp[0].assemble()
    del P0
    interp += [_to_petsc(PETSc, P, layouts[k], layouts[k + 1], comm) for k, P in enumerate(Ps)]
    location["coarse_sizes"] = [len(o) for o in owners]
    location["seconds"] = time.perf_counter() - t0
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
