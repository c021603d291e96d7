"""Re-inflation energies E(F, Ĉ, C) of the cage (paper Sec. 3.2, Eqs. 11-15).

Each energy is a small object holding its reused state (rest cage, Laplacian, tet mesh) with

* ``value(C) -> float``
* ``gradient(C) -> (nc,3)``
* ``metric(C) -> (3nc,3nc) csr``: a symmetric positive definite matrix used as the Hessian (exact
  for ``step``, the ARAP "global step" matrix for the ARAP energies, a proximal identity for
  ``volume``, whose true Hessian is indefinite), in ipctk's row-major DOF order
  ``[x0, y0, z0, x1, ...]``;
* ``begin_step(C)``: called at the start of every reverse time step (``step`` remembers C(t)).

:func:`make_energy` builds one by name: ``"step"``, ``"volume"``, ``"surface_arap"``,
or ``"volumetric_arap"`` (``"symmetry"`` is not implemented).

License: ``"volumetric_arap"`` tessellates the cage with TetGen (the ``tetgen`` package, AGPL-3.0). It is
a copyleft opt-in: TetGen is imported only when that energy is asked for by name, and a missing package
raises :class:`cagegen.BackendUnavailableError` naming the extra (``pip install "nestmg[tetgen]"``).
"""

from __future__ import annotations

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg  # noqa: F401  (sp.linalg.splu)

from ..errors import CageError, CageOptionError

__all__ = [
    "COPYLEFT_ENERGIES",
    "ENERGIES",
    "StepEnergy",
    "SurfaceARAPEnergy",
    "VolumeEnergy",
    "VolumetricARAPEnergy",
    "make_energy",
    "signed_volume",
]


def signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Enclosed volume of a closed, outward-oriented triangle mesh: Σ_f det(a, b, c) / 6 (Eq. 13)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _kron3(M: sp.spmatrix) -> sp.csr_matrix:
    """Expand an (n,n) scalar operator to (3n,3n) on row-major xyz DOFs."""
    return sp.kron(M, sp.identity(3), format="csr")


class StepEnergy:
    """E_step = ½ ‖C(t+∆t) − C(t)‖² (Eq. 12): move the cage as little as possible."""

    name = "step"

    def __init__(self, Vc_rest: np.ndarray, Fc: np.ndarray):
        self.prev = np.array(Vc_rest, dtype=float)
        self._M = sp.identity(3 * len(Vc_rest), format="csr")

    def begin_step(self, C: np.ndarray) -> None:
        self.prev = np.array(C, dtype=float)

    def value(self, C: np.ndarray) -> float:
        return 0.5 * float(np.sum((C - self.prev) ** 2))

    def gradient(self, C: np.ndarray) -> np.ndarray:
        return C - self.prev

    def metric(self, C: np.ndarray) -> sp.csr_matrix:
        return self._M


class VolumeEnergy:
    """E_vol = Vol(C) = ∫ x·n dA / 3 (Eq. 13); ∇E_vol = area-weighted vertex normals / 3.

    The Hessian of the volume is indefinite, so the metric is the lumped mass matrix (each vertex's
    third of its triangles' areas), scaled so that an unconstrained step moves the fastest vertex by
    ``max_move`` (a fraction of the cage's bounding-box diagonal): the L2 gradient flow, in which
    every vertex moves along its normal at about the same speed whatever the size of its triangles,
    the barrier Hessian added by the caller slowing down the vertices in contact. (A scaled identity
    moved each vertex in proportion to its area: on decimated cages, whose triangles differ in size
    by orders of magnitude, the small ones crawled: lucy.ply's first cage took 42 final iterations
    against 16 and ended looser, in one run; CPU seconds in ``benchmarks/results/cages/ab_massmetric_*.json``.)
    """

    name = "volume"

    def __init__(self, Vc_rest: np.ndarray, Fc: np.ndarray, max_move: float = 5e-3):
        self.F = np.asarray(Fc, dtype=np.int64)
        self.n = len(Vc_rest)
        self.max_move = max_move * float(np.linalg.norm(np.ptp(Vc_rest, axis=0)))

    def begin_step(self, C: np.ndarray) -> None:
        pass

    def value(self, C: np.ndarray) -> float:
        return signed_volume(C, self.F)

    def gradient(self, C: np.ndarray) -> np.ndarray:
        a, b, c = C[self.F[:, 0]], C[self.F[:, 1]], C[self.F[:, 2]]
        G = np.zeros_like(C)
        # d det(a,b,c)/da = b × c, and cyclically
        np.add.at(G, self.F[:, 0], np.cross(b, c))
        np.add.at(G, self.F[:, 1], np.cross(c, a))
        np.add.at(G, self.F[:, 2], np.cross(a, b))
        return G / 6.0

    def metric(self, C: np.ndarray) -> sp.csr_matrix:
        a, b, c = C[self.F[:, 0]], C[self.F[:, 1]], C[self.F[:, 2]]
        fa = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        area = np.bincount(self.F.ravel(), weights=np.repeat(fa / 3.0, 3), minlength=self.n)
        area = np.maximum(area, 1e-12 * max(float(area.max()), 1e-300))
        speed = np.linalg.norm(self.gradient(C), axis=1) / area
        scale = max(float(speed.max()), 1e-300) / self.max_move
        return sp.diags(np.repeat(area * scale, 3), format="csr")


def _fit_rotations(S: np.ndarray) -> np.ndarray:
    """Closest rotations R_k (k,3,3) maximising tr(R S_k) (polar decomposition via batched SVD)."""
    U, _, Vt = np.linalg.svd(S)
    R = np.einsum("kji,klj->kil", Vt, U)  # R = V Uᵀ
    det = np.linalg.det(R)
    flip = det < 0
    if np.any(flip):
        Vt2 = Vt[flip].copy()
        Vt2[:, 2, :] *= -1
        R[flip] = np.einsum("kji,klj->kil", Vt2, U[flip])
    return R


class SurfaceARAPEnergy:
    """Surface ("spokes") ARAP, Eq. 14: E = ½ Σ_i Σ_{j∈N(i)} w_ij ‖e_ij − R_i ê_ij‖².

    ``w_ij`` are the cotangent weights of the rest cage Ĉ (clamped to be positive so the metric
    2L stays positive definite), ``R_i`` the best-fit rotations (local step); with the rotations
    fixed the gradient is ``2 L C − b`` (global step), so ``2L`` is the metric.
    """

    name = "surface_arap"

    def __init__(self, Vc_rest: np.ndarray, Fc: np.ndarray):
        R0 = np.asarray(Vc_rest, dtype=float)
        F = np.asarray(Fc, dtype=np.int64)
        self.n = len(R0)
        Lc = -igl.cotmatrix(R0, F).tocoo()  # positive semi-definite cot Laplacian
        off = Lc.row != Lc.col
        i, j, w = Lc.row[off], Lc.col[off], -Lc.data[off]  # w_ij = ½(cot α + cot β)
        w = np.maximum(w, 1e-3 * np.abs(w).mean())
        self._set_edges(R0, i, j, w)

    def _set_edges(self, R0: np.ndarray, i: np.ndarray, j: np.ndarray, w: np.ndarray) -> None:
        self.i, self.j, self.w = i, j, w  # directed pairs (both orientations present)
        self.rest_e = R0[i] - R0[j]
        n = self.n
        W = sp.csr_matrix((w, (i, j)), shape=(n, n))
        L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
        eps = 1e-6 * float(L.diagonal().mean())
        self._M = _kron3(2.0 * L + eps * sp.identity(n))

    def begin_step(self, C: np.ndarray) -> None:
        pass

    def _rotations(self, C: np.ndarray) -> np.ndarray:
        e = C[self.i] - C[self.j]
        S = np.zeros((self.n, 3, 3))
        np.add.at(S, self.i, self.w[:, None, None] * np.einsum("ka,kb->kab", self.rest_e, e))
        return _fit_rotations(S)

    def value(self, C: np.ndarray) -> float:
        R = self._rotations(C)
        r = (C[self.i] - C[self.j]) - np.einsum("kab,kb->ka", R[self.i], self.rest_e)
        return 0.5 * float(self.w @ np.sum(r * r, axis=1))

    def gradient(self, C: np.ndarray) -> np.ndarray:
        R = self._rotations(C)
        e = C[self.i] - C[self.j]
        Re = np.einsum("kab,kb->ka", R[self.i] + R[self.j], self.rest_e)
        G = np.zeros_like(C)
        np.add.at(G, self.i, self.w[:, None] * (2.0 * e - Re))
        return G

    def metric(self, C: np.ndarray) -> sp.csr_matrix:
        return self._M


class VolumetricARAPEnergy(SurfaceARAPEnergy):
    """Volumetric ARAP, Eq. 15, on a TetGen tessellation of the rest cage Ĉ.

    The tet mesh (boundary kept: its first nc nodes are Ĉ's vertices, ``pYq`` switches) adds
    interior nodes. They are not collision DOFs: for a cage C the energy is minimised over the
    interior nodes by local-global iterations warm-started from the previous call (the paper's
    "optimize for the interior while holding the boundary fixed"), so E(C) = min_interior E and, by
    the envelope theorem, its gradient is the boundary part of the full ARAP gradient. The metric is
    the boundary block of 2L (L: cotangent Laplacian of the tet mesh, weights clamped positive).
    Rotations are per node over the tet-mesh edges (spokes).
    """

    name = "volumetric_arap"

    def __init__(self, Vc_rest: np.ndarray, Fc: np.ndarray, inner_iters: int = 3):
        check_energy_available(self.name)
        import tetgen  # AGPL-3.0: loaded only for this energy, asked for by name

        R0 = np.asarray(Vc_rest, dtype=float)
        nodes, T = tetgen.TetGen(R0, np.asarray(Fc, dtype=np.int64)).tetrahedralize(switches="pYq1.5Q")[:2]
        nodes = np.asarray(nodes, dtype=float)
        if not np.array_equal(nodes[: len(R0)], R0):
            raise CageError("TetGen reordered or moved the cage vertices")
        self.nb = len(R0)
        self.n = len(nodes)
        self.T = np.asarray(T, dtype=np.int64)
        Lc = -igl.cotmatrix(nodes, self.T).tocoo()
        off = Lc.row != Lc.col
        i, j, w = Lc.row[off], Lc.col[off], -Lc.data[off]
        w = np.maximum(w, 1e-3 * np.abs(w).mean())
        self._set_edges(nodes, i, j, w)
        self.interior = nodes[self.nb :].copy()
        self.inner_iters = inner_iters
        M = self._M.tocsr()
        nb3 = 3 * self.nb
        self._Mbb = M[:nb3, :nb3].tocsr()
        self._Mii = M[nb3:, nb3:].tocsc()
        self._Mib = M[nb3:, :nb3].tocsr()
        self._Mii_lu = sp.linalg.splu(self._Mii) if self.n > self.nb else None

    def _full(self, C: np.ndarray) -> np.ndarray:
        """Boundary C plus interior nodes relaxed by local-global iterations (warm start)."""
        X = np.vstack([C, self.interior])
        if self._Mii_lu is None:
            return X
        nb3 = 3 * self.nb
        for _ in range(self.inner_iters):
            G = SurfaceARAPEnergy.gradient(self, X).ravel()
            # global step on the interior with the rotations of X fixed: M_ii x_i = M_ii x_i - g_i
            rhs = self._Mii @ X[self.nb :].ravel() - G[nb3:]
            X[self.nb :] = self._Mii_lu.solve(rhs).reshape(-1, 3)
        self.interior = X[self.nb :].copy()
        return X

    def value(self, C: np.ndarray) -> float:
        return SurfaceARAPEnergy.value(self, self._full(C))

    def gradient(self, C: np.ndarray) -> np.ndarray:
        return SurfaceARAPEnergy.gradient(self, self._full(C))[: self.nb]

    def metric(self, C: np.ndarray) -> sp.csr_matrix:
        return self._Mbb


#: Energies that load copyleft code: name -> (module, what it is, extra that installs it).
COPYLEFT_ENERGIES = {"volumetric_arap": ("tetgen", "TetGen (AGPL-3.0)", "tetgen")}


def check_energy_available(name: str) -> None:
    """Raise :class:`cagegen.BackendUnavailableError` if energy ``name`` needs a package that is absent.

    Checked before any work (without importing the package), so a long flow does not end in an
    ImportError. Only the copyleft energies (:data:`COPYLEFT_ENERGIES`) have such a dependency.
    """
    import importlib.util

    from ..errors import BackendUnavailableError

    if name in COPYLEFT_ENERGIES:
        module, what, extra = COPYLEFT_ENERGIES[name]
        if importlib.util.find_spec(module) is None:
            raise BackendUnavailableError(
                f"energy={name!r} loads {what}, a copyleft opt-in, and the {module!r} package is not installed: "
                f'pip install "nestmg[{extra}]"'
            )


ENERGIES = {
    "step": StepEnergy,
    "volume": VolumeEnergy,
    "surface_arap": SurfaceARAPEnergy,
    "volumetric_arap": VolumetricARAPEnergy,
}


def make_energy(name: str, Vc_rest: np.ndarray, Fc: np.ndarray, **kw):
    """Build the energy ``name`` for the rest cage ``(Vc_rest, Fc)``.

    Parameters
    ----------
    name : str
        One of :data:`ENERGIES`.
    Vc_rest : (nc,3) float array
        Rest (decimated) cage Ĉ.
    Fc : (mc,3) int array
        Cage triangles.

    Returns
    -------
    energy object (see the module docstring)
    """
    if name not in ENERGIES:
        raise CageOptionError(f"unknown re-inflation energy {name!r}; choose one of {sorted(ENERGIES)}")
    return ENERGIES[name](Vc_rest, Fc, **kw)
