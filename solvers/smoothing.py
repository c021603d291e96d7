"""Smoothers chosen by name, built on pyamg's compiled relaxation kernels.

A smoother is set up once per level from its operator and applied in place::

    sm = make_smoother(A, ("chebyshev", {"degree": 3}))
    sm(A, x, b)          # x <- smoothed x, modified in place

Names (see :data:`SMOOTHERS`): ``"gauss_seidel"`` (``sweep="forward"|"backward"|"symmetric"``),
``"block_gauss_seidel"`` (nodal 3x3 blocks, :mod:`solvers.block_smoothing`), ``"symmetric_gauss_seidel"``,
``"jacobi"`` (weighted), ``"chebyshev"`` (Jacobi-preconditioned) and ``"none"``. Every setup function
accepts ``iterations`` (the number of sweeps: ν in V(ν, ν)).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from pyamg.relaxation import relaxation
from pyamg.relaxation.chebyshev import chebyshev_polynomial_coefficients
from pyamg.util.linalg import approximate_spectral_radius

from .errors import SolverInputError

__all__ = ["SMOOTHERS", "Smoother", "local_rows", "make_smoother", "reversed_order", "spectral_radius",
           "triangular_split", "with_local_sweeps"]


@dataclass
class Smoother:
    """A smoother bound to one level.

    Attributes
    ----------
    name : str
    apply : callable ``(A, x, b) -> None``, updates ``x`` in place.
    work : float
        Cost of one application in units of one SpMV with ``A`` (used by ``cycle_complexity``).
    params : dict
        The resolved parameters (e.g. the Jacobi weight or Chebyshev interval actually used).
    """

    name: str
    apply: Callable[[sp.csr_matrix, np.ndarray, np.ndarray], None]
    work: float
    params: dict = field(default_factory=dict)
    #: optional ``(A, x, b, zero) -> r``: ``apply`` then the residual ``b - A x``, cheaper than a separate
    #: product (``zero``: ``x`` is zero on entry); a pre-smoother's fast path in the cycle, see
    #: :func:`setup_gauss_seidel`
    smooth_residual: Callable | None = None

    def __call__(self, A, x, b) -> None:
        self.apply(A, x, b)

    def residual(self, A, x, b, zero: bool = False) -> np.ndarray:
        """Smooth ``x`` in place and return ``b - A x`` (by ``smooth_residual`` when the smoother has one)."""
        if self.smooth_residual is not None:
            r = self.smooth_residual(A, x, b, zero)
            if r is not None:
                return r
        self.apply(A, x, b)
        return b - A @ x


def _check_iterations(iterations) -> int:
    it = int(iterations)
    if it < 0 or it != iterations:
        raise SolverInputError(f"smoother iterations must be a non-negative integer, got {iterations!r}")
    return it


def _diag(A: sp.csr_matrix) -> np.ndarray:
    d = A.diagonal()
    if np.any(d <= 0):
        bad = np.flatnonzero(d <= 0)
        raise SolverInputError(
            f"smoother needs a positive diagonal; {bad.size} rows have diag <= 0 (first row {bad[0]})"
        )
    return d


def spectral_radius(A: sp.spmatrix, jacobi: bool = False, method: str = "lanczos") -> float:
    """Spectral radius of a symmetric ``A`` (or of ``D⁻¹A`` with ``jacobi=True``).

    Parameters
    ----------
    A : (n, n) sparse, symmetric
    jacobi : bool
        Estimate ``ρ(D⁻¹A)`` (computed on the similar symmetric matrix ``D^{-1/2} A D^{-1/2}``).
    method : {"lanczos", "gershgorin"}
        ``"lanczos"``: pyamg's 15-step Lanczos estimate from a fixed (seeded) start vector; it
        approaches ρ from below (about 4% low on the 3D Kuhn Laplacian), which Chebyshev's default
        ``upper_bound=1.1`` covers. ``"gershgorin"``: the bound ``max_i Σ_j |a_ij|`` (one pass, never
        below ρ; tight for M-matrices, loose when off-diagonals are positive).

    Returns
    -------
    float
    """
    A = sp.csr_matrix(A)
    if jacobi:
        d = _diag(A)
        # D^{-1/2} A D^{-1/2} is symmetric and similar to D^{-1} A
        s = 1.0 / np.sqrt(d)
        A = sp.csr_matrix(sp.diags(s) @ A @ sp.diags(s))
    if method == "gershgorin":
        return float(np.asarray(abs(A).sum(axis=1)).max())
    if method != "lanczos":
        raise SolverInputError(f"method must be 'lanczos' or 'gershgorin', got {method!r}")
    v0 = np.random.default_rng(0).random((A.shape[0], 1))
    return float(approximate_spectral_radius(A, symmetric=True, maxiter=15, restart=0, initial_guess=v0))


def _rho(A, rho) -> float:
    """Resolve a ``rho`` argument: a number, None (Lanczos) or a method name."""
    if rho is None:
        return spectral_radius(A, jacobi=True)
    if isinstance(rho, str):
        return spectral_radius(A, jacobi=True, method=rho)
    rho = float(rho)
    if not (np.isfinite(rho) and rho > 0):
        raise SolverInputError(f"rho must be a positive number, got {rho}")
    return rho


def setup_gauss_seidel(A: sp.csr_matrix, sweep: str = "forward", iterations: int = 1, omega: float = 1.0,
                       *, diagonal_checked: bool = False, lower=None):
    """Gauss–Seidel (SOR with ``omega != 1``); ``sweep`` is forward, backward or symmetric.

    ``diagonal_checked=True``: the caller has checked that ``A``'s diagonal is positive (as
    :class:`solvers.MultigridSolver` does once per level), so the O(nnz) check is skipped.
    ``lower``: ``(D + L, diag(A))`` of a symmetric ``A`` (``D + L`` its entries with column <= row, any order
    within rows; no copy is made): the forward sweeps' residual shortcut (:func:`_forward_residual`) then
    reads ``U = (D + L)ᵀ - D`` off it instead of splitting ``A`` at its first use.
    """
    if sweep not in ("forward", "backward", "symmetric"):
        raise SolverInputError(f"sweep must be 'forward', 'backward' or 'symmetric', got {sweep!r}")
    it = _check_iterations(iterations)
    if not diagonal_checked:
        _diag(A)
    omega = float(omega)
    if not 0.0 < omega < 2.0:
        raise SolverInputError(f"Gauss-Seidel/SOR weight must be in (0, 2), got {omega}")
    A0 = A

    reversed_A: list = []  # J A J, built on first use (as the forward split of _forward_residual)

    def backward(A, x, b, iterations):
        if (A is not A0 or x.ndim != 1 or not isinstance(A, sp.csr_matrix)
                or A.nnz < REVERSED_SWEEP_MIN_ROW * A.shape[0]):
            relaxation.gauss_seidel(A, x, b, iterations=iterations, sweep="backward", omega=omega)
            return
        # a backward sweep on A is a forward sweep on J A J (J reverses the numbering) that reads the
        # matrix forwards in memory (see reversed_order)
        if not reversed_A:
            reversed_A.append(reversed_order(A0))
        xr = x[::-1].copy()
        relaxation.gauss_seidel(reversed_A[0], xr, np.ascontiguousarray(b[::-1]), iterations=iterations,
                                sweep="forward", omega=omega)
        x[:] = xr[::-1]

    def apply(A, x, b):
        if not it:
            return
        if sweep == "backward":
            backward(A, x, b, it)
            return
        if sweep == "symmetric":  # forward then backward (pyamg's own symmetric sweep drops omega)
            for _ in range(it):
                relaxation.gauss_seidel(A, x, b, sweep="forward", omega=omega)
                backward(A, x, b, 1)
            return
        relaxation.gauss_seidel(A, x, b, iterations=it, sweep=sweep, omega=omega)

    work = it * (2.0 if sweep == "symmetric" else 1.0)
    fast = (_forward_residual(A, it, lower) if sweep == "forward" and omega == 1.0 and it
            and isinstance(A, sp.csr_matrix) else None)
    return Smoother("gauss_seidel", apply, work, {"sweep": sweep, "iterations": it, "omega": omega},
                    smooth_residual=fast)


#: Backward Gauss–Seidel sweeps run forwards on :func:`reversed_order`'s copy of a matrix whose rows hold at
#: least this many entries on average (4 cache lines of values). Measured
#: (``benchmarks/results/user_mesh/sweep_direction.json``): 4x faster on the first coarse levels of the 1M-tet
#: user hierarchies (50 entries per row, 25k rows), 1.2x on their second (75 per row, 4-7k rows: in cache), no
#: gain on their fine levels (14-15 per row: a sweep's cost is per row there); the copy costs memory, so it is
#: made only where it pays.
REVERSED_SWEEP_MIN_ROW = 32


def reversed_order(A: sp.csr_matrix) -> sp.csr_matrix:
    """``J A J`` for the reversal ``J`` of the numbering (unknown ``i`` becomes ``n - 1 - i``): ``A``'s three
    arrays reversed, one O(nnz) copy (canonical when ``A`` is).

    A backward Gauss–Seidel sweep on ``A`` is a forward sweep on ``J A J`` with ``J x`` and ``J b``, the same
    arithmetic up to the order of each row's sum, but it reads the matrix forwards in memory. pyamg's
    backward sweep reads it row by row downwards, each row upwards; on Galerkin coarse operators (50-100
    entries per row) that took up to 4x its forward sweep (hardware prefetch follows the rising runs within
    rows, not the falling row order): on the first coarse levels of 1M-tet user hierarchies 6.2-7.0 against
    1.5-1.7 CPU ms for two sweeps in 7 of 8 cases, 2.0 against 1.5 in the eighth
    (``benchmarks/results/user_mesh/sweep_direction.json``)."""
    n = A.shape[0]
    indptr = np.ascontiguousarray(A.indptr[-1] - A.indptr[::-1])
    indices = np.ascontiguousarray((n - 1 - A.indices)[::-1])
    out = sp.csr_matrix((np.ascontiguousarray(A.data[::-1]), indices, indptr), shape=A.shape)
    out.has_sorted_indices = bool(A.has_sorted_indices)
    return out


def triangular_split(A: sp.csr_matrix) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """``(D + L, U)``: the lower triangle with the diagonal and the strict upper triangle of a CSR matrix
    (one comparison per entry and two order-keeping gathers: each row keeps its entries' order)."""
    n = A.shape[0]
    rows = np.repeat(np.arange(n, dtype=A.indices.dtype), np.diff(A.indptr))
    upper = A.indices > rows
    del rows
    before = np.zeros(A.nnz + 1, dtype=A.indptr.dtype)  # upper entries before each position
    np.cumsum(upper, out=before[1:])
    ptr_u = before[A.indptr]
    ptr_l = A.indptr - ptr_u
    lower = ~upper
    L = sp.csr_matrix((A.data[lower], A.indices[lower], ptr_l), shape=A.shape)
    U = sp.csr_matrix((A.data[upper], A.indices[upper], ptr_u), shape=A.shape)
    return L, U


def _forward_residual(A0: sp.csr_matrix, it: int, lower=None) -> Callable:
    """``smooth_residual`` of ``it`` forward Gauss–Seidel sweeps on ``A0`` (the same result as the sweeps,
    cheaper residual). A forward sweep solves ``(D + L) x_new = b - U x_old``, so afterwards
    ``b - A x_new = U (x_old - x_new)``: a product with the strict upper triangle ``U`` instead of ``A``.
    From a zero ``x`` the first sweep is a forward substitution with ``D + L`` (half the entries of ``A``;
    the upper part would multiply zeros). ``lower = (D + L, d)`` of a symmetric ``A0`` gives both: ``U v =
    (D + L)ᵀ v - d v``. Without it, ``A0`` is split on first use (:func:`triangular_split`, a copy of its
    entries). On the fine levels of 1M-tet user hierarchies (14-15 entries per row) the product with ``U``
    cost 0.62-0.99 of one with ``A`` (0.67-1.11 as ``(D + L)ᵀ``), the substitution 0.78-0.93 of a sweep,
    and the split 9.6-10.7 sweeps (``benchmarks/results/user_mesh/cycle_cost.json``): over a solve of 7-12
    cycles the shortcut pays only with ``lower``."""
    split: list = []

    def smooth_residual(A, x, b, zero):
        if A is not A0 or x.ndim != 1:
            return None  # another operator, or a block of vectors: the plain path
        if not split:
            if lower is not None:
                L, d = lower
                split.extend((L, lambda v: L.T @ v - d * v))
            else:
                L, U = triangular_split(A0)
                split.extend((L, U.__matmul__))
        L, upper = split
        left = it
        if zero:
            relaxation.gauss_seidel(L, x, b, iterations=1, sweep="forward")
            left -= 1
            if not left:
                return -upper(x)
        if left > 1:
            relaxation.gauss_seidel(A, x, b, iterations=left - 1, sweep="forward")
        x_old = x.copy()
        relaxation.gauss_seidel(A, x, b, iterations=1, sweep="forward")
        x_old -= x
        return upper(x_old)

    return smooth_residual


def setup_block_gauss_seidel(A: sp.csr_matrix, **options) -> Smoother:
    """Nodal block Gauss–Seidel for interleaved vector unknowns (``blocksize=3``, ``sweep``, ``iterations``,
    ``ordering="multicolor"|"natural"``): :func:`solvers.block_smoothing.setup_block_gauss_seidel`."""
    from .block_smoothing import setup_block_gauss_seidel as setup

    return setup(A, **options)


def setup_symmetric_gauss_seidel(A: sp.csr_matrix, iterations: int = 1, omega: float = 1.0):
    """Symmetric Gauss–Seidel: a forward then a backward sweep per iteration."""
    sm = setup_gauss_seidel(A, sweep="symmetric", iterations=iterations, omega=omega)
    sm.name = "symmetric_gauss_seidel"
    return sm


def setup_jacobi(A: sp.csr_matrix, omega: float | None = None, iterations: int = 1, rho=None):
    """Weighted Jacobi ``x += ω D⁻¹ (b - A x)``.

    ``omega=None`` picks ``4 / (3 ρ(D⁻¹A))``, the weight that damps the upper two thirds of the
    spectrum of ``D⁻¹A`` best; ``rho`` is a number, None (Lanczos estimate) or ``"gershgorin"``.
    """
    it = _check_iterations(iterations)
    _diag(A)
    if omega is None:
        omega = 4.0 / (3.0 * _rho(A, rho))
    omega = float(omega)
    if not omega > 0:
        raise SolverInputError(f"Jacobi weight must be > 0, got {omega}")

    def apply(A, x, b):
        if it:
            relaxation.jacobi(A, x, b, iterations=it, omega=omega)

    return Smoother("jacobi", apply, float(it), {"omega": omega, "iterations": it})


def setup_chebyshev(
    A: sp.csr_matrix,
    degree: int = 3,
    lower_bound: float = 1.0 / 30.0,
    upper_bound: float = 1.1,
    iterations: int = 1,
    rho: float | None = None,
):
    """Jacobi-preconditioned Chebyshev smoother ``x += p(D⁻¹A) D⁻¹ (b - A x)``.

    ``p`` is the degree-``degree`` Chebyshev polynomial that damps the eigenvalues of ``D⁻¹A`` in
    ``[lower_bound·ρ, upper_bound·ρ]``, with ``ρ = ρ(D⁻¹A)`` a number, None (Lanczos estimate) or
    ``"gershgorin"``. Applied with pyamg's polynomial kernel to ``D⁻¹A`` (same sparsity as ``A``).
    """
    it = _check_iterations(iterations)
    degree = int(degree)
    if degree < 1:
        raise SolverInputError(f"Chebyshev degree must be >= 1, got {degree}")
    if not 0.0 < lower_bound < upper_bound:
        raise SolverInputError(f"need 0 < lower_bound < upper_bound, got {lower_bound}, {upper_bound}")
    d = _diag(A)
    dinv = 1.0 / d
    DinvA = sp.csr_matrix(sp.diags(dinv) @ A)
    rho = _rho(A, rho)
    a, bnd = rho * lower_bound, rho * upper_bound
    # chebyshev_polynomial_coefficients gives 1 - x q(x); drop the constant term to get -q's coefficients
    coefficients = -chebyshev_polynomial_coefficients(a, bnd, degree)[:-1]

    def apply(A, x, b):
        if it:
            relaxation.polynomial(DinvA, x, dinv * b, coefficients=coefficients, iterations=it)

    return Smoother(
        "chebyshev",
        apply,
        float(it * degree),
        {"degree": degree, "lower": a, "upper": bnd, "rho": rho, "iterations": it},
    )


def setup_none(A: sp.csr_matrix, iterations: int = 0):
    """No smoothing (for experiments)."""
    return Smoother("none", lambda A, x, b: None, 0.0, {})


def local_rows(A: sp.csr_matrix, nodes) -> sp.csr_matrix:
    """Copy of the rows ``nodes`` of ``A`` stored one after the other, as a square CSR matrix whose other
    rows are empty (what :func:`with_local_sweeps` relaxes; build it once and pass it as ``rows=`` to
    share it between a pre- and a post-smoother)."""
    idx = np.unique(np.asarray(nodes, dtype=np.int64))
    lens = np.zeros(A.shape[0], dtype=np.int64)
    lens[idx] = A.indptr[idx + 1] - A.indptr[idx]
    indptr = np.zeros(A.shape[0] + 1, dtype=A.indptr.dtype)
    np.cumsum(lens, out=indptr[1:])
    sub = A[idx]
    return sp.csr_matrix((sub.data, sub.indices, indptr), shape=A.shape)


def chained(base: Smoother, extra: Callable, first: bool) -> Callable:
    """``apply(A, x, b)``: ``extra`` after ``base`` (a pre-smoother), or before it with ``first=True`` (the
    adjoint post-smoother of a pair)."""

    def apply(A, x, b):
        if first:
            extra(A, x, b)
            base(A, x, b)
        else:
            base(A, x, b)
            extra(A, x, b)

    return apply


def with_local_sweeps(base: Smoother, A: sp.csr_matrix, nodes, sweeps: int = 1, first: bool = False,
                      sweep: str = "symmetric", rows: sp.csr_matrix | None = None) -> Smoother:
    """``base`` plus ``sweeps`` extra symmetric Gauss–Seidel sweeps restricted to the rows ``nodes``.

    Local relaxation (Brandt's "local relaxation" near boundaries and singularities): where the
    global smoother is weak on a small set of unknowns, a few extra sweeps there remove the error
    the coarse grid cannot see, at the cost of those rows only. With ``first=False`` the local
    sweeps follow ``base`` (a pre-smoother), with ``first=True`` they precede it (the post-smoother):
    the pair is then adjoint when ``base`` is self-adjoint or paired with its adjoint, so the cycle
    stays symmetric and preconditions CG.

    Parameters
    ----------
    base : Smoother
    A : (n, n) csr_matrix
        The level operator.
    nodes : int array
        Rows relaxed by the extra sweeps (sorted, unique).
    sweeps : int
        Extra symmetric sweeps (each is a forward and a backward pass over ``nodes``).
    first : bool
        Apply the local sweeps before ``base`` instead of after.
    sweep : {"symmetric", "forward", "backward"}
        Direction of each local sweep. A forward pre-smoother paired with a backward post-smoother
        (``first=True``) is still an adjoint pair, at half the cost of symmetric local sweeps.
    rows : csr_matrix, optional
        :func:`local_rows` ``(A, nodes)`` if already built (a pre/post pair shares one copy).

    Returns
    -------
    Smoother
        Its ``work`` adds ``2 * sweeps * nnz(A[nodes]) / nnz(A)`` SpMV to ``base.work``.
    """
    it = _check_iterations(sweeps)
    if sweep not in ("symmetric", "forward", "backward"):
        raise SolverInputError(f"local sweep must be 'symmetric', 'forward' or 'backward', got {sweep!r}")
    idx = np.unique(np.asarray(nodes, dtype=np.int64))
    if idx.size and (idx[0] < 0 or idx[-1] >= A.shape[0]):
        raise SolverInputError(f"local smoothing nodes must lie in [0, {A.shape[0]}), got [{idx[0]}, {idx[-1]}]")
    if it == 0 or idx.size == 0:
        return base
    idx = idx.astype(A.indices.dtype)
    # The sweeps read a copy of the rows ``idx`` stored one after the other (a square CSR matrix whose
    # other rows are empty): the boundary layer is scattered through the node order, and reading its
    # rows in place costs ~1.7x more per nonzero than reading them contiguously (memory latency;
    # measured at 1M tets, docs/reuse.md). Costs a copy of those rows (nnz(A[idx])).
    A_loc = local_rows(A, idx) if rows is None else rows
    if A_loc.shape != A.shape or A_loc.nnz != int((A.indptr[idx + 1] - A.indptr[idx]).sum()):
        raise SolverInputError("rows must be local_rows(A, nodes) of this operator and node set")

    def local(A, x, b):
        # ``A`` (the level operator passed at call time) has the same rows: A_loc is a copy of them
        relaxation.gauss_seidel_indexed(A_loc, x, b, idx, iterations=it, sweep=sweep)

    work = base.work + (2.0 if sweep == "symmetric" else 1.0) * it * A_loc.nnz / max(A.nnz, 1)
    apply = chained(base, local, first)
    params = dict(base.params, local_nodes=int(idx.size), local_sweeps=it, local_sweep=sweep)
    return Smoother(base.name, apply, work, params)


SMOOTHERS: dict[str, Callable[..., Smoother]] = {
    "gauss_seidel": setup_gauss_seidel,
    "block_gauss_seidel": setup_block_gauss_seidel,
    "symmetric_gauss_seidel": setup_symmetric_gauss_seidel,
    "jacobi": setup_jacobi,
    "chebyshev": setup_chebyshev,
    "none": setup_none,
}


def make_smoother(A: sp.csr_matrix, spec, *, diagonal_checked: bool = False, lower=None) -> Smoother:
    """Build a :class:`Smoother` for operator ``A`` from a spec.

    Parameters
    ----------
    A : (n, n) csr_matrix
    spec : str, (str, dict), or Smoother
        A name from :data:`SMOOTHERS`, or ``(name, options)`` such as
        ``("gauss_seidel", {"sweep": "symmetric", "iterations": 2})``.

    diagonal_checked : bool
        The caller has checked that ``A``'s diagonal is positive: Gauss–Seidel skips its own check.
    lower : (csr_matrix, ndarray), optional
        ``(D + L, diag(A))`` of a symmetric ``A`` (e.g. kept by :class:`solvers.MultigridSolver`'s Galerkin
        products): forward Gauss–Seidel uses it instead of splitting ``A`` (see :func:`setup_gauss_seidel`);
        other smoothers ignore it.

    Returns
    -------
    Smoother
    """
    if isinstance(spec, Smoother):
        return spec
    if isinstance(spec, str):
        name, opts = spec, {}
    elif isinstance(spec, (tuple, list)) and len(spec) == 2 and isinstance(spec[0], str):
        name, opts = spec[0], dict(spec[1] or {})
    else:
        raise SolverInputError(f"smoother spec must be a name or (name, options), got {spec!r}")
    if name not in SMOOTHERS:
        raise SolverInputError(f"unknown smoother {name!r}; choose one of {sorted(SMOOTHERS)}")
    if SMOOTHERS[name] is setup_gauss_seidel:
        if diagonal_checked:
            opts["diagonal_checked"] = True
        if lower is not None:
            opts["lower"] = lower
    try:
        return SMOOTHERS[name](A, **opts)
    except TypeError as e:  # unknown option name
        raise SolverInputError(f"bad options for smoother {name!r}: {e}") from None
