"""Coarse-level deflation: find the error components a cycle barely reduces and correct them exactly.

A geometric coarse space can miss a few low-energy modes of the finer operator: on a scan with thin,
weakly attached pieces (a wing tip joined to the body by a narrow neck) the cage level's basis functions
span the piece and its neighbour at once, so "the piece moves, the rest does not" is neither smoothed
nor corrected. Such modes are few and local, and an adaptive coarse space catches them the way
adaptive / bootstrap AMG does (Brezina et al. 2004, "Adaptive smoothed aggregation"): run the cycle on
the homogeneous problem ``A x = 0`` and look at what survives.

For a symmetric cycle the error propagation ``E = I - B A`` is self-adjoint in the A-inner product, so
the cycles of one random vector form a Krylov sequence and the Lanczos process (full
re-orthogonalisation, A-inner product) gives Ritz pairs ``(θ, z)`` of ``E``: ``θ`` is the factor by
which one cycle reduces ``z``. :func:`slow_modes` runs :data:`PROBE_CYCLES` steps; if the largest Ritz
value plus its pair's residual ``|E y - θ y|_A`` meets :data:`DEFLATION_GOAL` nothing more is done (the
Ritz value alone is a lower bound of the slowest factor), otherwise it continues to
:data:`LANCZOS_CYCLES` steps and returns the Ritz vectors above the goal as ``Z`` (``Zᵀ A Z = I``).
The i-th largest Ritz value never decreases from one step to the next and never exceeds the i-th largest
eigenvalue (Cauchy interlacing), so once more than ``max_vectors`` Ritz values are above the goal the
answer ("the bulk is slow, deflate nothing") is final: the probe stops there instead of running all
:data:`LANCZOS_CYCLES` steps. :func:`with_deflation` adds the exact correction ``x += Z Zᵀ (b - A x)`` (the A-orthogonal projection
onto span Z) after pre-smoothing and before post-smoothing: the cycle stays symmetric.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from .errors import SolverInputError
from .smoothing import Smoother, chained

__all__ = ["DEFLATION_GOAL", "LANCZOS_CYCLES", "PROBE_CYCLES", "slow_modes", "with_deflation"]

#: Lanczos steps (cycles) of the probe.
PROBE_CYCLES = 8
#: Lanczos steps (cycles) in all when the probe finds modes slower than the goal.
LANCZOS_CYCLES = 24
#: Per-cycle factor above which a level's slow modes are deflated: the V-cycle factor the defaults aim at.
DEFLATION_GOAL = 0.3
#: Largest ``|Zᵀ A Z - I|`` entry of modes returned as they are; beyond it they are A-orthonormalised
#: (:func:`_a_orthonormal`: the correction would not be a projection and could make the cycle diverge).
ORTHONORMAL_TOL = 1e-6


def _ritz(H: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Ritz values (descending) and vectors of the leading ``m x m`` block of the Lanczos matrix."""
    T = H[:m, :m]
    theta, U = np.linalg.eigh((T + T.T) / 2)
    return theta[::-1], U[:, ::-1]


def _kernel_projector(constant: bool, Q: np.ndarray | None) -> Callable[[np.ndarray], None]:
    """In-place removal of the known kernel from a Krylov vector: its mean, and/or its part along ``Q``."""

    def project(w: np.ndarray) -> None:
        if constant:
            w -= w.mean()
        if Q is not None:
            w -= Q @ (Q.T @ w)

    return project


def slow_modes(
    cycle: Callable[[np.ndarray], None],
    A: sp.csr_matrix,
    *,
    constant_nullspace: bool = False,
    nullspace_basis: np.ndarray | None = None,
    max_vectors: int = 8,
    goal: float = DEFLATION_GOAL,
    seed: int = 0,
    keep_bulk: bool = False,
) -> tuple[np.ndarray, dict]:
    """The error components that a symmetric ``cycle`` reduces by less than ``goal`` per application.

    Parameters
    ----------
    cycle : callable
        ``cycle(x)`` applies one cycle to ``A x = 0`` in place (so ``x`` becomes ``E x``); the cycle must
        be symmetric (post-smoother the adjoint of the pre-smoother).
    A : (n, n) csr_matrix
        The level operator (symmetric positive semi-definite).
    constant_nullspace : bool
        Pure Neumann operator: the Krylov vectors are kept at zero mean.
    nullspace_basis : (n, m) float array, optional
        An orthonormal basis ``Q`` of ``ker A`` (e.g. the rigid-body modes of pure-traction elasticity):
        the Krylov vectors are kept orthogonal to it, ``w -= Q (Qᵀ w)``. The cycle leaves a kernel vector
        unchanged (``E z = z``), so without this the probe would report the kernel as a factor-1 mode.
    max_vectors : int
        At most this many vectors are returned.
    goal : float
        Per-cycle factor above which a mode is returned.
    seed : int
        Seed of the random start vector (the result is deterministic).
    keep_bulk : bool
        When more than ``max_vectors`` modes are slower than the goal, return their Ritz vectors in ``info``
        as ``bulk_modes`` (A-orthonormal; where they live decides whether a subdomain solve can take them,
        :func:`solvers.subdomain.slow_region`).

    Returns
    -------
    Z : (n, m) float array
        A-orthonormal slow modes, slowest first. ``m = 0`` when the probe met the goal, or when more than
        ``max_vectors`` modes are slower than it (then the cycle is slow on the bulk of the spectrum, which
        deflation is not meant to fix).
    info : dict
        ``probe_factor`` (largest Ritz value after the probe), ``probe_residual`` (its Ritz pair's
        residual), ``probe_min`` (the smallest Ritz value), ``cycles`` run,
        ``vectors`` (m) and ``factors`` (the Ritz values of the kept vectors); ``slow_modes_found`` when the
        bulk was refused (a lower bound: the count when the probe stopped); ``non_finite`` when a cycle gave
        NaN/inf (nothing is deflated then: the setup never fails because of the probe).
    """
    n = A.shape[0]
    if nullspace_basis is not None:
        nullspace_basis = np.asarray(nullspace_basis, dtype=np.float64)
        if nullspace_basis.ndim != 2 or nullspace_basis.shape[0] != n:
            raise SolverInputError(f"nullspace_basis must have shape ({n}, m), got {nullspace_basis.shape}")
    project = _kernel_projector(constant_nullspace, nullspace_basis)
    steps = LANCZOS_CYCLES
    Q = np.zeros((n, steps + 1))
    AQ = np.zeros_like(Q)
    H = np.zeros((steps + 1, steps))
    info = {"probe_factor": 0.0, "cycles": 0, "vectors": 0, "factors": []}
    q = np.random.default_rng(seed).standard_normal(n)
    project(q)
    Aq = A @ q
    norm = float(np.sqrt(max(q @ Aq, 0.0)))
    if norm == 0.0:
        return np.zeros((n, 0)), info
    Q[:, 0], AQ[:, 0] = q / norm, Aq / norm
    for j in range(steps):
        w = Q[:, j].copy()
        with np.errstate(all="ignore"):
            cycle(w)  # w = E q_j
        if not np.all(np.isfinite(w)):  # a broken level: nothing to deflate; solve() will locate the NaN
            info["non_finite"] = True
            return np.zeros((n, 0)), info
        project(w)
        for _ in range(2):  # full re-orthogonalisation, twice: the Krylov vectors align with the slowest mode
            c = AQ[:, : j + 1].T @ w
            w -= Q[:, : j + 1] @ c
            H[: j + 1, j] += c
        Aw = A @ w
        beta = float(np.sqrt(max(w @ Aw, 0.0)))
        H[j + 1, j] = beta
        info["cycles"] = j + 1
        if j + 1 == PROBE_CYCLES:
            theta, U = _ritz(H, j + 1)
            # the extreme Ritz values of E: the slowest mode, and the most negative one (E must stay > -1 for
            # the cycle to be a positive definite preconditioner)
            info["probe_factor"], info["probe_min"] = float(theta[0]), float(theta[-1])
            # the slowest Ritz pair's residual |E y - θ y|_A = β |u_last| (an eigenvalue lies within it)
            info["probe_residual"] = float(beta * abs(U[-1, 0]))
            # a lower bound (interlacing): met only when the residual cannot lift it above the goal
            if info["probe_factor"] + info["probe_residual"] <= goal or max_vectors <= 0:
                return np.zeros((n, 0)), info
        if j + 1 >= PROBE_CYCLES and j + 1 > max_vectors:
            slow = int(np.count_nonzero(_ritz(H, j + 1)[0] > goal))
            if slow > max_vectors:  # already more slow modes than can be kept: the answer cannot change
                return _refused(Q, H, j + 1, slow, info, keep_bulk)
        # an invariant subspace: the Ritz pairs are exact. The Krylov vectors have unit A-norm, so the scale
        # is at least 1 (a column of round-off, as after a cycle that annihilates q_j, is no scale). On level
        # 1 of the tests' TetGen torus (diffusion, boundary-layer sweeps) w·Aw came out <= 0 at step 9 and the
        # Lanczos relation broke without this test firing: a Ritz value of 1.48, modes with Zᵀ A Z = 0.82, a
        # smoother amplifying by 1e12; the checks after the loop refuse such modes
        if beta <= 1e-10 * max(float(np.abs(H[: j + 1, : j + 1]).max()), 1.0):
            break
        Q[:, j + 1], AQ[:, j + 1] = w / beta, Aw / beta
    k = info["cycles"]
    theta, U = _ritz(H, k)
    if k < PROBE_CYCLES:  # an invariant subspace before the probe's verdict
        info["probe_factor"] = float(theta[0])
    slow = int(np.count_nonzero(theta > goal))
    if slow > max_vectors:  # the bulk of the spectrum, not a few outliers: a smoother / coarse space matter
        return _refused(Q, H, k, slow, info, keep_bulk)
    if slow and theta[0] > 1.0 + ORTHONORMAL_TOL:
        # a symmetric cycle's E = I - B A (B positive definite) has no eigenvalue above 1: the Lanczos
        # relation broke (a Ritz value of 1.48 on the tests' torus), its vectors are noise
        info["broken_ritz_value"] = float(theta[0])
        return np.zeros((n, 0)), info
    Z = _a_orthonormal(Q[:, :k] @ U[:, :slow], A, info)
    info.update(vectors=int(Z.shape[1]), factors=[float(t) for t in theta[:slow]] if Z.shape[1] else [])
    return Z, info


def _refused(Q: np.ndarray, H: np.ndarray, k: int, slow: int, info: dict,
             keep: bool) -> tuple[np.ndarray, dict]:
    """No modes deflated (``slow`` of the ``k``-step Ritz values are above the goal); with ``keep`` their
    Ritz vectors go to ``info["bulk_modes"]``."""
    info["slow_modes_found"] = slow
    if keep:
        info["bulk_modes"] = Q[:, :k] @ _ritz(H, k)[1][:, :slow]
    return np.zeros((Q.shape[0], 0)), info


def _a_orthonormal(Z: np.ndarray, A: sp.csr_matrix, info: dict) -> np.ndarray:
    """``Z`` itself when ``Zᵀ A Z = I`` to :data:`ORTHONORMAL_TOL`, else an A-orthonormal basis of its span
    (``Z V Λ^-1/2`` from ``Zᵀ A Z = V Λ Vᵀ``, directions with ``λ <= 1e-10 max λ`` dropped; ``info`` records
    the deviation as ``reorthonormalized``). The Lanczos basis loses A-orthogonality when the cycle is not
    quite A-self-adjoint or nearly annihilates a Krylov vector, and ``x += Z Zᵀ (b - A x)`` is an
    A-orthogonal projection (it never increases the error's A-norm) only for an A-orthonormal ``Z``."""
    if Z.shape[1] == 0:
        return Z
    G = Z.T @ (A @ Z)
    dev = float(np.abs(G - np.eye(Z.shape[1])).max())
    if dev <= ORTHONORMAL_TOL:
        return Z
    info["reorthonormalized"] = dev
    lam, V = np.linalg.eigh((G + G.T) / 2)
    keep = lam > 1e-10 * max(float(lam.max()), 0.0)
    Z = Z @ (V[:, keep] / np.sqrt(lam[keep]))
    dev = float(np.abs(Z.T @ (A @ Z) - np.eye(Z.shape[1])).max()) if Z.shape[1] else 0.0
    if dev > ORTHONORMAL_TOL:  # Zᵀ A Z lost to cancellation (huge vectors of tiny A-norm): noise, none kept
        info["not_orthonormal"] = dev
        return Z[:, :0]
    return Z


def with_deflation(base: Smoother, A: sp.csr_matrix, Z: np.ndarray, first: bool = False) -> Smoother:
    """``base`` plus the exact correction ``x += Z Zᵀ (b - A x)`` on the A-orthonormal modes ``Z``.

    With ``first=False`` the correction follows ``base`` (pre-smoother), with ``first=True`` it precedes
    it (post-smoother): the pair stays adjoint, so the cycle stays symmetric and preconditions CG.

    Parameters
    ----------
    base : Smoother
    A : (n, n) csr_matrix
        The level operator.
    Z : (n, m) float array
        ``Zᵀ A Z = I`` (:func:`slow_modes`).
    first : bool

    Returns
    -------
    Smoother
        Its ``work`` adds one SpMV and ``2 n m`` multiply-adds (in SpMV units) to ``base.work``.
    """
    Z = np.ascontiguousarray(Z, dtype=np.float64)
    ZT = np.ascontiguousarray(Z.T)

    def correct(A_, x, b):
        x += Z @ (ZT @ (b - A_ @ x))

    apply = chained(base, correct, first)
    work = base.work + 1.0 + 2.0 * Z.size / max(A.nnz, 1)
    return Smoother(base.name, apply, work, dict(base.params, deflation=int(Z.shape[1])))
