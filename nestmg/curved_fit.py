"""The fitting energy of *Mapping Polynomial Volumes* on P2 mid-nodes, minimised by L-BFGS (scipy).

``E = E_S + λ E_Ω`` (paper eq. 1) over the free edge nodes of a patch of tets:

* ``E_Ω`` (eq. 2–3, 7): the volume-weighted mean of the Hencky distortion
  ``ε(F) = ½‖½ ln(FᵀF)‖²`` of ``F = J A⁻¹``, ``J`` the P2 map's Jacobian at quadrature points, ``A`` the
  ideal element: the straight tet itself (``reference="straight"``, energy 0 before curving) or the
  regular tet of eq. 4 with the straight tet's volume (``reference="regular"``). ``dε/dF = F⁻ᵀ H``
  (paper App. A). ``E_Ω = ∞`` where ``det F <= 0`` at a quadrature point (paper §3.4: a barrier that
  stops L-BFGS's line search), and here also where a Bernstein coefficient of ``det J`` is ``<= 0``:
  every iterate is a certified mesh.
* ``E_S`` (eq. 9, point-to-plane): the mean of ``(n·(x − p) / h)²`` over the free boundary nodes, ``p``
  the closest surface point, ``n`` the surface normal there, ``h`` the edge's length; planes are
  refreshed between L-BFGS rounds, so boundary nodes slide along the surface.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from solvers.fem_p2 import det3, inv3, p2_basis, p2_jacobians, tet_quadrature

from .curved import _bernstein_change, jacobian_bernstein
from .errors import NestmgInputError

__all__ = ["A_TET", "FitResult", "fit_mid_nodes", "hencky_energy", "jacobian_spread_energy", "relax_interior"]

#: Ideal (regular, unit-edge) tet of the paper's eq. 4: columns map the reference tet's edges.
A_TET = np.array([[1.0, 0.5, 0.5], [0.0, np.sqrt(3) / 2, np.sqrt(3) / 6], [0.0, 0.0, np.sqrt(2.0 / 3.0)]])


def reference_inverse(V: np.ndarray, T: np.ndarray, reference: str = "straight") -> np.ndarray:
    """``A⁻¹`` per tet (t,3,3): the straight tet's own Jacobian, or eq. 4's regular tet (same volume)."""
    P = np.asarray(V, dtype=np.float64)[np.asarray(T)]
    Js = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)  # (t,3,3)
    if reference == "straight":
        return np.linalg.inv(Js)
    if reference == "regular":
        s = np.cbrt(np.linalg.det(Js) / np.linalg.det(A_TET))
        return np.linalg.inv(s[:, None, None] * A_TET[None])
    raise NestmgInputError(f"reference must be 'straight' or 'regular', got {reference!r}")


def hencky_energy(X: np.ndarray, T10: np.ndarray, Ainv: np.ndarray, *, degree: int = 3,
                  gradient: bool = True, weighting: str = "volume",
                  deviatoric: bool = False) -> tuple[float, np.ndarray | None]:
    """Volume-weighted mean Hencky distortion of P2 tets and its gradient with respect to ``X``.

    Parameters
    ----------
    X : (N,3) float array
    T10 : (t,10) int array
    Ainv : (t,3,3) float array
        Inverse ideal-element Jacobians (:func:`reference_inverse`).
    weighting : {"volume", "element"}
        ``"volume"``: the integral of eq. 7 over the patch divided by its volume (large tets dominate);
        ``"element"``: the mean over tets of each tet's own mean distortion (every tet counts alike:
        the quality pass, where the worst tets are the small ones).
    deviatoric : bool
        Only the deviatoric part ``½‖H − (tr H / 3) I‖²`` of the Hencky distortion: shape, not volume
        (``tr H = ln det F``).

    Returns
    -------
    E : float
        ``Σ_t Σ_q w_q |det A_t| ε(J A⁻¹) / Σ_t |A_t| / 6`` (eq. 7); ``inf`` if some ``det F <= 0``.
    G : (N,3) float array or None
        ``∂E/∂X`` (eq. 8), zero where ``E`` is infinite.
    """
    pts, w = tet_quadrature(degree)
    _, dN = p2_basis(pts)
    F = np.einsum("tqdk,tkl->tqdl", p2_jacobians(X, T10, dN), Ainv, optimize=True)  # F = J A⁻¹
    if np.any(det3(F) <= 0):
        return np.inf, (np.zeros_like(X) if gradient else None)
    mu, Q = np.linalg.eigh(np.einsum("tqki,tqkj->tqij", F, F, optimize=True))  # C = FᵀF
    lg = 0.5 * np.log(mu)  # eigenvalues of H = ln U
    if deviatoric:  # d/dF ½‖dev H‖² = F⁻ᵀ dev H: the same formula below with dev H's eigenvalues
        lg = lg - lg.mean(axis=2, keepdims=True)
    wq = _quadrature_weights(w, np.abs(1.0 / det3(Ainv)), weighting)
    E = float(wq.ravel() @ (0.5 * (lg**2).sum(axis=2)).ravel())  # ε = ½‖H‖²
    if not gradient:
        return E, None
    # dε/dF = F⁻ᵀH (App. A) = F C⁻¹ H = F Q diag(lg / μ) Qᵀ: no inverse needed
    S = np.einsum("tqik,tqk,tqjk->tqij", Q, wq[..., None] * lg / mu, Q, optimize=True)
    dJ = np.einsum("tqdk,tqkl,tml->tqdm", F, S, Ainv, optimize=True)  # ∂/∂J = ∂/∂F A⁻ᵀ
    g = np.einsum("tqdk,qak->tad", dJ, dN, optimize=True)
    G = np.zeros_like(X)
    np.add.at(G, T10, g)
    return E, G


def _quadrature_weights(w: np.ndarray, vol: np.ndarray, weighting: str) -> np.ndarray:
    """(t,q) weights of eq. 7: by tet volume (the integral / the patch volume), or every tet alike."""
    if weighting == "volume":
        return w[None, :] * vol[:, None] / (vol.sum() / 6.0)
    if weighting == "element":
        return np.broadcast_to(6.0 * w[None, :] / len(vol), (len(vol), len(w)))
    raise NestmgInputError(f"weighting must be 'volume' or 'element', got {weighting!r}")


class FitResult(dict):
    """Figures of one :func:`fit_mid_nodes` run (a dict: ``rounds``, ``iterations``, ``energy``, ...)."""


def fit_mid_nodes(X: np.ndarray, T10: np.ndarray, Ainv: np.ndarray, free: np.ndarray, bnd: np.ndarray,
                  h: np.ndarray, project, *, lam: float = 0.05, rounds: int = 4, maxiter: int = 200,
                  weighting: str = "volume") -> tuple[np.ndarray, FitResult]:
    """Minimise ``E_S + λ E_Ω`` over the nodes ``free`` of the tets ``T10`` (a patch), L-BFGS.

    Parameters
    ----------
    X : (N,3) float array
        All node positions; the patch must be valid (finite energy) at the start.
    T10 : (t,10) int array
        The tets whose energy counts: every tet containing a free node.
    Ainv : (t,3,3) float array
        Their ideal elements (:func:`reference_inverse`).
    free : (m,) int array
        Nodes moved.
    bnd : (m,) bool array
        Which free nodes are on the boundary (fitted to the surface).
    h : (m,) float array
        Length scale of each free node (its edge's length).
    project : callable
        Closest points and normals on the target surface (:data:`nestmg.curved.Projector`).
    lam : float
        Weight λ of the volume energy (paper: 0.05 for the close fit).
    rounds : int
        L-BFGS runs, each with the point-to-plane targets refreshed at the current positions.
    maxiter : int
        L-BFGS iterations per round.
    weighting : {"volume", "element"}
        How tets are weighted in ``E_Ω`` (:func:`hencky_energy`).

    Returns
    -------
    X : (N,3) float array
        Moved copy.
    FitResult
    """
    X = np.array(X, dtype=np.float64)
    free = np.asarray(free, dtype=np.int64)
    bidx = free[bnd]
    hb = np.asarray(h)[bnd]
    nb = max(1, len(bidx))
    info = FitResult(rounds=0, iterations=0, energy=[], fit_rms=[])
    # variables scaled by a tenth of each node's edge: L-BFGS's first step then moves nodes by ~0.1 h
    scale = np.repeat(0.1 * np.asarray(h, dtype=np.float64), 3)
    for _ in range(rounds):
        p, n = project(X[bidx]) if len(bidx) else (np.zeros((0, 3)), np.zeros((0, 3)))
        x0 = X[free].ravel().copy()

        def energy(y):
            X[free] = (x0 + scale * y).reshape(-1, 3)
            Ev, Gv = hencky_energy(X, T10, Ainv, weighting=weighting)
            if not np.isfinite(Ev) or jacobian_bernstein(X, T10)[0].min() <= 0:  # barrier: certified only
                return np.inf, np.zeros_like(y)
            d = np.einsum("ij,ij->i", n, X[bidx] - p) / hb  # eq. 9, point-to-plane
            G = lam * Gv
            G[bidx] += (2.0 / nb) * (d / hb)[:, None] * n
            return float(d @ d / nb + lam * Ev), G[free].ravel() * scale

        r = minimize(energy, np.zeros_like(x0), jac=True, method="L-BFGS-B",
                     options={"maxiter": maxiter, "gtol": 1e-10, "ftol": 1e-15})
        X[free] = (x0 + scale * r.x).reshape(-1, 3)
        if not np.isfinite(r.fun):  # cannot happen from a valid start; keep the start then
            X[free] = x0.reshape(-1, 3)
        info.setdefault("messages", []).append(str(r.message))
        info["rounds"] += 1
        info["iterations"] += int(r.nit)
        info["energy"].append(float(r.fun))
        info["fit_rms"].append(float(np.sqrt(np.mean(
            (np.linalg.norm(project(X[bidx])[0] - X[bidx], axis=1) / hb) ** 2))) if len(bidx) else 0.0)
    return X, info



def jacobian_spread_energy(X: np.ndarray, T10: np.ndarray, Ainv: np.ndarray, *,
                           beta: float = 0.1) -> tuple[float, np.ndarray]:
    """How far ``det J`` of P2 tets is from constant on each tet, plus ``beta`` times their shape distortion.

    The Hencky strain of the paper (eq. 2–3) split into its volumetric part ``tr H = ln det F`` and its
    deviatoric part. The volumetric part is measured against each tet's *own* mean instead of the
    straight tet: curving a boundary tet must change its volume, but not evenly is what lowers its
    scaled Jacobian. It is taken on the 20 Bernstein coefficients ``c`` of ``det J``
    (:func:`nestmg.curved.jacobian_bernstein`), whose ratio ``min c / max c`` is the certified scaled
    Jacobian: per tet the variance of ``ln c``. The deviatoric part (:func:`hencky_energy` with
    ``deviatoric=True``, ideal element ``Ainv``) keeps the tets' shape. Both are means over tets.

    Parameters
    ----------
    X : (N,3) float array
    T10 : (t,10) int array
    Ainv : (t,3,3) float array
        Inverse ideal-element Jacobians (:func:`reference_inverse`).
    beta : float
        Weight of the deviatoric Hencky distortion.

    Returns
    -------
    E : float
        ``inf`` if some Bernstein coefficient is ``<= 0`` (not certified: a barrier).
    G : (N,3) float array
        ``∂E/∂X`` (zero where ``E`` is infinite).
    """
    A, Binv = _bernstein_change()
    _, dN = p2_basis((A / 3.0)[:, 1:])
    J = p2_jacobians(X, T10, dN)  # at the degree-3 lattice points (t,20,3,3)
    d = det3(J)
    c = d @ Binv.T
    if np.any(c <= 0):
        return np.inf, np.zeros_like(X)
    lc = np.log(c)
    dev = lc - lc.mean(axis=1, keepdims=True)
    E = float((dev**2).mean(axis=1).sum() / len(T10))
    gd = (2.0 * dev / (c.shape[1] * c * len(T10))) @ Binv  # ∂E/∂det J at the lattice points
    gJ = (gd * d)[..., None, None] * np.swapaxes(inv3(J, d), -1, -2)  # ∂det J/∂J = det J · J⁻ᵀ
    G = np.zeros_like(X)
    np.add.at(G, T10, np.einsum("tpdk,pak->tad", gJ, dN, optimize=True))
    if beta:
        Ed, Gd = hencky_energy(X, T10, Ainv, weighting="element", deviatoric=True)
        E, G = E + beta * Ed, G + beta * Gd
    return E, G


def relax_interior(X: np.ndarray, T10: np.ndarray, Ainv: np.ndarray, free: np.ndarray, h: np.ndarray, *,
                   beta: float = 0.1, maxiter: int = 500) -> tuple[np.ndarray, FitResult]:
    """Minimise :func:`jacobian_spread_energy` over the (interior) nodes ``free`` of a patch, L-BFGS.

    The boundary nodes stay where they are (on the surface), so the fit is untouched; every iterate is
    certified (the energy is infinite otherwise). Parameters as :func:`fit_mid_nodes`.

    Returns
    -------
    X : (N,3) float array
        Moved copy.
    FitResult
        ``iterations``, ``energy`` (start, end), ``message``.
    """
    X = np.array(X, dtype=np.float64)
    free = np.asarray(free, dtype=np.int64)
    x0 = X[free].ravel().copy()
    scale = np.repeat(0.1 * np.asarray(h, dtype=np.float64), 3)  # as in fit_mid_nodes

    def energy(y):
        X[free] = (x0 + scale * y).reshape(-1, 3)
        E, G = jacobian_spread_energy(X, T10, Ainv, beta=beta)
        return E, G[free].ravel() * scale

    e0 = energy(np.zeros_like(x0))[0]
    r = minimize(energy, np.zeros_like(x0), jac=True, method="L-BFGS-B",
                 options={"maxiter": maxiter, "gtol": 1e-12, "ftol": 1e-15})
    X[free] = (x0 + scale * r.x).reshape(-1, 3)
    if not np.isfinite(r.fun) or r.fun > e0:  # cannot happen from a certified start; keep the start then
        X[free] = x0.reshape(-1, 3)
    return X, FitResult(iterations=int(r.nit), energy=[float(e0), float(r.fun)], message=str(r.message))
