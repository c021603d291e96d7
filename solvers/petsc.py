"""Optional PETSc backend: nestmg's hierarchy solved by PETSc's PCMG inside KSP, in parallel under MPI.

Install with ``scripts/install-petsc.sh`` (Debian's PETSc 3.18 + petsc4py built against it; extra
``petsc``). Every rank calls the same functions with the same *global* scipy matrices (built
deterministically on every rank, or read from a ``.npz`` written by :func:`save_operators`); each rank
copies only its own rows into PETSc::

    mpirun -n 4 python my_solve.py            # inside: PetscMultigrid(A, Ps).solve(b)

When the fine level is too large for one rank, :meth:`PetscMultigrid.from_distributed` takes the caller's
distributed PETSc matrix and the coordinates of each rank's unknowns instead, and builds each rank's rows
of ``P₀`` by point location in its crop of the first coarse tet mesh and reads only its rows of the
coarse prolongations (from a :func:`save_coarse_levels` file): no rank holds a global fine-level or
coarse-level object, only the coarsest operator (issue 33; ``docs/examples/petsc_distributed.py``).

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

Lifetime: the PETSc objects of a :class:`PetscMultigrid` are destroyed by ``destroy()`` (or leaving a
``with`` block), when the solver is garbage-collected, and at the latest at interpreter exit, by a
:func:`weakref.finalize` that runs before petsc4py's ``PetscFinalize``. That order matters: petsc4py
finalises PETSc from a C-level exit hook, *after* the Python interpreter is gone, and PETSc then destroys
the objects still alive; the coarsest solve's python PC (``_PyCoarse``) calls back into Python from
``PCReset`` -- a segfault (PETSc's SEGV banner, exit code 59) after a correct solve, for every script
that kept a solver in a global variable.
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np
import scipy.sparse as sp

from .errors import IncompatibleRHSError, SolverError, SolverInputError
from .multilevel import DEFAULT_MAXITER, convergence_factor
from .petsc_amg import petsc_amg_solve
from .petsc_common import (
    SMOOTHER_NAMES,
    PetscUnavailableError,
    _allgather,
    _barrier_time,
    _check_diagonal,
    _check_hierarchy,
    _check_nullspace,
    _check_reason,
    _check_vector,
    _coarse_choice,
    _coarse_owner,
    _fine_owner,
    _gather,
    _ghost_count,
    _ksp_solve,
    _Layout,
    _noop_monitor,
    _options,
    _petsc,
    _petsc_message,
    _prepare_rhs,
    _to_petsc,
    petsc_available,
    row_partition,
)
from .coarse_levels import CoarseLevels, save_coarse_levels
from .petsc_distributed import broadcast_arrays
from .petsc_io import load_operators, save_operators

__all__ = [
    "CoarseLevels",
    "PetscMultigrid",
    "broadcast_arrays",
    "PetscUnavailableError",
    "load_operators",
    "petsc_amg_solve",
    "petsc_available",
    "row_partition",
    "save_coarse_levels",
    "save_operators",
]


class _PyCoarse:
    """PETSc python PC context: :class:`solvers.coarse._CoarseSolver` on the whole coarsest operator.

    On several ranks every rank holds the full (small) coarsest matrix (``MatCreateSubMatrices``) and
    the full right-hand side (scatter to all), solves redundantly and keeps its own rows.
    """

    def __init__(self, nullspace, method, pinv_max, level):
        self.nullspace, self.method, self.pinv_max, self.level = nullspace, method, pinv_max, level
        self.cs = None
        self._scatter = self._xall = None

    def setUp(self, pc) -> None:
        from .coarse import _CoarseSolver

        PETSc = _petsc()
        A, _ = pc.getOperators()
        n = A.getSize()[0]
        if A.getComm().getSize() > 1:
            iset = PETSc.IS().createStride(n, 0, 1, comm=PETSc.COMM_SELF)
            A = A.createSubMatrices(iset, iset)[0]
        ai, aj, av = A.getValuesCSR()
        As = sp.csr_matrix((np.array(av), np.array(aj), np.array(ai)), shape=(n, n))
        As.sum_duplicates()
        self.cs = _CoarseSolver(As, self.nullspace, self.level, self.method, self.pinv_max)
        self.reset(pc)

    def reset(self, pc) -> None:
        """Free the scatter-to-all of :meth:`apply` (PCReset/PCDestroy call this while Python runs)."""
        for obj in (getattr(self, "_scatter", None), getattr(self, "_xall", None)):
            if obj is not None:
                obj.destroy()
        self._scatter = self._xall = None

    def apply(self, pc, x, y) -> None:
        PETSc = _petsc()
        if x.getComm().getSize() > 1:
            if self._scatter is None:
                self._scatter, self._xall = PETSc.Scatter.toAll(x)
            self._scatter.scatter(x, self._xall, PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD)
            sol = self.cs(np.array(self._xall.getArray(readonly=True)))
            lo, hi = y.getOwnershipRange()
            y.setArray(sol[lo:hi])
        else:
            y.setArray(self.cs(np.array(x.getArray(readonly=True))))


def _destroy_petsc(PETSc, objs: list) -> None:
    """Destroy ``objs`` last-created first (the KSP before the matrices it holds), while Python runs.

    After ``PetscFinalize`` (a user's own ``PETSc._finalize()``) there is nothing left to free.
    """
    if PETSc.Sys.isFinalized():
        objs.clear()
        return
    while objs:
        objs.pop().destroy()


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
    coarse_solver : {"auto", "splu", "pivoted", "regularized", "pinv", "petsc"}
        Coarsest solve. The in-process names (default ``"auto"``) run :class:`solvers.MultigridSolver`'s
        coarsest solver (same safeguards: ``"auto"`` survives rank-deficient Galerkin coarse operators
        of cage hierarchies) inside PETSc on every rank, as a python PC. ``"petsc"``: PETSc's Cholesky
        (CHOLMOD) / LU, or SVD for Neumann (dense: slow).
    pinv_max : int
        Size limit of the pseudo-inverse fallback (as in :class:`solvers.MultigridSolver`).

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
        coarse_solver: str = "auto",
        pinv_max: int = 3000,
    ):
        PETSc = _petsc()
        self._configure(PETSc, comm, cycle=cycle, smoother=smoother, presmooth=presmooth,
                        postsmooth=postsmooth, omega=omega, nullspace=nullspace, krylov=krylov,
                        options_prefix=options_prefix, coarse_solver=coarse_solver, pinv_max=pinv_max)
        galerkin, given_ops = _coarse_choice(coarse)
        A, Ps, given_ops = _check_hierarchy(A, Ps, given_ops)
        _check_diagonal(A, "A")
        for k, Ac in enumerate(given_ops or []):
            _check_diagonal(Ac, f"coarse[{k}]")
        self.coarse = "galerkin" if galerkin else "given"  # as MultigridSolver.coarse
        self.n = A.shape[0]
        self.distributed = False
        t0 = _barrier_time(self.comm)
        layouts = self._layouts_for(PETSc, A, Ps, partition)
        self._layouts = layouts
        ghosts = _allgather(PETSc, self.comm, _ghost_count(A, layouts[0], self.comm.getRank()))
        self.rows_per_rank = np.diff(layouts[0].offsets).tolist()
        self.ghosts_per_rank = ghosts.astype(np.int64).tolist()

        mats = [_to_petsc(PETSc, A, layouts[0], layouts[0], self.comm)]
        interp = [_to_petsc(PETSc, P, layouts[k], layouts[k + 1], self.comm) for k, P in enumerate(Ps)]
        given = [] if given_ops is None else [
            _to_petsc(PETSc, Ac, layouts[k + 1], layouts[k + 1], self.comm) for k, Ac in enumerate(given_ops)
        ]
        self._owned.extend(mats + given + interp)
        self._build(mats[0], interp, given, galerkin, options)
        self.setup_seconds = _barrier_time(self.comm) - t0

    @classmethod
    def from_distributed(cls, A, points, coarse_mesh, coarse_Ps=(), **kwargs) -> PetscMultigrid:
        """PCMG on the caller's distributed fine matrix; each rank builds only its own rows of every ``P``.

        No rank ever holds a global fine-level object: the caller's ``A`` stays as it is (any row
        ownership), each rank locates its own fine nodes in its crop of the first coarse tet mesh (the
        tets whose bounding box meets its points' box; :func:`solvers.locate.locate_in_tets`) and
        assembles its rows of ``P₀`` directly as an MPI AIJ matrix. Coarse nodes go to the rank holding
        most of their interpolation weight, which reads only those rows of ``P_1, P_2, ...``; PETSc forms
        the Galerkin operators ``P_kᵀ A_k P_k`` by its parallel ``MatPtAP``. Given a file (``coarse_mesh``
        a path written by :func:`save_coarse_levels`), each rank streams it and keeps only its pieces, so
        no rank holds the coarse levels in full either; given arrays, the caller holds them and the
        solver keeps only the pieces. Only the coarsest operator is gathered on every rank (its exact
        solve). Collective.

        Parameters
        ----------
        A : petsc4py ``PETSc.Mat`` (MPIAIJ / AIJ)
            Fine operator, assembled by the caller; rank ``r`` owns rows ``A.getOwnershipRange()``. Its
            communicator is the solver's. Used as is (with ``nullspace="constant"`` the constant null
            space is attached to it).
        points : (n_local,3) float array
            Coordinates of this rank's fine unknowns, in the order of its owned rows.
        coarse_mesh : str or path-like, :class:`CoarseLevels`, or tuple ``(V_1, T_1)``
            The coarse levels: the path of a :func:`save_coarse_levels` file (read piecewise, the
            scalable choice), or the first coarse tet mesh ``V_1`` (n_1,3) float, ``T_1`` (t_1,4) int,
            identical on every rank (then with ``coarse_Ps``).
        coarse_Ps : list of sparse
            With ``(V_1, T_1)`` only: prolongations between the coarse levels, ``coarse_Ps[k-1]`` of shape
            ``(n_k, n_{k+1})``, k >= 1 (identical on every rank; may be empty: two levels).
        **kwargs
            ``on_boundary_tol`` (default 1e-12, relative to the global fine bounding-box diagonal, as
            :func:`nestmg.prolongation.prolongation`) and every keyword of :class:`PetscMultigrid` except
            ``comm``, ``coarse`` (Galerkin only) and ``partition`` (the caller's ownership is kept; each
            coarse node goes to the rank holding most of its interpolation weight).

        Returns
        -------
        PetscMultigrid
            ``solve(b)`` then takes and returns this rank's entries only. ``location`` holds the
            certification reduced over ranks: ``n_outside`` (0), ``n_on_boundary``; ``coarse_sizes``;
            this rank's ``crop_tets`` and ``coarse_rows`` (rows of each coarse prolongation); ``seconds``.

        Raises
        ------
        SolverInputError
            Wrong shapes, NaN, a ``points`` count that differs from the rank's row count.
        OutsideCoarseMeshError
            On every rank, when any rank has fine nodes outside every coarse tet (``n_outside > 0``).
        """
        from .petsc_distributed import distributed_prolongations

        PETSc = _petsc()
        if not isinstance(A, PETSc.Mat):
            raise SolverInputError(f"A must be a petsc4py PETSc.Mat, got {type(A).__name__}")
        for bad in ("comm", "coarse", "partition"):
            if bad in kwargs:
                raise SolverInputError(f"from_distributed takes no {bad!r}: see its docstring")
        tol = kwargs.pop("on_boundary_tol", 1e-12)
        options = kwargs.pop("options", None)
        self = cls.__new__(cls)
        self._configure(PETSc, A.getComm(), **kwargs)
        t0 = _barrier_time(self.comm)
        self.coarse, self.distributed, self.partition = "galerkin", True, "caller's"
        self.n = int(A.getSize()[0])
        self._layouts = None
        interp, self.location = distributed_prolongations(PETSc, A, points, coarse_mesh, coarse_Ps, tol)
        self._owned.extend(interp)
        self.rows_per_rank = _allgather(PETSc, self.comm, A.getLocalSize()[0]).astype(np.int64).tolist()
        self.ghosts_per_rank = None
        self._build(A, interp, [], True, options)
        self.setup_seconds = _barrier_time(self.comm) - t0
        return self

    def _configure(self, PETSc, comm, *, cycle: str = "V", smoother: str = "sor", presmooth: int = 1,
                   postsmooth: int = 1, omega: float | None = None, nullspace: str | None = None,
                   krylov: str = "cg", options_prefix: str = "nestmg_", coarse_solver: str = "auto",
                   pinv_max: int = 3000) -> None:
        """Check and store the cycle's settings; start the list of owned PETSc objects."""
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
            raise SolverInputError(
                f"options_prefix must be a non-empty string without '-', got {options_prefix!r}")
        if coarse_solver not in ("auto", "splu", "pivoted", "regularized", "pinv", "petsc"):
            raise SolverInputError(
                "coarse_solver must be 'auto', 'splu', 'pivoted', 'regularized', 'pinv' or 'petsc', "
                f"got {coarse_solver!r}")
        self.nullspace = _check_nullspace(nullspace)
        self.comm = PETSc.COMM_WORLD if comm is None else comm
        self.comm_size = self.comm.getSize()
        self.cycle, self.smoother, self.krylov = cycle, smoother, krylov
        self.presmooth, self.postsmooth = int(presmooth), int(postsmooth)
        self.prefix = options_prefix
        self.omega = {"sor": 1.0, "jacobi": 2.0 / 3.0}.get(smoother) if omega is None else omega
        self._coarse_method, self._pinv_max = coarse_solver, int(pinv_max)
        # every PETSc object this solver owns, destroyed last-created first by destroy(), by the garbage
        # collector or at exit (before PetscFinalize: see the module docstring), also if __init__ fails
        self._owned: list = []
        self._finalizer = weakref.finalize(self, _destroy_petsc, PETSc, self._owned)

    def _layouts_for(self, PETSc, A, Ps, partition) -> list[_Layout]:
        """Row layout of every level for global matrices: the fine partition, then coarse owners."""
        size = self.comm_size
        owner = None
        if isinstance(partition, str) and partition not in ("auto", "natural", "rcm"):
            if partition not in ("ptscotch", "parmetis"):
                raise SolverInputError("partition must be 'auto', 'natural', 'rcm', 'ptscotch', 'parmetis' "
                                       f"or an array of ranks, got {partition!r}")
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
            nat = _Layout(None, self.n, size)
            A_nat = _to_petsc(PETSc, A, nat, nat, self.comm) if isinstance(partition, str) else None
            try:
                owner = _fine_owner(PETSc, A, A_nat, partition, self.n, size, self.comm)
            finally:
                if A_nat is not None:
                    A_nat.destroy()
        elif partition == "rcm" and size > 1:
            owner = _fine_owner(PETSc, A, None, partition, self.n, size, self.comm)
        given = partition if isinstance(partition, str) else "given"
        self.partition = "natural" if owner is None else given
        layouts = [_Layout(owner, self.n, size)]
        for P in Ps:
            if owner is not None:
                owner = _coarse_owner(P, owner, size)
            layouts.append(_Layout(owner, P.shape[1], size))
        return layouts

    def _build(self, A, interp: list, given: list, galerkin: bool, options: dict | None) -> None:
        """KSP + PCMG on the PETSc fine operator ``A`` and interpolations ``interp`` (finest first)."""
        PETSc = self._PETSc
        if self.nullspace == "constant":
            ns = PETSc.NullSpace().create(constant=True, comm=self.comm)
            self._owned.append(ns)
            for M in [A] + given:
                M.setNullSpace(ns)
        self._A = A
        nlev = len(interp) + 1
        self._nlev = nlev
        ksp = PETSc.KSP().create(comm=self.comm)
        self._owned.append(ksp)  # destroyed first: it holds the operators and the python coarse PC
        ksp.setOptionsPrefix(self.prefix)
        ksp.setOperators(self._A)
        ksp.setType("cg" if self.krylov == "cg" else "richardson")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        if self.krylov == "richardson":
            # Without a monitor KSPRICHARDSON hands the whole iteration to PCApplyRichardson_MG, which
            # neither records a residual history nor computes the true residual each cycle.
            ksp.setMonitor(_noop_monitor)
        pc = ksp.getPC()
        pc.setType("mg")
        pc.setMGLevels(nlev)
        pc.setMGType(PETSc.PC.MGType.MULTIPLICATIVE)
        pc.setMGCycleType(PETSc.PC.MGCycleType.V if self.cycle == "V" else PETSc.PC.MGCycleType.W)
        for k, P in enumerate(interp):
            pc.setMGInterpolation(nlev - 1 - k, P)  # PETSc level nlev-1-k is nestmg level k
        if not galerkin:
            for k, Ac in enumerate(given):
                lev = nlev - 2 - k
                if lev == 0:
                    pc.getMGCoarseSolve().setOperators(Ac)
                else:
                    pc.getMGSmootherDown(lev).setOperators(Ac)
                    pc.getMGSmootherUp(lev).setOperators(Ac)
        self._setup_ksp(ksp, pc, galerkin, options)

    def _setup_ksp(self, ksp, pc, galerkin: bool, options: dict | None) -> None:
        """Options database, smoothers, coarsest solve and ``KSPSetUp``; then the per-level sizes."""
        PETSc, nlev, prefix = self._PETSc, self._nlev, self.prefix
        top = {"pc_mg_galerkin": "both" if galerkin else "none"}
        top.update(options or {})
        with _options(PETSc, prefix, top):
            ksp.setFromOptions()
            # the user may have asked for another cycle through -<prefix>pc_mg_cycle_type
            user_cycle = PETSc.Options().getString(f"{prefix}pc_mg_cycle_type", self.cycle)
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

        Default (``coarse_solver="auto"`` and the other in-process names): a PETSc python PC that runs
        the in-process coarsest solver (:class:`solvers.coarse._CoarseSolver`: SuperLU, validated; then
        the regularised LU of ``A + 1e-9 diag(A)``; then the pseudo-inverse up to ``pinv_max``
        unknowns) on the whole coarsest operator, gathered on every rank. So PETSc survives the
        rank-deficient Galerkin coarse operators of cage hierarchies exactly where
        :class:`solvers.MultigridSolver` does (issue 15: PETSc's own Cholesky stopped at a zero pivot).
        ``coarse_solver="petsc"`` keeps PETSc's factorisations:

        Cholesky by CHOLMOD when PETSc has SuiteSparse (the coarse operators are SPD; 3.5x faster than
        PETSc's own LU on a 6.8k-unknown Galerkin operator with 73 non-zeros per row), else PETSc's LU;
        an SVD pseudo-inverse for a singular Neumann operator.
        """
        PETSc = self._PETSc
        if self._coarse_method != "petsc":
            cksp.setType("preonly")
            cpc = cksp.getPC()
            cpc.setType("python")
            self._pycoarse = _PyCoarse(self.nullspace, self._coarse_method, self._pinv_max, self._nlev - 1)
            cpc.setPythonContext(self._pycoarse)
            self.coarse_solver = f"in-process {self._coarse_method} (gathered on every rank)"
            return
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
            f"Coarse operators:   {'Galerkin (PETSc MatPtAP)' if self.coarse == 'galerkin' else 'given'}",
            (f"Partition:          {self.partition} (fine rows per rank {self.rows_per_rank}"
             + ("" if self.ghosts_per_rank is None else f", off-rank couplings {self.ghosts_per_rank}")
             + ")"),
            f"Null space:         {self.nullspace}",
            f"Coarsest solve:     {self.coarse_solver}{' (redundant)' if self.comm_size > 1 else ''}",
            "  level   unknowns     nonzeros   nnz/row",
        ]
        for k, L in enumerate(self.levels):
            lines.append(f"{k:7d} {L['n']:10d} {L['nnz']:12d} {L['nnz'] / max(L['n'], 1):9.1f}")
        return "\n".join(lines)

    def view(self) -> None:
        """Print PETSc's own description of the solver (``KSPView``)."""
        self._check_alive()
        self.ksp.view()

    def _check_alive(self) -> None:
        if not self._finalizer.alive:
            raise SolverError("this PetscMultigrid was destroyed (destroy() or the end of its with block)")

    def local_rows(self) -> np.ndarray:
        """Global (caller's numbering) fine rows owned by this rank."""
        if self.distributed:
            return np.arange(*self._A.getOwnershipRange())
        return self._layouts[0].local_rows(self.comm.getRank())

    # ------------------------------------------------------------------ solve
    def solve(self, b, tol: float = 1e-8, maxiter: int = DEFAULT_MAXITER, *, x0=None, project: bool = False,
              divtol: float = 1e5) -> tuple[np.ndarray, dict]:
        """Solve ``A x = b``; collective (every rank calls it with the same global ``b``).

        Parameters
        ----------
        b : (n_0,) array_like
            Global right-hand side (identical on every rank); for a solver made by
            :meth:`from_distributed`, this rank's entries only, ``(n_local,)`` in the order of its rows.
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
            Global solution on every rank (zero plain mean with ``nullspace="constant"``); this rank's
            entries only, ``(n_local,)``, for a solver made by :meth:`from_distributed`.
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
        self._check_alive()
        maxiter = int(maxiter)
        if maxiter < 0:
            raise SolverInputError(f"maxiter must be >= 0, got {maxiter}")
        if not tol > 0:
            raise SolverInputError(f"tol must be > 0, got {tol}")
        xv, bv = self._A.createVecs()
        if self.distributed:
            self._fill_local(bv, xv, b, x0, project)
        else:
            b = _prepare_rhs(b, self.n, self.nullspace, project)
            rows = self._layouts[0].local_rows(self.comm.getRank())
            bv.setArray(b[rows])
            if x0 is not None:
                xv.setArray(_check_vector(x0, self.n, "x0")[rows])
        self.ksp.setInitialGuessNonzero(x0 is not None)
        if x0 is None:
            xv.set(0.0)
        normb = float(bv.norm())
        ksp = self.ksp
        ksp.setTolerances(rtol=tol, atol=1e-300, divtol=divtol, max_it=maxiter)
        ksp.setConvergenceHistory(length=maxiter + 1, reset=True)
        out = _ksp_solve(PETSc, ksp, self._A, bv, xv, normb, self.comm)
        hist, its, reason = out["history"], out["iterations"], out["reason"]
        solve_seconds, final = out["solve_seconds"], out["final"]
        if self.distributed:
            if self.nullspace == "constant":
                xv.shift(-xv.sum() / self.n)
            x = xv.getArray().copy()
        else:
            x = self._layouts[0].to_old(_gather(PETSc, xv))
            if self.nullspace == "constant":
                x -= x.mean()
        for v in (xv, bv):
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
            "ghosts_per_rank": None if self.ghosts_per_rank is None else list(self.ghosts_per_rank),
        }

    def _fill_local(self, bv, xv, b, x0, project: bool) -> None:
        """This rank's ``b`` (and ``x0``) into PETSc vectors; the Neumann compatibility check is global."""
        n_local = bv.getLocalSize()
        try:  # a bad local vector must stop every rank, not leave the others waiting in KSPSolve
            b, error = _check_vector(b, n_local), ""
            x0 = None if x0 is None else _check_vector(x0, n_local, "x0")
        except SolverInputError as e:
            error = str(e)
        bad = np.flatnonzero(_allgather(self._PETSc, self.comm, float(bool(error))))
        if bad.size:
            raise SolverInputError(error or f"rank {bad[0]} was given a bad local b or x0 (this rank's are "
                                   "fine)")
        bv.setArray(b)
        if x0 is not None:
            xv.setArray(x0)
        if self.nullspace == "constant":
            total, scale = bv.sum(), bv.norm(self._PETSc.NormType.NORM_1)
            if project:
                bv.shift(-total / self.n)
            elif abs(total) > 1e-10 * max(scale, 1e-300):
                raise IncompatibleRHSError(
                    f"sum(b) = {total:.3e} over all ranks is not zero (relative {abs(total) / scale:.2e}): "
                    "the singular system has no solution; pass project=True to remove the mean of b")

    def destroy(self) -> None:
        """Free the PETSc objects now (collective; idempotent).

        Also done when the solver is garbage-collected, and at interpreter exit before PETSc is finalised.
        """
        self._finalizer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()
