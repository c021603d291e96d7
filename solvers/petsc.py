"""Optional PETSc backend: nestmg's hierarchy solved by PETSc's PCMG inside KSP, in parallel under MPI.

Install with ``scripts/install-petsc.sh`` (Debian's PETSc 3.18 + petsc4py built against it; extra
``petsc``). Every rank calls the same functions with the same *global* scipy matrices (built
deterministically on every rank, or read from a ``.npz`` written by :func:`save_hierarchy`); each rank
copies only its own rows into PETSc::

    mpirun -n 4 python my_solve.py            # inside: PetscMultigrid(A, Ps).solve(b)

Level numbering follows :class:`solvers.MultigridSolver` (level 0 finest, ``Ps[k]`` of shape
``(n_k, n_{k+1})`` maps level ``k+1`` to level ``k``). PETSc numbers the other way (its level 0 is the
coarsest); the translation happens here. ``Ps[k]`` is handed to ``PCMGSetInterpolation`` and PETSc
restricts with its transpose, ``R_k = P_kᵀ``, as the in-process solver does. Coarse operators are
either PETSc's Galerkin products ``A_{k+1} = P_kᵀ A_k P_k`` (``-pc_mg_galerkin both``, computed in
parallel by ``MatPtAP``) or the caller's (e.g. re-discretised on the nested coarse tet meshes).

Smoothers: ``"sor"`` is PETSc's PCSOR with symmetric sweeps and ω = 1 inside one Richardson step, i.e.
one symmetric Gauss–Seidel sweep, the in-process default. On one rank the cycle is the same operator
as :class:`solvers.MultigridSolver`'s V(1,1); on several ranks PETSc's SOR is *processor-local*
(block Jacobi between ranks, Gauss–Seidel inside), so factors drift slightly with the rank count.

PETSc options: every object gets the options prefix ``options_prefix`` (default ``"nestmg_"``), so a
user can inspect or override anything from the command line or ``PETSC_OPTIONS``, e.g.
``-nestmg_ksp_view -nestmg_ksp_monitor -nestmg_mg_levels_pc_sor_omega 1.2``. Options that the
user set win over the constructor's choices. To read command-line options, initialise petsc4py with
``import petsc4py, sys; petsc4py.init(sys.argv)`` *before* importing this module's users.
"""

from __future__ import annotations

import contextlib
import re
import time
import warnings
from typing import Any

import numpy as np
import scipy.sparse as sp

from .errors import IncompatibleRHSError, SolverError, SolverInputError
from .multilevel import ConvergenceWarning, convergence_factor

__all__ = [
    "PetscMultigrid",
    "PetscUnavailableError",
    "load_hierarchy",
    "petsc_amg_solve",
    "petsc_available",
    "row_partition",
    "save_hierarchy",
]

SMOOTHER_NAMES = ("sor", "jacobi", "chebyshev")
AMG_KINDS = ("gamg", "hypre")


class PetscUnavailableError(SolverError, ImportError):
    """petsc4py (or a PETSc feature such as hypre) is not installed; see ``scripts/install-petsc.sh``."""


def _petsc():
    """Import petsc4py lazily (it initialises MPI) and return the ``PETSc`` module."""
    try:
        from petsc4py import PETSc
    except ImportError as e:  # pragma: no cover - exercised only without petsc4py
        raise PetscUnavailableError(
            f"the PETSc backend needs petsc4py ({e}); run scripts/install-petsc.sh "
            "(Debian petsc-dev + petsc4py 3.18.5 built against it)"
        ) from None
    return PETSc


def petsc_available() -> bool:
    """True when ``from petsc4py import PETSc`` works."""
    try:
        _petsc()
    except PetscUnavailableError:
        return False
    return True


# --------------------------------------------------------------------------------------------- input
def _as_csr(M, name: str, shape: tuple[int, int] | None = None) -> sp.csr_matrix:
    if not sp.issparse(M):
        raise SolverInputError(f"{name} must be a scipy sparse matrix, got {type(M).__name__}")
    if np.iscomplexobj(M.data):
        raise SolverInputError(f"{name} must be real")
    M = sp.csr_matrix(M, dtype=np.float64, copy=True)
    M.sum_duplicates()
    M.sort_indices()
    if shape is not None and M.shape != shape:
        raise SolverInputError(f"{name} has shape {M.shape}, expected {shape}")
    if not np.all(np.isfinite(M.data)):
        raise SolverInputError(f"{name} contains {np.count_nonzero(~np.isfinite(M.data))} NaN/inf entries")
    return M


def _check_hierarchy(A, Ps, coarse_ops) -> tuple[sp.csr_matrix, list[sp.csr_matrix], list[sp.csr_matrix] | None]:
    A = _as_csr(A, "A")
    if A.shape[0] != A.shape[1] or A.shape[0] == 0:
        raise SolverInputError(f"A must be square and non-empty, got {A.shape}")
    if isinstance(Ps, sp.spmatrix) or not hasattr(Ps, "__len__"):
        raise SolverInputError("Ps must be a list of sparse prolongation matrices")
    sizes = [A.shape[0]]
    out = []
    for k, P in enumerate(Ps):
        P = _as_csr(P, f"Ps[{k}]")
        if P.shape[0] != sizes[-1]:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}; expected {sizes[-1]} rows (level {k} size)")
        if not 0 < P.shape[1] < P.shape[0]:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}: a coarse level must have 1..n_{k}-1 nodes")
        empty = np.flatnonzero(np.diff(sp.csc_matrix(P).indptr) == 0)
        if empty.size:
            raise SolverInputError(
                f"Ps[{k}] has {empty.size} all-zero columns (first {empty[0]}): those coarse nodes would get a "
                "zero row in P^T A P; drop them (solvers.restrict_prolongations does)"
            )
        sizes.append(P.shape[1])
        out.append(P)
    ops = None
    if coarse_ops is not None:
        if len(coarse_ops) != len(out):
            raise SolverInputError(f"coarse_ops needs {len(out)} matrices (levels 1..), got {len(coarse_ops)}")
        ops = [_as_csr(Ac, f"coarse_ops[{k}]", (sizes[k + 1], sizes[k + 1])) for k, Ac in enumerate(coarse_ops)]
    return A, out, ops


def _check_diagonal(M: sp.csr_matrix, name: str) -> None:
    """SOR/Jacobi/Chebyshev smoothing divides by the diagonal: refuse it here, not deep inside PETSc.

    (An error raised inside PETSc's KSPSolve leaves Debian's PETSc 3.18 in a state that crashes at exit.)
    """
    d = M.diagonal()
    bad = np.flatnonzero(~(d > 0))
    if bad.size:
        raise SolverInputError(
            f"{name} has {bad.size} non-positive diagonal entries (first at row {bad[0]}: {d[bad[0]]:g}); "
            "the smoothers need a positive diagonal (an SPD operator)"
        )


def _check_vector(b, n: int, name: str = "b") -> np.ndarray:
    b = np.asarray(b)
    if b.ndim == 2 and b.shape[1] == 1:
        b = b[:, 0]
    if b.shape != (n,):
        raise SolverInputError(f"{name} must have shape ({n},), got {b.shape}")
    if not np.issubdtype(b.dtype, np.number) or np.iscomplexobj(b):
        raise SolverInputError(f"{name} must be real, got dtype {b.dtype}")
    b = np.array(b, dtype=np.float64)  # a copy: never touch the caller's array
    if not np.all(np.isfinite(b)):
        raise SolverInputError(f"{name} contains {np.count_nonzero(~np.isfinite(b))} NaN/inf entries")
    return b


def _check_nullspace(nullspace) -> str | None:
    if nullspace not in (None, "constant"):
        raise SolverInputError(f"nullspace must be None or 'constant', got {nullspace!r}")
    return nullspace


def _prepare_rhs(b, n: int, nullspace: str | None, project: bool) -> np.ndarray:
    b = _check_vector(b, n)
    if nullspace == "constant":
        scale = float(np.abs(b).sum())
        if project:
            b -= b.mean()
        elif abs(b.sum()) > 1e-10 * max(scale, 1e-300):
            raise IncompatibleRHSError(
                f"sum(b) = {b.sum():.3e} is not zero (relative {abs(b.sum()) / scale:.2e}): the singular system "
                "has no solution; pass project=True to remove the mean of b"
            )
    return b


# ------------------------------------------------------------------------------------- partitioning
def row_partition(n: int, size: int) -> np.ndarray:
    """PETSc's natural contiguous row split (``PETSC_DECIDE``): the first ``n % size`` ranks get one more.

    Parameters
    ----------
    n : int
        Global number of rows.
    size : int
        Number of ranks.

    Returns
    -------
    offsets : (size + 1,) int64
        Rank ``r`` owns rows ``offsets[r]:offsets[r+1]``.
    """
    n, size = int(n), int(size)
    counts = np.full(size, n // size, dtype=np.int64)
    counts[: n % size] += 1
    return np.concatenate([[0], np.cumsum(counts)])


class _Layout:
    """Row distribution of one level: a permutation (new -> old global index) and per-rank offsets."""

    def __init__(self, owner: np.ndarray | None, n: int, size: int):
        self.n = n
        if owner is None:  # natural partition: identity permutation
            self.perm = None
            self.inv = None
            self.offsets = row_partition(n, size)
        else:
            owner = np.asarray(owner, dtype=np.int64)
            self.perm = np.argsort(owner, kind="stable")
            self.inv = np.empty(n, dtype=np.int64)
            self.inv[self.perm] = np.arange(n)
            self.offsets = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=size))])

    def local_rows(self, rank: int) -> np.ndarray:
        lo, hi = self.offsets[rank], self.offsets[rank + 1]
        return np.arange(lo, hi) if self.perm is None else self.perm[lo:hi]

    def nlocal(self, rank: int) -> int:
        return int(self.offsets[rank + 1] - self.offsets[rank])

    def to_new(self, cols: np.ndarray) -> np.ndarray:
        return cols if self.inv is None else self.inv[cols]

    def to_old(self, x_new: np.ndarray) -> np.ndarray:
        if self.perm is None:
            return x_new
        x = np.empty_like(x_new)
        x[self.perm] = x_new
        return x


def _coarse_owner(P: sp.csr_matrix, fine_owner: np.ndarray, size: int) -> np.ndarray:
    """Give each coarse node to the rank holding most of its interpolation weight ``sum_i |P_ij|``."""
    onehot = sp.csr_matrix(
        (np.ones(fine_owner.size), (np.arange(fine_owner.size), fine_owner)), shape=(fine_owner.size, size)
    )
    weight = np.asarray((abs(P).T @ onehot).todense())
    return np.argmax(weight, axis=1).astype(np.int64)


def _fine_owner(PETSc, A_global, A_nat, partition, n: int, size: int, comm) -> np.ndarray | None:
    """Owner rank of every fine row: None (natural), RCM slabs, a given array, or PETSc MatPartitioning.

    PETSc's MatPartitioning runs in parallel on the naturally distributed operator ``A_nat``; note that
    PT-Scotch is not deterministic (Debian's build): repeated runs cut in different places, so factors
    vary by ~0.01 between runs. "rcm" is deterministic.
    """
    if partition is None or (isinstance(partition, str) and partition == "natural"):
        return None
    if isinstance(partition, str) and partition == "rcm":
        # deterministic level-set slabs: contiguous blocks of the reverse Cuthill-McKee order
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        order = reverse_cuthill_mckee(sp.csr_matrix(A_global), symmetric_mode=True)
        owner = np.empty(n, dtype=np.int64)
        offsets = row_partition(n, size)
        for r in range(size):
            owner[order[offsets[r] : offsets[r + 1]]] = r
        return owner
    if isinstance(partition, str):
        if size == 1:
            return None
        part = PETSc.MatPartitioning().create(comm=comm)
        try:
            part.setType(partition)
        except PETSc.Error as e:
            raise SolverInputError(f"PETSc has no partitioner {partition!r} ({e}); try 'ptscotch' or 'natural'") from None
        part.setAdjacency(A_nat)
        is_ = PETSc.IS()
        part.apply(is_)
        owner = is_.allGather().getIndices().astype(np.int64)
        is_.destroy()
        part.destroy()
        if np.bincount(owner, minlength=size).min() == 0:
            raise SolverError(f"partitioner {partition!r} left a rank without rows")
        return owner
    owner = np.asarray(partition)
    if owner.shape != (n,) or not np.issubdtype(owner.dtype, np.integer):
        raise SolverInputError(f"partition must be 'natural', a PETSc partitioner name or ({n},) int ranks")
    if owner.min() < 0 or owner.max() >= size:
        raise SolverInputError(f"partition ranks must lie in [0, {size})")
    return owner.astype(np.int64)


def _to_petsc(PETSc, M: sp.csr_matrix, rows: _Layout, cols: _Layout, comm):
    """Copy this rank's rows of the global ``M`` into a PETSc AIJ matrix (columns in the new numbering)."""
    rank = comm.getRank()
    local = M[rows.local_rows(rank)] if rows.perm is not None else M[rows.offsets[rank] : rows.offsets[rank + 1]]
    local = sp.csr_matrix(local)
    if cols.inv is not None:
        local = sp.csr_matrix((local.data, cols.to_new(local.indices), local.indptr), shape=local.shape)
    local.sort_indices()
    it = PETSc.IntType
    mat = PETSc.Mat().createAIJ(
        size=((rows.nlocal(rank), rows.n), (cols.nlocal(rank), cols.n)),
        csr=(local.indptr.astype(it), local.indices.astype(it), local.data),
        comm=comm,
    )
    mat.assemble()
    return mat


def _gather(PETSc, vec) -> np.ndarray:
    """All entries of a distributed vector on every rank."""
    scatter, full = PETSc.Scatter.toAll(vec)
    scatter.scatter(vec, full, addv=PETSc.InsertMode.INSERT_VALUES, mode=PETSc.ScatterMode.FORWARD)
    out = full.getArray().copy()
    scatter.destroy()
    full.destroy()
    return out


def _allgather(PETSc, comm, value: float) -> np.ndarray:
    """One float from every rank, on every rank (without mpi4py)."""
    size = comm.getSize()
    vec = PETSc.Vec().createMPI((1, size), comm=comm)
    vec.setValue(comm.getRank(), float(value))
    vec.assemble()
    out = _gather(PETSc, vec)
    vec.destroy()
    return out


def _ghost_count(M: sp.csr_matrix, lay: _Layout, rank: int) -> int:
    """Distinct off-rank columns coupled to this rank's rows (the halo a SpMV must receive)."""
    rows = lay.local_rows(rank)
    cols = lay.to_new(np.unique(M[rows].indices))
    return int(np.count_nonzero((cols < lay.offsets[rank]) | (cols >= lay.offsets[rank + 1])))


@contextlib.contextmanager
def _options(PETSc, prefix: str, values: dict[str, Any]):
    """Put ``values`` into PETSc's options database under ``prefix`` unless the user set them already.

    The options this function inserted are removed on exit, so nothing leaks into later solvers.
    """
    db = PETSc.Options()
    added = []
    for key, val in values.items():
        name = f"{prefix}{key}"
        if db.hasName(name):
            continue
        db.setValue(name, "" if val is None else str(val))
        added.append(name)
    try:
        yield
    finally:
        for name in added:
            db.delValue(name)


def _barrier_time(comm) -> float:
    comm.barrier()
    return time.perf_counter()


def _history(ksp, normb: float) -> list[float]:
    h = np.asarray(ksp.getConvergenceHistory(), dtype=np.float64)
    return [float(v) / normb for v in h]


def _coarse_choice(coarse, galerkin, coarse_ops):
    """``coarse=`` ("galerkin" or a list), with the deprecated ``galerkin=`` / ``coarse_ops=`` spelling."""
    if galerkin is not None or coarse_ops is not None:
        warnings.warn("PetscMultigrid(galerkin=..., coarse_ops=...) is deprecated; use coarse='galerkin' or "
                      "coarse=[A_1, ..., A_L]", DeprecationWarning, stacklevel=3)
        if not (isinstance(coarse, str) and coarse == "galerkin"):
            raise SolverInputError("give the coarse operators once: coarse=[...] (galerkin=/coarse_ops= are deprecated)")
        if galerkin is None:
            galerkin = coarse_ops is None
        if galerkin and coarse_ops is not None:
            raise SolverInputError("coarse_ops given with galerkin=True: pass coarse=[A_1, ...] to use them")
        return bool(galerkin), coarse_ops
    if isinstance(coarse, str):
        if coarse != "galerkin":
            raise SolverInputError(
                f"coarse must be 'galerkin' or a list of coarse operators, got {coarse!r} (named coarse "
                "operators such as 'weighted' are built by nestmg.problems.setup_problem)")
        return True, None
    return False, list(coarse)


# ------------------------------------------------------------------------------------ PCMG solver
class PetscMultigrid:
    """nestmg's multigrid hierarchy run by PETSc: KSP (CG or Richardson) preconditioned by PCMG.

    Every rank passes the same global matrices; each rank copies its own rows into PETSc.

    Parameters
    ----------
    A : (n_0, n_0) sparse matrix
        Fine operator (symmetric positive (semi-)definite for CG).
    Ps : list of sparse matrices
        ``Ps[k]`` of shape ``(n_k, n_{k+1})``, interpolation from level ``k+1`` to level ``k`` (finest
        first, as :class:`solvers.MultigridSolver`). May be empty (one level: a parallel direct solve).
    comm : petsc4py ``PETSc.Comm``, optional
        Default ``PETSc.COMM_WORLD`` (all ranks of ``mpirun``).
    coarse : "galerkin" or list of sparse
        ``"galerkin"`` (default): PETSc computes ``A_{k+1} = P_kᵀ A_k P_k`` (``-pc_mg_galerkin both``).
        A list ``[A_1, ..., A_L]``: coarse operators built by nestmg (re-discretised or weighted,
        ``nestmg.problems.setup_problem(coarse=...)``), as ``MultigridSolver(coarse=...)``.
    galerkin, coarse_ops
        Deprecated spelling (``galerkin=False, coarse_ops=[...]``) of ``coarse=[...]``.
    cycle : {"V", "W"}
    smoother : {"sor", "jacobi", "chebyshev"}
        ``"sor"``: Richardson + PCSOR, symmetric sweeps, ω = ``omega`` (default 1: symmetric
        Gauss–Seidel; processor-local in parallel). ``"jacobi"``: Richardson + PCJACOBI with scale ω
        (default 2/3). ``"chebyshev"``: KSPCHEBYSHEV + PCJACOBI targeting ``[λ/30, 1.1 λ]`` of the
        estimated largest eigenvalue λ of ``D⁻¹A`` (as the in-process Chebyshev smoother); ``presmooth``
        / ``postsmooth`` are then the polynomial degrees.
    presmooth, postsmooth : int
        Smoothing steps before / after the coarse-grid correction (ν₁, ν₂ of V(ν₁, ν₂)); >= 0.
    omega : float, optional
        Relaxation weight of ``"sor"`` / ``"jacobi"``.
    nullspace : None or "constant"
        ``"constant"`` for pure Neumann operators: attaches PETSc's constant null space to the fine
        operator, solves the singular coarsest system by SVD (pseudo-inverse), and returns solutions with
        zero plain nodal mean (the in-process convention).
    krylov : {"cg", "richardson"}
        ``"cg"``: CG preconditioned by one cycle. ``"richardson"``: plain stationary cycling (each
        iteration is one cycle), the setting in which a convergence factor per cycle is defined.
    partition : "auto", "natural", "rcm", "ptscotch", "parmetis", or (n_0,) int array
        Distribution of the fine rows. "natural": contiguous blocks of rows in the given order (PETSc's
        default). "rcm": contiguous blocks of the reverse Cuthill–McKee order (scipy; deterministic
        level-set slabs, good for few ranks). "ptscotch" / "parmetis": PETSc's MatPartitioning of the
        fine operator's graph (best cuts, but PT-Scotch is not deterministic run to run). Every coarse
        node then goes to the rank holding most of its interpolation weight; the problem is renumbered
        internally, and ``solve`` takes and returns vectors in the caller's numbering. "auto"
        (default): natural on one rank, else PT-Scotch (ParMETIS) when PETSc has it, else RCM. Tet
        meshers number nodes without spatial coherence: on a 313k-unknown tetgen mesh the natural split
        on 2 ranks took CG from 9 to 15 iterations (PT-Scotch: 9).
    options_prefix : str
        PETSc options prefix of the KSP (see the module docstring).
    options : dict, optional
        Extra PETSc options (without the prefix), e.g. ``{"mg_levels_pc_sor_its": 2}``.

    Attributes
    ----------
    setup_seconds : float
        Wall time (max over ranks) to copy the matrices into PETSc and set up PCMG (incl. Galerkin
        products and the coarse factorisation).
    levels : list of dict
        ``{"n": global unknowns, "nnz": global non-zeros}`` of each level's operator, finest first.
    comm_size : int
    rows_per_rank, ghosts_per_rank : list of int
        Fine rows owned by each rank, and the distinct off-rank unknowns each rank's rows couple to (the
        halo received in every fine SpMV / SOR sweep): a measure of the partition's quality.

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> from solvers.fem import stiffness_matrix, boundary_nodes
    >>> from solvers.multilevel import restrict_prolongations
    >>> meshes, Ps = kuhn_cube_hierarchy(8, 3)
    >>> V, T = meshes[0]
    >>> free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    >>> Pf, _ = restrict_prolongations(Ps, free)
    >>> mg = PetscMultigrid(stiffness_matrix(V, T)[free][:, free], Pf)    # doctest: +SKIP
    >>> x, info = mg.solve(np.ones(len(free)), tol=1e-8)                     # doctest: +SKIP
    >>> info["iterations"] <= 10                                             # doctest: +SKIP
    True
    """

    def __init__(
        self,
        A,
        Ps,
        *,
        comm=None,
        coarse="galerkin",
        galerkin: bool | None = None,
        coarse_ops=None,
        cycle: str = "V",
        smoother: str = "sor",
        presmooth: int = 1,
        postsmooth: int = 1,
        omega: float | None = None,
        nullspace: str | None = None,
        krylov: str = "cg",
        partition="auto",
        options_prefix: str = "nestmg_",
        options: dict | None = None,
    ):
        PETSc = _petsc()
        self._PETSc = PETSc
        if cycle not in ("V", "W"):
            raise SolverInputError(f"cycle must be 'V' or 'W' (PCMG), got {cycle!r}")
        if smoother not in SMOOTHER_NAMES:
            raise SolverInputError(f"smoother must be one of {SMOOTHER_NAMES}, got {smoother!r}")
        if krylov not in ("cg", "richardson"):
            raise SolverInputError(f"krylov must be 'cg' or 'richardson', got {krylov!r}")
        for name, v in (("presmooth", presmooth), ("postsmooth", postsmooth)):
            if int(v) != v or v < 0:
                raise SolverInputError(f"{name} must be a non-negative integer, got {v!r}")
        if omega is not None and not (np.isfinite(omega) and 0 < omega < 2):
            raise SolverInputError(f"omega must lie in (0, 2), got {omega!r}")
        if not isinstance(options_prefix, str) or not options_prefix or options_prefix.startswith("-"):
            raise SolverInputError(f"options_prefix must be a non-empty string without '-', got {options_prefix!r}")
        galerkin, coarse_ops = _coarse_choice(coarse, galerkin, coarse_ops)
        self.nullspace = _check_nullspace(nullspace)
        A, Ps, coarse_ops = _check_hierarchy(A, Ps, coarse_ops)
        if not galerkin and Ps and coarse_ops is None:
            raise SolverInputError("galerkin=False needs coarse_ops=[A_1, ..., A_L]")
        _check_diagonal(A, "A")
        for k, Ac in enumerate(coarse_ops or []):
            _check_diagonal(Ac, f"coarse_ops[{k}]")
        self.comm = PETSc.COMM_WORLD if comm is None else comm
        self.comm_size = self.comm.getSize()
        self.cycle, self.smoother, self.krylov = cycle, smoother, krylov
        self.presmooth, self.postsmooth = int(presmooth), int(postsmooth)
        self.galerkin = bool(galerkin)
        self.prefix = options_prefix
        self.n = A.shape[0]
        if omega is None:
            omega = {"sor": 1.0, "jacobi": 2.0 / 3.0}.get(smoother)
        self.omega = omega

        t0 = _barrier_time(self.comm)
        size = self.comm_size
        nat = _Layout(None, self.n, size)
        owner = None
        if isinstance(partition, str) and partition not in ("auto", "natural", "rcm"):
            if partition not in ("ptscotch", "parmetis"):
                raise SolverInputError(f"partition must be 'auto', 'natural', 'rcm', 'ptscotch', 'parmetis' or an "
                                       f"array of ranks, got {partition!r}")
            if not PETSc.Sys.hasExternalPackage(partition):
                raise SolverInputError(f"this PETSc was built without {partition}; use 'auto' or 'natural'")
        if isinstance(partition, str) and partition == "auto":
            partition = "natural"
            if size > 1:
                partition = "rcm"
                for name in ("ptscotch", "parmetis"):
                    if PETSc.Sys.hasExternalPackage(name):
                        partition = name
                        break
        if not (isinstance(partition, str) and partition in ("natural", "rcm")) and partition is not None:
            A_nat = _to_petsc(PETSc, A, nat, nat, self.comm) if isinstance(partition, str) else None
            owner = _fine_owner(PETSc, A, A_nat, partition, self.n, size, self.comm)
            if A_nat is not None:
                A_nat.destroy()
        elif partition == "rcm" and size > 1:
            owner = _fine_owner(PETSc, A, None, partition, self.n, size, self.comm)
        self.partition = "natural" if owner is None else (partition if isinstance(partition, str) else "given")
        layouts = [_Layout(owner, self.n, size)]
        for P in Ps:
            if owner is not None:
                owner = _coarse_owner(P, owner, size)
            layouts.append(_Layout(owner, P.shape[1], size))
        self._layouts = layouts
        ghosts = _allgather(PETSc, self.comm, _ghost_count(A, layouts[0], self.comm.getRank()))
        self.rows_per_rank = np.diff(layouts[0].offsets).tolist()
        self.ghosts_per_rank = ghosts.astype(np.int64).tolist()

        mats = [_to_petsc(PETSc, A, layouts[0], layouts[0], self.comm)]
        interp = [_to_petsc(PETSc, P, layouts[k], layouts[k + 1], self.comm) for k, P in enumerate(Ps)]
        given = [] if coarse_ops is None else [
            _to_petsc(PETSc, Ac, layouts[k + 1], layouts[k + 1], self.comm) for k, Ac in enumerate(coarse_ops)
        ]
        self._ns = None
        if self.nullspace == "constant":
            self._ns = PETSc.NullSpace().create(constant=True, comm=self.comm)
            for M in mats + given:
                M.setNullSpace(self._ns)
        self._A = mats[0]
        self._mats = mats + given + interp

        nlev = len(Ps) + 1
        ksp = PETSc.KSP().create(comm=self.comm)
        ksp.setOptionsPrefix(options_prefix)
        ksp.setOperators(self._A)
        ksp.setType("cg" if krylov == "cg" else "richardson")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        if krylov == "richardson":
            # Without a monitor KSPRICHARDSON hands the whole iteration to PCApplyRichardson_MG, which
            # neither records a residual history nor computes the true residual each cycle.
            ksp.setMonitor(_noop_monitor)
        pc = ksp.getPC()
        pc.setType("mg")
        pc.setMGLevels(nlev)
        pc.setMGType(PETSc.PC.MGType.MULTIPLICATIVE)
        pc.setMGCycleType(PETSc.PC.MGCycleType.V if cycle == "V" else PETSc.PC.MGCycleType.W)
        for k, P in enumerate(interp):
            pc.setMGInterpolation(nlev - 1 - k, P)  # PETSc level nlev-1-k is nestmg level k
        if not self.galerkin:
            for k, Ac in enumerate(given):
                lev = nlev - 2 - k
                if lev == 0:
                    pc.getMGCoarseSolve().setOperators(Ac)
                else:
                    pc.getMGSmootherDown(lev).setOperators(Ac)
                    pc.getMGSmootherUp(lev).setOperators(Ac)

        top = {"pc_mg_galerkin": "both" if self.galerkin else "none"}
        top.update(options or {})
        with _options(PETSc, options_prefix, top):
            ksp.setFromOptions()
            # the user may have asked for another cycle through -<prefix>pc_mg_cycle_type
            user_cycle = PETSc.Options().getString(f"{options_prefix}pc_mg_cycle_type", cycle)
            self.cycle = "W" if str(user_cycle).lower().startswith("w") else "V"
            for lev in range(1, nlev):
                down = pc.getMGSmootherDown(lev)
                self._setup_smoother(down, self.presmooth)
                self._setup_smoother(pc.getMGSmootherUp(lev), self.postsmooth)
                if self.cycle == "W" and lev < nlev - 1:
                    # PCMG's pre-smoothers assume a zero initial guess (true in a V-cycle); on the second
                    # visit of a W-cycle they must start from the current iterate, or W == V.
                    down.setInitialGuessNonzero(True)
            self._setup_coarse(pc.getMGCoarseSolve())
            try:
                ksp.setUp()
            except PETSc.Error as e:
                raise SolverError(f"PETSc PCMG setup failed: {_petsc_message(e)}") from None
        self.ksp = ksp
        self.levels = []
        for lev in range(nlev - 1, -1, -1):
            M = self._A if lev == nlev - 1 else (
                pc.getMGCoarseSolve() if lev == 0 else pc.getMGSmootherDown(lev)).getOperators()[0]
            info = M.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)
            self.levels.append({"n": int(M.getSize()[0]), "nnz": int(info["nz_used"])})
        self.setup_seconds = _barrier_time(self.comm) - t0

    # ------------------------------------------------------------------ setup helpers
    def _setup_smoother(self, sksp, steps: int) -> None:
        PETSc = self._PETSc
        spc = sksp.getPC()
        opts: dict[str, Any] = {}
        if self.smoother == "chebyshev":
            sksp.setType("chebyshev")
            spc.setType("jacobi")
            # eigenvalue window [λ/30, 1.1 λ] as solvers.smoothing.setup_chebyshev (λ estimated by PETSc)
            opts["ksp_chebyshev_esteig"] = f"0,{1.0 / 30.0},0,1.1"
            opts["ksp_chebyshev_esteig_steps"] = 20
        else:
            sksp.setType("richardson")
            if self.smoother == "sor":
                spc.setType("sor")
                opts["pc_sor_local_symmetric"] = None  # = symmetric GS on one rank; MPIAIJ has only local sweeps
                opts["pc_sor_omega"] = self.omega
            else:
                spc.setType("jacobi")
                opts["ksp_richardson_scale"] = self.omega
        sksp.setTolerances(rtol=0.0, atol=0.0, max_it=max(int(steps), 0))
        sksp.setNormType(PETSc.KSP.NormType.NONE)
        with _options(PETSc, sksp.getOptionsPrefix() or "", opts):
            sksp.setFromOptions()

    def _setup_coarse(self, cksp) -> None:
        """Exact coarsest solve, redundant on every rank in parallel.

        Cholesky by CHOLMOD when PETSc has SuiteSparse (the coarse operators are SPD; 3.5x faster than
        PETSc's own LU on a 6.8k-unknown Galerkin operator with 73 non-zeros per row), else PETSc's LU;
        an SVD pseudo-inverse for a singular Neumann operator.
        """
        PETSc = self._PETSc
        if self.nullspace == "constant":
            inner = {"pc_type": "svd"}
        elif PETSc.Sys.hasExternalPackage("suitesparse"):
            inner = {"pc_type": "cholesky", "pc_factor_mat_solver_type": "cholmod"}
        else:
            inner = {"pc_type": "lu"}
        cksp.setType("preonly")
        cpc = cksp.getPC()
        if self.comm_size == 1:
            cpc.setType(inner["pc_type"])
            opts = {k: v for k, v in inner.items() if k != "pc_type"}
        else:  # every rank factorises the whole (small) coarsest operator
            cpc.setType("redundant")
            opts = {f"redundant_{k}": v for k, v in inner.items()}
        with _options(PETSc, cksp.getOptionsPrefix() or "", opts):
            cksp.setFromOptions()
        self.coarse_solver = "+".join(str(v) for v in inner.values())

    # ------------------------------------------------------------------ description
    def __repr__(self) -> str:
        lines = [
            f"PetscMultigrid (PETSc PCMG, {self.comm_size} rank{'s' if self.comm_size > 1 else ''})",
            f"Krylov / cycle:     {self.krylov} / {self.cycle}({self.presmooth},{self.postsmooth})",
            f"Smoother:           {self.smoother} (omega={self.omega})",
            f"Coarse operators:   {'Galerkin (PETSc MatPtAP)' if self.galerkin else 'given'}",
            (f"Partition:          {self.partition} (fine rows per rank {self.rows_per_rank}, "
             f"off-rank couplings {self.ghosts_per_rank})"),
            f"Null space:         {self.nullspace}",
            f"Coarsest solve:     {self.coarse_solver}{' (redundant)' if self.comm_size > 1 else ''}",
            "  level   unknowns     nonzeros   nnz/row",
        ]
        for k, L in enumerate(self.levels):
            lines.append(f"{k:7d} {L['n']:10d} {L['nnz']:12d} {L['nnz'] / max(L['n'], 1):9.1f}")
        return "\n".join(lines)

    def view(self) -> None:
        """Print PETSc's own description of the solver (``KSPView``)."""
        self.ksp.view()

    def local_rows(self) -> np.ndarray:
        """Global (caller's numbering) fine rows owned by this rank."""
        return self._layouts[0].local_rows(self.comm.getRank())

    # ------------------------------------------------------------------ solve
    def solve(self, b, tol: float = 1e-8, maxiter: int = 100, *, x0=None, project: bool = False,
              divtol: float = 1e5) -> tuple[np.ndarray, dict]:
        """Solve ``A x = b``; collective (every rank calls it with the same global ``b``).

        Parameters
        ----------
        b : (n_0,) array_like
            Global right-hand side (identical on every rank).
        tol : float
            Stop when ``||b - A x||_2 <= tol ||b||_2`` (unpreconditioned norm, as in-process).
        maxiter : int
            Maximum number of CG iterations (or cycles with ``krylov="richardson"``).
        x0 : (n_0,) array_like, optional
            Initial guess (default zero).
        project : bool
            With ``nullspace="constant"``: remove the mean of an incompatible ``b`` instead of raising.
        divtol : float
            PETSc's divergence tolerance (residual growth factor).

        Returns
        -------
        x : (n_0,) float64
            Global solution on every rank (zero plain mean with ``nullspace="constant"``).
        info : dict
            ``iterations``, ``converged``, ``reason`` (PETSc's KSPConvergedReason name), ``residuals``
            (relative residual norms, initial first), ``factor`` (:func:`solvers.convergence_factor`
            of the history), ``final_residual`` (true ``||b - A x|| / ||b||``), ``setup_seconds``,
            ``solve_seconds`` (max over ranks), ``ranks``, ``levels``.

        Raises
        ------
        IncompatibleRHSError
            Neumann problem with ``sum(b) != 0`` and ``project=False``.
        SolverError
            PETSc reported a breakdown or divergence (the reason is named).
        """
        PETSc = self._PETSc
        maxiter = int(maxiter)
        if maxiter < 0:
            raise SolverInputError(f"maxiter must be >= 0, got {maxiter}")
        if not tol > 0:
            raise SolverInputError(f"tol must be > 0, got {tol}")
        b = _prepare_rhs(b, self.n, self.nullspace, project)
        lay = self._layouts[0]
        rank = self.comm.getRank()
        rows = lay.local_rows(rank)
        xv, bv = self._A.createVecs()
        bv.setArray(b[rows])
        if x0 is not None:
            xv.setArray(_check_vector(x0, self.n, "x0")[rows])
            self.ksp.setInitialGuessNonzero(True)
        else:
            xv.set(0.0)
            self.ksp.setInitialGuessNonzero(False)
        normb = float(np.linalg.norm(b))
        ksp = self.ksp
        ksp.setTolerances(rtol=tol, atol=1e-300, divtol=divtol, max_it=maxiter)
        ksp.setConvergenceHistory(length=maxiter + 1, reset=True)
        t0 = _barrier_time(self.comm)
        if normb == 0.0:
            xv.set(0.0)
            hist, reason, its = [0.0], "CONVERGED_ATOL", 0
        else:
            try:
                ksp.solve(bv, xv)
            except PETSc.Error as e:
                raise SolverError(f"PETSc KSPSolve failed: {_petsc_message(e)}") from None
            hist = _history(ksp, normb)
            its = ksp.getIterationNumber()
            code = ksp.getConvergedReason()
            reason = _reason_name(PETSc, code)
        solve_seconds = _barrier_time(self.comm) - t0
        x = lay.to_old(_gather(PETSc, xv))
        if self.nullspace == "constant":
            x -= x.mean()
        rv = bv.duplicate()
        self._A.mult(xv, rv)
        rv.aypx(-1.0, bv)
        final = float(rv.norm()) / normb if normb > 0 else 0.0
        for v in (xv, bv, rv):
            v.destroy()
        _check_reason(reason, its, hist, f"PETSc KSP {self.krylov}+PCMG", tol)
        return x, {
            "iterations": int(its),
            "converged": reason.startswith("CONVERGED"),
            "reason": reason,
            "residuals": hist,
            "factor": convergence_factor(hist),
            "final_residual": final,
            "setup_seconds": self.setup_seconds,
            "solve_seconds": solve_seconds,
            "ranks": self.comm_size,
            "levels": [dict(L) for L in self.levels],
            "partition": self.partition,
            "rows_per_rank": list(self.rows_per_rank),
            "ghosts_per_rank": list(self.ghosts_per_rank),
        }

    def destroy(self) -> None:
        """Free the PETSc objects (also done by the garbage collector)."""
        for obj in [self.ksp, *self._mats] + ([self._ns] if self._ns is not None else []):
            obj.destroy()
        self._mats = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()


def _check_reason(reason: str, its: int, hist: list[float], what: str, tol: float) -> None:
    """Raise on breakdown/divergence; warn (as the in-process solver does) when maxiter was reached."""
    if reason == "DIVERGED_ITS":
        warnings.warn(f"{what} stopped after {its} iterations at relative residual {hist[-1]:.3e} > tol={tol:g}",
                      ConvergenceWarning, stacklevel=3)
    elif reason.startswith("DIVERGED"):
        raise SolverError(f"{what} failed: {reason} after {its} iterations (relative residual {hist[-1]:.3e})")


def _petsc_message(err) -> str:
    """The last lines of PETSc's error traceback (the message proper) on one line."""
    lines = [ln.split("] ", 1)[-1] for ln in str(err).splitlines() if ln.strip()]
    return " / ".join(lines[-2:]) if lines else repr(err)


def _noop_monitor(ksp, its, rnorm) -> None:
    """Empty KSP monitor (see PetscMultigrid: keeps KSPRICHARDSON on its generic, history-logging path)."""


def _reason_name(PETSc, code: int) -> str:
    """KSPConvergedReason as PETSc prints it with -ksp_converged_reason (e.g. "DIVERGED_ITS")."""
    if code == PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT:
        return "DIVERGED_ITS"
    for name, val in vars(PETSc.KSP.ConvergedReason).items():
        if not name.startswith("_") and val == code and name != "ITERATING":
            return name
    return f"REASON_{code}"


# ----------------------------------------------------------------------------------- PETSc AMG
def petsc_amg_solve(
    A,
    b,
    kind: str = "gamg",
    *,
    tol: float = 1e-8,
    maxiter: int = 200,
    comm=None,
    nullspace: str | None = None,
    project: bool = False,
    options_prefix: str | None = None,
    options: dict | None = None,
) -> tuple[np.ndarray, dict]:
    """Solve ``A x = b`` by CG preconditioned with PETSc's algebraic multigrid, for comparison.

    Parameters
    ----------
    A : (n, n) sparse matrix
        Global SPD (or, with ``nullspace="constant"``, semi-definite) matrix, identical on every rank.
    b : (n,) array_like
        Global right-hand side.
    kind : {"gamg", "hypre"}
        ``"gamg"``: PETSc's smoothed-aggregation PCGAMG (defaults of PETSc 3.18: Chebyshev/Jacobi
        smoothing). ``"hypre"``: hypre's BoomerAMG through PCHYPRE (classical AMG).
    tol, maxiter : float, int
        Relative unpreconditioned residual tolerance and iteration cap of CG.
    comm : petsc4py ``PETSc.Comm``, optional
    nullspace : None or "constant"
    project : bool
        With ``nullspace="constant"``: project an incompatible ``b`` instead of raising.
    options_prefix : str, optional
        Default ``"nestmg_gamg_"`` / ``"nestmg_hypre_"``.
    options : dict, optional
        Extra PETSc options without the prefix (e.g. ``{"pc_gamg_threshold": 0.02}``).

    Returns
    -------
    x : (n,) float64, on every rank
    info : dict
        As :meth:`PetscMultigrid.solve`, plus ``kind``; ``setup_seconds`` covers matrix copy and AMG setup.

    Raises
    ------
    PetscUnavailableError
        No petsc4py, or ``kind="hypre"`` and this PETSc has no hypre.
    """
    PETSc = _petsc()
    if kind not in AMG_KINDS:
        raise SolverInputError(f"kind must be one of {AMG_KINDS}, got {kind!r}")
    nullspace = _check_nullspace(nullspace)
    A, _, _ = _check_hierarchy(A, [], None)
    n = A.shape[0]
    b = _prepare_rhs(b, n, nullspace, project)
    maxiter = int(maxiter)
    if maxiter < 0 or not tol > 0:
        raise SolverInputError(f"need tol > 0 and maxiter >= 0, got {tol}, {maxiter}")
    comm = PETSc.COMM_WORLD if comm is None else comm
    prefix = options_prefix or f"nestmg_{kind}_"
    t0 = _barrier_time(comm)
    lay = _Layout(None, n, comm.getSize())
    Ap = _to_petsc(PETSc, A, lay, lay, comm)
    ns = None
    if nullspace == "constant":
        ns = PETSc.NullSpace().create(constant=True, comm=comm)
        Ap.setNullSpace(ns)
        Ap.setNearNullSpace(ns)
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(Ap)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    pc = ksp.getPC()
    try:
        if kind == "gamg":
            pc.setType("gamg")
            pc.setGAMGType(PETSc.PC.GAMGType.AGG)
        else:
            pc.setType("hypre")
            pc.setHYPREType("boomeramg")
    except PETSc.Error as e:
        ksp.destroy()
        Ap.destroy()
        raise PetscUnavailableError(f"this PETSc cannot provide {kind!r} ({e})") from None
    ksp.setTolerances(rtol=tol, atol=1e-300, max_it=maxiter)
    with _options(PETSc, prefix, dict(options or {})):
        ksp.setFromOptions()
        try:
            ksp.setUp()
        except PETSc.Error as e:
            raise SolverError(f"PETSc {kind} setup failed: {_petsc_message(e)}") from None
    setup_seconds = _barrier_time(comm) - t0
    rows = lay.local_rows(comm.getRank())
    xv, bv = Ap.createVecs()
    bv.setArray(b[rows])
    xv.set(0.0)
    normb = float(np.linalg.norm(b))
    ksp.setConvergenceHistory(length=maxiter + 1, reset=True)
    t0 = _barrier_time(comm)
    if normb > 0:
        try:
            ksp.solve(bv, xv)
        except PETSc.Error as e:
            raise SolverError(f"PETSc KSPSolve (CG+{kind}) failed: {_petsc_message(e)}") from None
        hist = _history(ksp, normb)
        its = ksp.getIterationNumber()
        reason = _reason_name(PETSc, ksp.getConvergedReason())
    else:
        hist, its, reason = [0.0], 0, "CONVERGED_ATOL"
    solve_seconds = _barrier_time(comm) - t0
    x = _gather(PETSc, xv)
    if nullspace == "constant":
        x -= x.mean()
    rv = bv.duplicate()
    Ap.mult(xv, rv)
    rv.aypx(-1.0, bv)
    final = float(rv.norm()) / normb if normb > 0 else 0.0
    for obj in (xv, bv, rv, ksp, Ap) + ((ns,) if ns is not None else ()):
        obj.destroy()
    _check_reason(reason, its, hist, f"PETSc CG+{kind}", tol)
    return x, {
        "kind": kind,
        "iterations": int(its),
        "converged": reason.startswith("CONVERGED"),
        "reason": reason,
        "residuals": hist,
        "factor": convergence_factor(hist),
        "final_residual": final,
        "setup_seconds": setup_seconds,
        "solve_seconds": solve_seconds,
        "ranks": comm.getSize(),
    }


# ---------------------------------------------------------------------------------- .npz exchange
def save_hierarchy(path, A, Ps, *, coarse_ops=None, b=None, **arrays) -> None:
    """Write a hierarchy to one ``.npz`` file (call on one rank only, e.g. ``if rank == 0``).

    Parameters
    ----------
    path : str or path-like
    A : (n_0, n_0) sparse
    Ps : list of sparse, ``Ps[k]`` of shape (n_k, n_{k+1})
    coarse_ops : list of sparse, optional
    b : (n_0,) array_like, optional
    **arrays : extra numpy arrays stored under their names (e.g. the fine node positions).
    """
    A, Ps, coarse_ops = _check_hierarchy(A, Ps, coarse_ops)
    out: dict[str, np.ndarray] = {"n_levels": np.array(len(Ps) + 1)}

    def put(tag, M):
        out[f"{tag}_data"], out[f"{tag}_indices"], out[f"{tag}_indptr"] = M.data, M.indices, M.indptr
        out[f"{tag}_shape"] = np.array(M.shape)

    put("A", A)
    for k, P in enumerate(Ps):
        put(f"P{k}", P)
    if coarse_ops is not None:
        for k, Ac in enumerate(coarse_ops):
            put(f"C{k}", Ac)
    if b is not None:
        out["b"] = _check_vector(b, A.shape[0])
    for name, arr in arrays.items():
        if name in ("A", "Ps", "coarse_ops", "b", "n_levels") or re.fullmatch(r"(A|P\d+|C\d+)_\w+", name):
            raise SolverInputError(f"extra array name {name!r} clashes with the hierarchy's own keys")
        out[name] = np.asarray(arr)
    np.savez(path, **out)


def load_hierarchy(path) -> dict:
    """Read a file written by :func:`save_hierarchy` (every rank may call it).

    Returns
    -------
    dict
        ``A`` (csr), ``Ps`` (list of csr), ``coarse_ops`` (list or None), ``b`` (array or None), and any
        extra arrays under their names.
    """
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}

    def get(tag):
        return sp.csr_matrix((data.pop(f"{tag}_data"), data.pop(f"{tag}_indices"), data.pop(f"{tag}_indptr")),
                             shape=tuple(data.pop(f"{tag}_shape")))

    L = int(data.pop("n_levels"))
    out = {"A": get("A"), "Ps": [get(f"P{k}") for k in range(L - 1)]}
    out["coarse_ops"] = [get(f"C{k}") for k in range(L - 1)] if "C0_data" in data else None
    out["b"] = data.pop("b", None)
    out.update(data)
    return out
