"""Linear elasticity with P1 vector elements on tets, and multigrid for it.

Conventions
-----------
* Unknowns are **interleaved** per node: ``u = [x_0, y_0, z_0, x_1, y_1, z_1, ...]``, i.e. dof
  ``3 a + i`` is component ``i`` of the displacement of node ``a``. Every ``(3n, 3n)`` operator here is
  a csr matrix of 3x3 nodal blocks in that order.
* Isotropic material, Lamé parameters from Young's modulus ``E`` and Poisson's ratio ``ν``:
  ``λ = E ν / ((1 + ν)(1 - 2ν))``, ``μ = E / (2 (1 + ν))``.
* Bilinear form ``a(u, v) = ∫ 2μ ε(u):ε(v) + λ (∇·u)(∇·v)``, ``ε(u) = (∇u + ∇uᵀ)/2``. For the hat
  functions ``φ_a e_i`` and ``φ_b e_j`` it is (the 3x3 block of nodes ``a``, ``b``)::

      K[3a+i, 3b+j] = ∫ λ ∂_i φ_a ∂_j φ_b + μ ∂_j φ_a ∂_i φ_b + μ δ_ij ∇φ_a·∇φ_b        (1)

  constant on a P1 tet, so the integral is the tet volume times the integrand.
* The kernel of the unconstrained ``K`` is spanned by the six rigid-body modes (three translations,
  three infinitesimal rotations about the centroid), :func:`rigid_body_modes`.
* Prolongations act per component: ``P ⊗ I₃`` (:func:`block_prolongation`). A barycentric ``P`` on
  nested levels reproduces linear fields exactly, hence every rigid motion, so ``P_k ⊗ I₃`` maps the
  coarse rigid modes onto the fine ones and Galerkin products ``Pᵀ K P`` keep them in their kernel.

Pure-traction problems are handled like the Neumann constant of :class:`solvers.MultigridSolver`:
:class:`NullspaceMultigridSolver` projects right-hand sides, coarse solves and solutions orthogonal to
per-level null-space bases, and factorises the singular coarsest operator with the regularised LU.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ._threads import under_one_blas_thread
from .errors import IncompatibleRHSError, SolverError, SolverInputError
from .fem import check_tet_mesh
from .multilevel import MultigridSolver

__all__ = [
    "NullspaceMultigridSolver",
    "block_dofs",
    "block_prolongation",
    "elasticity_matrix",
    "galerkin_nullspaces",
    "lame_parameters",
    "rigid_body_modes",
]


def lame_parameters(E, nu) -> tuple[np.ndarray, np.ndarray]:
    """Lamé parameters ``(λ, μ)`` of an isotropic material.

    Parameters
    ----------
    E : float or (t,) float
        Young's modulus, > 0.
    nu : float or (t,) float
        Poisson's ratio, in (-1, 0.5).

    Returns
    -------
    lam, mu : float arrays broadcast from ``E`` and ``nu``
        ``λ = E ν / ((1 + ν)(1 - 2ν))``, ``μ = E / (2 (1 + ν))``.
    """
    E = np.asarray(E, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    if not np.all(np.isfinite(E)) or np.any(E <= 0):
        raise SolverInputError("Young's modulus E must be finite and > 0")
    if not np.all(np.isfinite(nu)) or np.any(nu <= -1.0) or np.any(nu >= 0.5):
        raise SolverInputError(
            f"Poisson's ratio must lie in (-1, 0.5), got range [{nu.min():g}, {nu.max():g}]")
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), E / (2.0 * (1.0 + nu))


def _per_tet(x, t: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0:
        return np.full(t, float(x))
    if x.shape != (t,):
        raise SolverInputError(f"{name} must be a scalar or one value per tet ({t},), got shape {x.shape}")
    return x


def _barycentric_gradients(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients ``G[e, a] = ∇φ_a`` (t, 4, 3) of the barycentric coordinates, and volumes (t,).

    With ``J = [x_1 - x_0, x_2 - x_0, x_3 - x_0]`` (columns), ``φ_{1,2,3}(x) = (J⁻¹ (x - x_0))_{1,2,3}``,
    so ``∇φ_{1,2,3}`` are the rows of ``J⁻¹`` and ``∇φ_0 = -Σ ∇φ_{1,2,3}``; ``vol = |det J| / 6``.
    """
    X = V[T]  # (t, 4, 3)
    J = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))  # (t, 3, 3), columns x_k - x_0
    Ji = np.linalg.inv(J)
    G = np.empty((len(T), 4, 3))
    G[:, 1:] = Ji
    G[:, 0] = -Ji.sum(axis=1)
    return G, np.abs(np.linalg.det(J)) / 6.0


_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _assemble_blocks(T: np.ndarray, n: int, G: np.ndarray, wl: np.ndarray, wm: np.ndarray) -> sp.csr_matrix:
    """Sum the per-tet 3x3 blocks of equation (1) into a (3n, 3n) csr matrix.

    ``G`` (t, 4, 3) are the gradients, ``wl = vol λ`` and ``wm = vol μ`` (t,). Symmetry halves the work:
    the diagonal blocks are summed per node (``bincount``, no sort), the off-diagonal ones once per tet
    edge ``{a, b}`` oriented ``a < b`` (the corner gradients are swapped where a tet lists ``b`` first,
    since ``B_qp = B_pqᵀ``), then mirrored: ``B_ba = B_abᵀ``.
    """
    Gc = np.ascontiguousarray(np.transpose(G, (1, 2, 0)))  # (4, 3, t): contiguous per corner and axis
    nodes = T.T.ravel()  # (p, e) -> T[e, p], the order of Gc[:, i].ravel()
    D = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            # diagonal block of corner p: (λ + μ) ∂_i φ_p ∂_j φ_p + μ δ_ij |∇φ_p|²
            w = (wl + wm) * Gc[:, i] * Gc[:, j] + (wm * (Gc * Gc).sum(axis=1) if i == j else 0.0)
            D[:, i, j] = D[:, j, i] = np.bincount(nodes, weights=w.ravel(), minlength=n)
    a, b = T[:, _TET_EDGES[:, 0]].T, T[:, _TET_EDGES[:, 1]].T  # (6, t) edge corners
    swap = (a > b)[:, None, :]
    GA = np.where(swap, Gc[_TET_EDGES[:, 1]], Gc[_TET_EDGES[:, 0]])  # (6, 3, t), gradient of the lower node
    GB = np.where(swap, Gc[_TET_EDGES[:, 0]], Gc[_TET_EDGES[:, 1]])
    dot = wm * (GA * GB).sum(axis=1)  # μ vol ∇φ_a·∇φ_b, (6, t)
    key, inv = np.unique(np.minimum(a, b) * np.int64(n) + np.maximum(a, b), return_inverse=True)
    inv = inv.ravel()
    m = len(key)
    U = np.empty((m, 3, 3))
    for i in range(3):
        for j in range(3):
            # equation (1) for nodes a < b: λ ∂_i φ_a ∂_j φ_b + μ ∂_j φ_a ∂_i φ_b + μ δ_ij ∇φ_a·∇φ_b
            w = wl * GA[:, i] * GB[:, j] + wm * GA[:, j] * GB[:, i] + (dot if i == j else 0.0)
            U[:, i, j] = np.bincount(inv, weights=w.ravel(), minlength=m)
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(U))):
        raise SolverInputError("elasticity matrix has NaN/inf entries (degenerate tets?)")
    lo, hi = key // n, key % n
    rows = np.concatenate([np.arange(n), lo, hi])
    cols = np.concatenate([np.arange(n), hi, lo])
    blocks = np.concatenate([D, U, np.swapaxes(U, 1, 2)])
    # block order of a row-major CSR pattern: a COO -> CSR pass whose values are the block numbers
    pat = sp.csr_matrix((np.arange(1, len(rows) + 1, dtype=np.float64), (rows, cols)), shape=(n, n))
    order = pat.data.astype(np.int64) - 1
    K = sp.bsr_matrix((blocks[order], pat.indices, pat.indptr), shape=(3 * n, 3 * n)).tocsr()
    K.sort_indices()
    return K


def elasticity_matrix(V, T, E=1.0, nu=0.3, *, check: bool = True) -> sp.csr_matrix:
    """Stiffness matrix of isotropic linear elasticity, P1 vector elements, interleaved dofs.

    Parameters
    ----------
    V : (n, 3) float
        Node positions.
    T : (t, 4) int
        Tets (any orientation).
    E : float or (t,) float
        Young's modulus, constant or per tet.
    nu : float or (t,) float
        Poisson's ratio in (-1, 0.5), constant or per tet.
    check : bool
        Validate the mesh (:func:`solvers.fem.check_tet_mesh`).

    Returns
    -------
    K : (3n, 3n) csr_matrix
        Symmetric positive semi-definite, entries (1) of the module docstring, dof ``3a + i`` =
        component ``i`` of node ``a``; ``K @ r = 0`` for every rigid-body mode ``r``.

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_mesh
    >>> V, T = kuhn_cube_mesh(2)
    >>> K = elasticity_matrix(V, T, E=1.0, nu=0.3)
    >>> K.shape, bool(abs(K @ rigid_body_modes(V)).max() < 1e-12)
    ((81, 81), True)
    """
    if check:
        V, T = check_tet_mesh(V, T)
    else:
        V = np.ascontiguousarray(V, dtype=np.float64)
        T = np.ascontiguousarray(T, dtype=np.int64)
    n, t = len(V), len(T)
    lam, mu = lame_parameters(_per_tet(E, t, "E"), _per_tet(nu, t, "nu"))
    # K scales like length in 3D (∇φ ~ 1/s, vol ~ s³): gradients on a unit-sized copy, then rescaled
    lo = V.min(axis=0)
    s = float(np.abs(V.max(axis=0) - lo).max())
    G, vol = _barycentric_gradients((V - lo) / s, T)
    wl, wm = vol * lam * s, vol * mu * s
    return _assemble_blocks(T, n, G, wl, wm)


def rigid_body_modes(V, center=None) -> np.ndarray:
    """The six rigid-body modes of a point set, interleaved dofs.

    Parameters
    ----------
    V : (n, 3) float
        Node positions.
    center : (3,) float, optional
        Centre of the rotations (default: the mean of ``V``, which keeps the six columns well scaled).

    Returns
    -------
    Z : (3n, 6) float
        Columns 0-2: unit translations along x, y, z. Columns 3-5: the infinitesimal rotations
        ``e_k × (x - c)`` about the x, y and z axes through ``c``.
    """
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise SolverInputError(f"V must be a finite (n, 3) array, got shape {V.shape}")
    c = V.mean(axis=0) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    x, y, z = (V - c).T
    Z = np.zeros((len(V), 3, 6))
    Z[:, 0, 0] = Z[:, 1, 1] = Z[:, 2, 2] = 1.0
    Z[:, 1, 3], Z[:, 2, 3] = -z, y  # e_x × r = (0, -z, y)
    Z[:, 0, 4], Z[:, 2, 4] = z, -x  # e_y × r = (z, 0, -x)
    Z[:, 0, 5], Z[:, 1, 5] = -y, x  # e_z × r = (-y, x, 0)
    return Z.reshape(3 * len(V), 6)


def block_dofs(nodes, dim: int = 3) -> np.ndarray:
    """Interleaved dof indices ``[dim a, dim a + 1, ..., dim a + dim - 1 for a in nodes]``.

    Parameters
    ----------
    nodes : (m,) int
    dim : int

    Returns
    -------
    (dim m,) int64
    """
    nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
    return (dim * nodes[:, None] + np.arange(dim)).ravel()


def block_prolongation(P, dim: int = 3) -> sp.csr_matrix:
    """Vector prolongation ``P ⊗ I_dim`` for interleaved dofs.

    Parameters
    ----------
    P : (n_f, n_c) sparse
        Nodal (scalar) prolongation.
    dim : int
        Components per node.

    Returns
    -------
    (dim n_f, dim n_c) csr_matrix
        ``(P ⊗ I)[dim a + i, dim c + j] = P[a, c] δ_ij``: each component interpolated like a scalar.
    """
    if not sp.issparse(P):
        raise SolverInputError(f"P must be a scipy sparse matrix, got {type(P).__name__}")
    Pb = sp.kron(sp.csr_matrix(P, dtype=np.float64), sp.identity(int(dim), format="csr"), format="csr")
    Pb.sort_indices()
    return Pb


def galerkin_nullspaces(Ps, candidates, *, rtol: float = 1e-8) -> list[np.ndarray]:
    """The null space of every level's Galerkin operator within the span of given candidates.

    ``ker(Pᵀ A P) = {z : P z ∈ ker A}`` for a positive semi-definite ``A``. Level ``k + 1`` keeps the
    part of ``span candidates[k+1]`` that ``Ps[k]`` carries into the kernel basis kept on level ``k``
    (level 0 keeps ``candidates[0]``): all of it when ``Ps[k]`` reproduces the candidates exactly (rigid
    modes and barycentric interpolation on nested levels: then ``candidates[k+1]`` is returned as it is),
    the translations only when the rows of fine nodes outside the coarse mesh are clamped barycentric
    weights (a ``decimate`` hierarchy), which sum to 1 but do not reproduce rotations.

    Parameters
    ----------
    Ps : list of sparse
        ``Ps[k]`` of shape ``(n_k, n_{k+1})``, e.g. :func:`block_prolongation` of nodal prolongations.
    candidates : list of (n_k, m) float arrays
        One per level, finest first (``len(Ps) + 1``), e.g. :func:`rigid_body_modes` of every level's nodes;
        ``candidates[0]`` must span (part of) the fine operator's kernel.
    rtol : float
        A direction ``c`` is kept when the part of ``Ps[k] C c`` outside the finer kernel is at most
        ``rtol ||Ps[k] C c||`` (``C`` = the candidates with unit columns).

    Returns
    -------
    list of (n_k, m_k) float arrays, ``m_k <= m``
        Finest first; ``m_k`` never grows towards the coarse levels, and may be 0 (no kernel left).

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> meshes, Ps = kuhn_cube_hierarchy(4, 2)
    >>> Pb = [block_prolongation(P) for P in Ps]
    >>> Zs = galerkin_nullspaces(Pb, [rigid_body_modes(V) for V, _ in meshes])
    >>> [Z.shape[1] for Z in Zs]   # nested levels: every rigid mode on every level
    [6, 6]
    """
    if len(candidates) != len(Ps) + 1:
        raise SolverInputError(
            f"candidates needs {len(Ps) + 1} arrays (one per level), got {len(candidates)}")
    Zs = [np.asarray(candidates[0], dtype=np.float64)]
    Q = _orthonormal(Zs[0], 0)
    for k, P in enumerate(Ps):
        C = np.asarray(candidates[k + 1], dtype=np.float64)
        if C.ndim != 2 or C.shape[0] != P.shape[1]:
            raise SolverInputError(f"candidates[{k + 1}] must have {P.shape[1]} rows, got shape {C.shape}")
        C = C / np.maximum(np.linalg.norm(C, axis=0), np.finfo(float).tiny)
        W = P @ C
        R = (W - Q @ (Q.T @ W)) / np.maximum(np.linalg.norm(W, axis=0), np.finfo(float).tiny)
        _, s, Vt = np.linalg.svd(R, full_matrices=False)
        keep = s <= rtol
        # reproduced exactly (nested levels): the caller's basis as it is
        Zs.append(np.asarray(candidates[k + 1], dtype=np.float64) if keep.all() else C @ Vt[keep].T)
        Q = _orthonormal(Zs[-1], k + 1)
    return Zs


def _orthonormal(Z: np.ndarray, level: int) -> np.ndarray:
    """An orthonormal basis of the columns of ``Z`` (none: an empty basis, a level without a kernel)."""
    Z = np.asarray(Z, dtype=np.float64)
    if Z.ndim == 2 and Z.shape[1] == 0:
        return np.zeros((Z.shape[0], 0))
    Q, R = np.linalg.qr(Z)
    d = np.abs(np.diag(R))
    if d.size == 0 or d.min() <= 1e-10 * d.max():
        raise SolverInputError(f"null-space basis of level {level} is rank-deficient")
    return Q


class _ProjectedCoarseSolve:
    """The coarsest direct solve with its input and output projected orthogonal to ``Q`` (Q orthonormal).

    The restricted residual is orthogonal to the coarse kernel up to round-off; projecting it first keeps
    the regularised LU (``(A + ε D)⁻¹``, which would amplify a kernel component by ``1/ε``) on the range,
    and projecting the output drops the arbitrary kernel part of the singular solve.
    """

    def __init__(self, solver, Q: np.ndarray):
        self._solver, self._Q = solver, Q

    def __getattr__(self, name):  # method, nnz, fallback, nullity, seconds of the wrapped solver
        return getattr(self._solver, name)

    def __call__(self, b: np.ndarray) -> np.ndarray:
        Q = self._Q
        x = self._solver(b - Q @ (Q.T @ b))
        return x - Q @ (Q.T @ x)


class NullspaceMultigridSolver(MultigridSolver):
    """:class:`solvers.MultigridSolver` for a singular operator with a known null space on every level.

    The six rigid-body modes of pure-traction elasticity are the case in mind (the constants of the
    Neumann Laplacian are ``MultigridSolver(nullspace="constant")``). The treatment is the same: with
    ``Z_k`` spanning ``ker A_k`` and ``P_k Z_{k+1} = Z_k`` (exact for rigid modes and barycentric
    prolongations on nested levels), the Galerkin operators keep ``Z_{k+1}`` in their kernel and
    restricted residuals stay orthogonal to it, ``Z_{k+1}ᵀ P_kᵀ r = Z_kᵀ r = 0``. The right-hand side is
    projected (or checked), the coarsest solve removes the kernel from its input and output
    (:class:`_ProjectedCoarseSolve`, regularised SuperLU by default), and solutions are returned
    orthogonal to ``Z_0``.

    Parameters
    ----------
    A : (n_0, n_0) sparse
        Symmetric positive semi-definite fine operator.
    Ps : list of sparse
        ``Ps[k]`` of shape ``(n_k, n_{k+1})``; every coarse unknown must be reached by a finer one
        (restrict first, :func:`solvers.restrict_prolongations`).
    nullspaces : list of (n_k, m_k) arrays
        A basis of ``ker A_k`` for every level, finest first (``len(Ps) + 1`` arrays), e.g.
        :func:`rigid_body_modes` of every level's nodes on nested levels, :func:`galerkin_nullspaces` of
        them on any (``m_k`` may then drop to 3, the translations, or 0 on coarse levels). Checked:
        ``||A_k Z_k|| <= 1e-8 ||A_k|| ||Z_k||``.
    coarse_solver : str
        As :class:`solvers.MultigridSolver`; default ``"regularized"`` (the coarsest operator is singular).
    **kwargs
        Passed to :class:`solvers.MultigridSolver` (smoothers, ``coarse``, ...); ``nullspace`` is not
        accepted.
    deflate : int
        As :class:`solvers.MultigridSolver` (slow modes deflated per probed level), default 0 here. The
        probe runs once the projected coarsest solve is installed, with its Krylov vectors kept orthogonal
        to each probed level's kernel basis (:func:`solvers.deflation.slow_modes`, ``nullspace_basis``).
    probe_finest, probe_at
        As :class:`solvers.MultigridSolver`.

    Attributes
    ----------
    nullspace_bases : list of (n_k, m) float arrays
        Orthonormal bases of the kernels, finest first.
    """

    @under_one_blas_thread  # its probe runs after MultigridSolver's set-up returns: limited here too
    def __init__(self, A, Ps, nullspaces, *, coarse_solver: str = "regularized", deflate: int = 0,
                 probe_finest: bool = False, probe_at: str = "setup", **kwargs):
        t0 = time.perf_counter()
        if "nullspace" in kwargs:
            raise SolverInputError(
                "NullspaceMultigridSolver takes its null space from nullspaces=, not nullspace=")
        Ps = list(Ps)
        if len(nullspaces) != len(Ps) + 1:
            raise SolverInputError(
                f"nullspaces needs {len(Ps) + 1} bases (one per level), got {len(nullspaces)}")
        kwargs.setdefault("ordering", None)  # the null-space bases are given in the caller's order
        # no probe yet: it must run the real cycles, with the projected coarse solve installed below
        super().__init__(A, Ps, coarse_solver=coarse_solver, deflate=0, **kwargs)
        if len(self.levels) != len(nullspaces):
            raise SolverInputError("the hierarchy was changed at set-up (unreached coarse unknowns dropped): "
                                   "restrict the prolongations first (solvers.restrict_prolongations)")
        self.nullspace_bases = []
        for k, (L, Z) in enumerate(zip(self.levels, nullspaces)):
            Z = np.asarray(Z, dtype=np.float64)
            if Z.ndim != 2 or Z.shape[0] != L.A.shape[0]:
                raise SolverInputError(f"nullspaces[{k}] must have {L.A.shape[0]} rows, got shape {Z.shape}")
            Q = _orthonormal(Z, k)
            res = float(np.abs(L.A @ Q).max()) if Q.shape[1] else 0.0
            scale = float(abs(L.A).sum(axis=1).max())  # ||A_k||_inf; Q has unit columns
            if res > 1e-8 * scale:
                hint = "; on non-nested levels pass galerkin_nullspaces(Ps, nullspaces)" if k else ""
                raise SolverError(f"nullspaces[{k}] is not in the kernel of the level-{k} operator "
                                  f"(max |A_{k} Z_{k}| = {res:.3e}, ||A_{k}|| = {scale:.3e}){hint}")
            self.nullspace_bases.append(Q)
        self._coarse_solver = _ProjectedCoarseSolve(self._coarse_solver, self.nullspace_bases[-1])
        # Krylov vectors kept off nullspace_bases[k]
        self.deflate = deflate  # no "auto" here: elasticity probes only when asked
        self._schedule_probe(deflate, probe_finest, probe_at)
        self.setup_seconds = time.perf_counter() - t0

    def _level_kernel(self, k: int) -> np.ndarray:
        return self.nullspace_bases[k]

    def __repr__(self) -> str:
        m = [Q.shape[1] for Q in self.nullspace_bases]
        what = f"{m[0]} vectors per level" if len(set(m)) == 1 else f"{' / '.join(map(str, m))} vectors"
        return super().__repr__().replace("Null space:           None", f"Null space:           {what} "
                                          "(projected)", 1)

    def _project(self, v: np.ndarray) -> np.ndarray:
        Q = self.nullspace_bases[0]
        return v - Q @ (Q.T @ v)

    def _prepare_rhs(self, b, project: bool) -> np.ndarray:
        b = super()._prepare_rhs(b, project)
        Q = self.nullspace_bases[0]
        c = Q.T @ b
        nb = float(np.linalg.norm(b))
        if not project and float(np.linalg.norm(c)) > 1e-10 * nb:
            raise IncompatibleRHSError(
                f"b has a component {np.linalg.norm(c) / nb:.2e} (relative) along the null space of A "
                "(an unbalanced load); balance it or pass project=True")
        return b - Q @ c

    def solve(self, b, *args, **kwargs):
        """:meth:`solvers.MultigridSolver.solve`; the solution is orthogonal to the null space."""
        out = super().solve(b, *args, **kwargs)
        if isinstance(out, tuple):
            return self._project(out[0]), out[1]
        return self._project(out)

    def _preconditioner(self, cycle: str) -> spla.LinearOperator:
        """One cycle from zero, input and output projected off the null space: the ``M`` of
        ``solve(accel="cg")`` and of :meth:`aspreconditioner`.

        Unprojected, the cycle's kernel part piles up in CG's search directions until ``pᵀ A p`` is
        round-off: on fandisk at 173k tets (``elasticity-free``, V-cycle) CG stopped on a "negative
        curvature" after 31 iterations at a true residual of 3.4e-6 (ν = 0.3) and 1.4e-5 (ν = 0.45);
        projected, it reaches 1e-8 in 16 and 24.
        """
        M = super()._preconditioner(cycle)

        def matvec(b):
            return self._project(M.matvec(self._project(np.asarray(b, dtype=np.float64).reshape(-1))))

        return spla.LinearOperator(M.shape, matvec=matvec, rmatvec=matvec, dtype=np.float64)
