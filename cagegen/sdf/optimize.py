"""Step 3 of the ``sdf`` backend: barrier-protected vertex relocation and edge flips.

Qiu, Liao, Chen (2024), Sec. 3.3. The cage ``C`` (the fine surface ``M`` is a static obstacle)
minimises

    E(C) = w_s * sum_v A_v (xi(v) - h)^2 / (A h_ref^2)         cage spacing ("tightness"), paper Sec. 3.3
         + w_q * sum_f A_f (MIPS_f - 2) / A                  element quality, MIPS w.r.t. equilateral
         + B(C)                                              IPC barrier (eq. 7, ipctk)

by gradient descent with a line search whose largest step is the collision-free fraction given by
continuous collision detection (ipctk's additive CCD): every accepted step keeps the cage free of
self-intersections and off the input, as the paper requires. ``xi(v)`` is the exact distance of a
cage vertex to ``M`` (``igl.point_mesh_squared_distance``), ``A_v`` a third of the incident area.
We relocate all vertices at once (the paper moves one vertex at a time); the barrier set ``C`` of
eq. 7 is ipctk's normal-collision set of cage-cage and cage-input pairs within ``dhat``.

Edge flips (paper: "where they lower the energy") are applied between descent rounds to edges
whose flip lowers the two triangles' share of ``E`` (spacing at their corners and centroids + MIPS;
a flip judged by angles alone can bridge a concavity and move the cage away from the input), only
when the flipped pair passes the same exact intersection tests (:mod:`cagegen.intersect`).
"""

from __future__ import annotations

import time

import ipctk
import numpy as np

from .._geometry import segment_segment_sqdist
from ..errors import CageError, CageOptionError
from ..intersect import cross_pairs, self_pairs
from ..collision import PairMesh
from .simplify import too_close

__all__ = ["mips", "optimize_cage"]

_SQ3 = np.sqrt(3.0)


def mips(V: np.ndarray, F: np.ndarray, grad: bool = False):
    """MIPS energy of each triangle w.r.t. an equilateral reference: ``sum |e|^2 / (2 sqrt3 A)``
    (2 for an equilateral triangle, growing without bound as it degenerates). With ``grad=True``
    also the per-corner gradients (m,3,3)."""
    X = V[F]
    e = [X[:, 2] - X[:, 1], X[:, 0] - X[:, 2], X[:, 1] - X[:, 0]]  # edge opposite corner k
    s = sum(np.einsum("ij,ij->i", x, x) for x in e)
    N = np.cross(e[2], -e[1])
    A2 = np.linalg.norm(N, axis=1)
    A = 0.5 * A2
    m = s / (2 * _SQ3 * np.maximum(A, 1e-300))
    if not grad:
        return m
    n = N / np.maximum(A2, 1e-300)[:, None]
    G = np.empty_like(X)
    for k in range(3):
        # d s / d x_k = 2 (x_k - x_{k+1}) + 2 (x_k - x_{k-1});  d A / d x_k = 0.5 n x e_k
        ds = 2 * (X[:, k] - X[:, (k + 1) % 3]) + 2 * (X[:, k] - X[:, (k + 2) % 3])
        dA = 0.5 * np.cross(n, e[k])
        G[:, k] = (ds * A[:, None] - s[:, None] * dA) / (2 * _SQ3 * np.maximum(A, 1e-300)[:, None] ** 2)
    return m, G


def _min_angles(V, F):
    X = V[F]
    out = []
    for k in range(3):
        u = X[:, (k + 1) % 3] - X[:, k]
        w = X[:, (k + 2) % 3] - X[:, k]
        c = np.einsum("ij,ij->i", u, w) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        out.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.min(np.stack(out, 1), axis=1)


def _barycentric(Q, A, B, C):
    """Barycentric coordinates (k,3) of points ``Q`` lying on the triangles ``(A, B, C)`` (clipped to the
    triangle: ``Q`` comes from a closest-point query, so it is on it up to rounding)."""
    v0, v1, v2 = B - A, C - A, Q - A
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1e-300)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    L = np.clip(np.c_[1.0 - v - w, v, w], 0.0, 1.0)
    return L / np.maximum(L.sum(axis=1, keepdims=True), 1e-300)


class _Energy:
    def __init__(self, Fc, Vin, Fin, h, w_s, w_q, h_ref, w_p=0.0, t_pull=None, h_local=None, pull_mask=None):
        import igl

        # local spacing target (not in the paper): (points, h_loc, radius) -> the target at a point whose
        # closest input point is at distance s from the nearest of ``points`` is
        # h + (h_loc - h) exp(-(s / radius)^2) (held fixed in the gradient: it varies on the scale radius)
        self.h_local = None
        if h_local is not None and len(h_local[0]):
            from scipy.spatial import cKDTree

            self.h_local = (cKDTree(np.asarray(h_local[0], dtype=float)), float(h_local[1]), float(h_local[2]))
        self.igl = igl
        self.Fc, self.Vin, self.Fin = Fc, Vin, Fin
        # the input's AABB tree, built once (igl.point_mesh_squared_distance rebuilds it per call: about
        # half of a query's time on a 5k-face input)
        self._Vin = np.ascontiguousarray(Vin, dtype=np.float64)
        self._Fin = np.ascontiguousarray(Fin, dtype=np.int64)
        self._tree = igl.AABB()
        self._tree.init(self._Vin, self._Fin)
        self.h, self.w_s, self.w_q, self.h_ref = h, w_s, w_q, h_ref
        # input-to-cage pull (not in the paper): input vertices farther than t_pull from the cage (a
        # concavity the offset bridged) pull the closest cage point toward them
        self.w_p = float(w_p)
        self.t_pull = t_pull
        if self.w_p > 0:
            X = Vin[Fin]
            Ain = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)
            a = np.zeros(len(Vin))
            for k in range(3):
                np.add.at(a, Fin[:, k], Ain / 3)
            self.a_in = a / float(Ain.sum())
        # the input vertices that pull (all by default); the others are ignored by the pull term
        self.pull_idx = np.arange(len(Vin)) if pull_mask is None else np.flatnonzero(pull_mask)

    def to_input(self, P):
        """Squared distances, closest input faces and closest points of the query points ``P``."""
        return self._tree.squared_distance(self._Vin, self._Fin, np.ascontiguousarray(P, dtype=np.float64))

    def target(self, P):
        """Spacing target at query points whose closest input points are ``P``."""
        if self.h_local is None:
            return self.h
        tree, hl, rad = self.h_local
        s = tree.query(P, distance_upper_bound=4 * rad)[0]
        return self.h + (hl - self.h) * np.where(np.isfinite(s), np.exp(-np.minimum(s / rad, 4.0) ** 2), 0.0)

    def pull(self, C, grad=False):
        """``w_p * sum_i a_i (d_i - t)_+^2 / h_ref^2``, ``d_i`` the distance of input vertex ``i`` to the cage,
        ``a_i`` its share of the input's area; the gradient moves the closest cage point's corners
        (barycentric weights held fixed) toward the input vertex."""
        idx = self.pull_idx
        if self.w_p <= 0 or len(idx) == 0:
            return (0.0, np.zeros_like(C)) if grad else 0.0
        d2, fi, Q = self.igl.point_mesh_squared_distance(self.Vin[idx], C, self.Fc)
        d = np.sqrt(d2)
        ex = np.maximum(d - self.t_pull, 0.0)
        a_in = self.a_in[idx]
        e = self.w_p * float(np.sum(a_in * ex * ex)) / self.h_ref ** 2
        if not grad:
            return e
        g = np.zeros_like(C)
        on = np.flatnonzero(ex > 0)
        if len(on):
            T = self.Fc[fi[on]]
            L = _barycentric(Q[on], C[T[:, 0]], C[T[:, 1]], C[T[:, 2]])
            u = (Q[on] - self.Vin[idx[on]]) / np.maximum(d[on], 1e-300)[:, None]  # d d_i / d q
            coef = (self.w_p * 2 * a_in[on] * ex[on] / self.h_ref ** 2)[:, None] * u
            for k in range(3):
                np.add.at(g, T[:, k], L[:, k:k + 1] * coef)
        return e, g

    def triangles(self, C):
        """Per-triangle share of the energy (spacing at the corners and centroid + MIPS), up to the
        common normalisation, as a function of the triangles ``T`` (k,3) of the cage ``C``: what an
        edge flip changes."""
        d2v, _, Pv = self.to_input(C)
        rv = np.sqrt(d2v) - self.target(Pv)

        def e(T):
            X = C[T]
            A = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)
            d2c, _, Pc = self.to_input(X.mean(axis=1))
            rc = np.sqrt(d2c) - self.target(Pc)
            spacing = (rv[T] ** 2).sum(axis=1) / 6 + 0.5 * rc ** 2
            return A * (self.w_s * spacing / self.h_ref ** 2 + self.w_q * (mips(C, T) - 2.0))
        return e

    def __call__(self, C, grad=False):
        Fc = self.Fc
        X = C[Fc]
        A = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)
        At = float(A.sum())
        # spacing integral by a vertex + centroid rule: half the weight at the corners, half at the centroid
        Av = np.zeros(len(C))
        for k in range(3):
            np.add.at(Av, Fc[:, k], A / 6)
        cen = X.mean(axis=1)
        Q = np.vstack([C, cen])
        w = np.r_[Av, 0.5 * A]
        d2, _, P = self.to_input(Q)
        d = np.sqrt(d2)
        r = d - self.target(P)
        Es = self.w_s * float(np.sum(w * r * r)) / (At * self.h_ref ** 2)
        if grad:
            m, Gm = mips(C, Fc, grad=True)
        else:
            m = mips(C, Fc)
        Eq = self.w_q * float(np.sum(A * (m - 2.0))) / At
        if not grad:
            return Es + Eq + self.pull(C)
        u = (Q - P) / np.maximum(d, 1e-300)[:, None]
        gq = (self.w_s * 2 * w * r / (At * self.h_ref ** 2))[:, None] * u  # area weights held fixed
        g = gq[: len(C)].copy()
        for k in range(3):
            np.add.at(g, Fc[:, k], gq[len(C):] / 3)
        # d(A_f (m_f - 2)) = A_f dm_f + (m_f - 2) dA_f; the dA term is dropped (quality, not area)
        for k in range(3):
            np.add.at(g, Fc[:, k], (self.w_q * A / At)[:, None] * Gm[:, k])
        if self.w_p > 0:
            ep, gp = self.pull(C, grad=True)
            return Es + Eq + ep, g + gp
        return Es + Eq, g


def _flip_pass(C, F, Vin, Fin, max_flips, clear=0.0, tri_energy=None):
    """Flip edges whose flip lowers the energy of the two triangles (``tri_energy(T)``: per-triangle
    share of the descent's energy, paper Sec. 3.3 "where they lower the energy"), or, without
    ``tri_energy``, raises their smaller minimum angle by > 2 degrees; every flip exactly checked."""
    he = np.stack([F, np.roll(F, -1, axis=1)], 2).reshape(-1, 2)
    fid = np.repeat(np.arange(len(F)), 3)
    opp = np.roll(F, 1, axis=1).reshape(-1)  # corner opposite half-edge (F[k], F[k+1])
    n = len(C)
    key = np.minimum(he[:, 0], he[:, 1]) * n + np.maximum(he[:, 0], he[:, 1])
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = order[0::2][ks[0::2] == ks[1::2]]
    second = order[1::2][ks[0::2] == ks[1::2]]
    i, j = he[first, 0], he[first, 1]
    k, l_ = opp[first], opp[second]
    f1, f2 = fid[first], fid[second]
    before = np.minimum(_min_angles(C, F[f1]), _min_angles(C, F[f2]))
    T1 = np.stack([k, l_, j], 1)  # new triangles (i, j) -> (k, l): (k, l, j) and (l, k, i)
    T2 = np.stack([l_, k, i], 1)
    after = np.minimum(_min_angles(C, T1), _min_angles(C, T2))
    if tri_energy is not None:
        e_old = tri_energy(F[f1]) + tri_energy(F[f2])
        gain = e_old - (tri_energy(T1) + tri_energy(T2))
        better = gain > 1e-12 * np.maximum(np.abs(e_old), 1e-300)
    else:
        gain = after - before
        better = gain > 2.0
    # the flipped edge must not exist already (keeps the mesh manifold), and must improve clearly
    ekey = np.minimum(k, l_) * n + np.maximum(k, l_)
    exists = np.isin(ekey, key)
    # new normals must agree with the old ones (no fold)
    def nrm(T):
        return np.cross(C[T[:, 1]] - C[T[:, 0]], C[T[:, 2]] - C[T[:, 0]])
    n_old = nrm(F[f1]) + nrm(F[f2])
    ok = (~exists & better & (np.einsum("ij,ij->i", nrm(T1), n_old) > 0)
          & (np.einsum("ij,ij->i", nrm(T2), n_old) > 0))
    cand = np.flatnonzero(ok)
    cand = cand[np.argsort(-gain[cand])]
    used = np.zeros(len(F), dtype=bool)
    made: set[int] = set()  # two flips creating the same edge would make it non-manifold
    sel = []
    for c in cand.tolist():
        if used[f1[c]] or used[f2[c]] or int(ekey[c]) in made:
            continue
        used[f1[c]] = used[f2[c]] = True
        made.add(int(ekey[c]))
        sel.append(c)
        if len(sel) >= max_flips:
            break
    if not sel:
        return F, 0
    sel = np.asarray(sel)
    from scipy.spatial import cKDTree

    vin_tree = cKDTree(Vin)
    EI = np.unique(np.sort(np.concatenate([Fin[:, [0, 1]], Fin[:, [1, 2]], Fin[:, [2, 0]]]), axis=1), axis=0)
    e_tree = cKDTree(0.5 * (Vin[EI[:, 0]] + Vin[EI[:, 1]]))
    e_half = 0.5 * float(np.linalg.norm(Vin[EI[:, 0]] - Vin[EI[:, 1]], axis=1).max())
    for _ in range(4):
        Fn = F.copy()
        Fn[f1[sel]] = T1[sel]
        Fn[f2[sel]] = T2[sel]
        changed = np.r_[f1[sel], f2[sel]]
        owner = np.r_[np.arange(len(sel)), np.arange(len(sel))]
        bad = np.zeros(len(sel), dtype=bool)
        pr = cross_pairs(C, Fn[changed], Vin, Fin)
        if len(pr):
            bad[owner[pr[:, 0]]] = True
        if clear > 0:  # keep the clearance the descent kept: vertex-face and new-edge-edge distances
            bad[owner[too_close(C[Fn[changed]], Vin, Fin, vin_tree, clear)]] = True
            P0, P1 = C[k[sel]], C[l_[sel]]
            mid = 0.5 * (P0 + P1)
            lists = e_tree.query_ball_point(mid, 0.5 * np.linalg.norm(P1 - P0, axis=1) + e_half + clear)
            cnt = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            if cnt.sum():
                ie = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
                iflip = np.repeat(np.arange(len(sel)), cnt)
                d2 = segment_segment_sqdist(P0[iflip], P1[iflip], Vin[EI[ie, 0]], Vin[EI[ie, 1]])
                bad[iflip[d2 < clear * clear]] = True
        pr = self_pairs(C, Fn)
        if len(pr):
            pos = -np.ones(len(F), dtype=np.int64)
            pos[changed] = owner
            hit = np.r_[pos[pr[:, 0]], pos[pr[:, 1]]]
            bad[hit[hit >= 0]] = True
            if (hit < 0).all():  # a pre-existing problem: do not flip at all
                return F, 0
        if not bad.any():
            return Fn, len(sel)
        sel = sel[~bad]
        if len(sel) == 0:
            return F, 0
    return F, 0


def optimize_cage(
    C: np.ndarray,
    Fc: np.ndarray,
    Vin: np.ndarray,
    Fin: np.ndarray,
    *,
    h: float,
    dhat: float,
    w_s: float = 1.0,
    w_q: float = 0.05,
    kappa: float = 1.0,
    step: float | None = None,
    iters: int = 60,
    flip_rounds: int = 2,
    time_limit: float = 10.0,
    w_p: float = 0.0,
    pull_target: float | None = None,
    min_distance: float = 0.0,
    h_local: tuple | None = None,
    free: np.ndarray | None = None,
    pull_mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Relocate the cage's vertices (and flip edges) to lower spacing + MIPS energy, intersection-free.

    Parameters
    ----------
    C, Fc : arrays
        Cage strictly containing ``(Vin, Fin)``, free of (self-)intersections (unit diagonal).
    h : float
        Target spacing (paper's ``h``).
    dhat : float
        Barrier activation distance.
    w_s, w_q, kappa : float
        Weights of the spacing, MIPS and barrier terms (paper's ``lambda`` = kappa = 0.1).
    iters : int
        Gradient steps per round (``flip_rounds + 1`` rounds of descent, flips between rounds).
    time_limit : float
        CPU seconds of this process; the descent stops early beyond it.
    w_p : float
        Weight of the input-to-cage pull (not in the paper; 0 = off): input vertices farther than
        ``pull_target`` (default ``2 h``) from the cage pull the closest cage point toward them, so the
        descent can lower the cage into a concavity the envelope bridged (still under the barrier and
        the CCD line search: nothing may intersect).
    min_distance : float
        Clearance a second CCD (cage-input pairs only) keeps between the cage and the input (the
        caller's ``min_gap``; at most the starting gap). The first CCD (all pairs, cage-cage too) keeps
        ``min(dhat / 10, half the starting gap)``: below a ``min_gap`` of the order of ``dhat``, so
        without it the optimised cage failed the caller's certificate and the simplified one was kept.
    h_local : (points, h_loc, radius), optional
        Not in the paper: a smaller spacing target near ``points`` (the envelope's active points), so the
        cage hugs the input where two parts nearly touch: ``h + (h_loc - h) exp(-(s / radius)^2)``,
        ``s`` the distance of a query's closest input point to the nearest of ``points``.
    free : (n,) bool array, optional
        Only these cage vertices move (default: all); the others are obstacles like the input (the
        tightening pass optimises a patch of the cage, its border held).
    pull_mask : (len(Vin),) bool array, optional
        Only these input vertices pull (default: all; the patch's input vertices whose closest cage
        point may lie outside the patch must not pull).

    Returns
    -------
    C, Fc : arrays
        The optimised cage (same vertex count; ``Fc`` changed by flips).
    info : dict
        Energies before/after, steps, flips, mean/min CCD step fraction, seconds.
    """
    t0 = time.perf_counter()
    c0 = time.process_time()
    C = np.array(C, dtype=np.float64)
    Fc = np.array(Fc, dtype=np.int64)
    h_ref = max(h, dhat)
    step = 2 * dhat if step is None else float(step)
    t_pull = 2 * h if pull_target is None else pull_target
    energy = _Energy(Fc, Vin, Fin, h, w_s, w_q, h_ref, w_p=w_p, t_pull=t_pull, h_local=h_local,
                     pull_mask=pull_mask)
    nc = len(C)
    if free is not None:
        free = np.asarray(free, dtype=bool)
        if free.shape != (nc,):
            raise CageOptionError(f"free must be a boolean mask of the {nc} cage vertices")
    run = _Descent(energy, dhat, kappa, nc, free=free, step=step, cpu_start=c0, cpu_limit=time_limit)
    info = run.info
    E0 = None
    for rnd in range(flip_rounds + 1):
        X, f, g = run.start_round(C, Fc, Vin, Fin, min_distance)
        if E0 is None:
            E0 = f
        C = run.descend(C, X, f, g, iters)
        if rnd < flip_rounds:  # flips between the descent rounds (paper: where they lower the energy)
            Fc, nfl = _flip_pass(C, Fc, Vin, Fin, max_flips=len(Fc), clear=max(run.min_dist, run.mdf),
                                 tri_energy=energy.triangles(C))
            info["flips"] += nfl
            if nfl == 0 and rnd > 0:
                break
    energy.Fc = Fc
    run.pm = PairMesh(C, Fc, Vin, Fin)
    if w_p > 0:
        info["pull_after"] = energy.pull(C)
    info.update({"energy_before": E0, "energy_after": run.total(run.pm.stack(C, Vin), C),
                 "seconds": time.perf_counter() - t0})
    return C, Fc, info


class _Descent:
    """What the descent rounds of :func:`optimize_cage` share: the energy ``E`` + barrier ``B`` (eq. 7),
    the collision meshes of the current connectivity, the clearances the CCDs keep, and the counters."""

    def __init__(self, energy: _Energy, dhat: float, kappa: float, nc: int, *, free: np.ndarray | None,
                 step: float, cpu_start: float, cpu_limit: float):
        self.energy, self.dhat, self.nc = energy, dhat, nc
        self.barrier = ipctk.BarrierPotential(dhat, kappa)
        self.free, self.step, self.cpu_start, self.cpu_limit = free, step, cpu_start, cpu_limit
        self.info: dict = {"steps": 0, "flips": 0, "ccd_limited": 0}
        self.active = np.zeros(nc, dtype=bool)  # cage vertices in barrier pairs at the last gradient
        self.pm: PairMesh | None = None  # all pairs (cage-cage and cage-input)
        self.pmf: PairMesh | None = None  # cage-input pairs, for the caller's min_distance
        self.Xf = None
        self.min_dist, self.mdf = 0.0, 0.0

    def total(self, X: np.ndarray, Cc: np.ndarray, grad: bool = False, cand=None):
        """``E(Cc) + B(X)`` (and its (nc,3) gradient in the cage vertices, marking :attr:`active`)."""
        pm = self.pm
        col = pm.collisions(X, self.dhat, cand)
        if grad:
            e, g = self.energy(Cc, grad=True)
            gb = self.barrier.gradient(col, pm.mesh, X)[: 3 * self.nc].reshape(-1, 3)
            self.active[:] = np.abs(gb).max(axis=1) > 0
            return e + float(self.barrier(col, pm.mesh, X)), g + gb
        return self.energy(Cc) + float(self.barrier(col, pm.mesh, X))

    def start_round(self, C: np.ndarray, Fc: np.ndarray, Vin: np.ndarray, Fin: np.ndarray,
                    min_distance: float):
        """Collision meshes of the connectivity ``Fc`` and the CCD clearances; returns ``X, E + B, grad``."""
        self.energy.Fc = Fc
        pm = self.pm = PairMesh(C, Fc, Vin, Fin)
        Xf = self.Xf = np.asarray(Vin, dtype=float)
        X = pm.stack(C, Xf)
        if pm.intersects(X):
            raise CageError("optimize_cage: the start cage intersects")
        f, g = self.total(X, C, grad=True)
        # minimum distance kept by the CCD (a fraction of the current gap, at most dhat / 10)
        col = pm.collisions(X, self.dhat)
        d0 = float(np.sqrt(col.compute_minimum_distance(pm.mesh, X))) if len(col) else self.dhat
        self.min_dist = min(0.1 * self.dhat, 0.5 * d0)
        self.info.setdefault("min_distance_start", d0)
        self.pmf, self.mdf = None, 0.0
        if min_distance > 0:  # the caller's min_gap between cage and input: a second CCD on those pairs
            pmf = self.pmf = PairMesh(C, Fc, Vin, Fin, cage_fine_only=True)
            Xs = pmf.stack(C, Xf)
            colf = pmf.collisions(Xs, 2 * float(min_distance))
            d0f = float(np.sqrt(colf.compute_minimum_distance(pmf.mesh, Xs))) if len(colf) else np.inf
            self.mdf = min(float(min_distance), 0.999 * d0f)
        return X, f, g

    def ccd(self, Ca: np.ndarray, Cb: np.ndarray, cand=None) -> float:
        """The collision-free fraction of the motion ``Ca -> Cb`` (both CCDs)."""
        pm, pmf, Xf = self.pm, self.pmf, self.Xf
        a_ = pm.stepsize(pm.stack(Ca, Xf), pm.stack(Cb, Xf), self.min_dist, cand)
        if pmf is not None and a_ > 0:
            a_ = min(a_, pmf.stepsize(pmf.stack(Ca, Xf), pmf.stack(Cb, Xf), self.mdf))
        return a_

    def descend(self, C: np.ndarray, X: np.ndarray, f: float, g: np.ndarray, iters: int) -> np.ndarray:
        """Up to ``iters`` accepted gradient steps from ``C``; returns the last accepted cage."""
        for _ in range(iters):
            # CPU time: a loaded machine does not cut it short
            if time.process_time() - self.cpu_start > self.cpu_limit:
                break
            gn = np.linalg.norm(g, axis=1)
            if float(gn.max()) < 1e-12:
                break
            # per-vertex normalised gradient (a positive diagonal scaling: still a descent direction)
            gref = float(np.quantile(gn, 0.9))
            d = -g * (self.step / np.maximum(gn, gref if gref > 0 else float(gn.max())))[:, None]
            if self.free is not None:
                d[~self.free] = 0.0
            moved = self._line_search(C, X, f, d)
            if moved is None:
                break
            C, X, cand = moved
            f, g = self.total(X, C, grad=True, cand=cand)
            self.info["steps"] += 1
        return C

    def _line_search(self, C: np.ndarray, X: np.ndarray, f: float, d: np.ndarray):
        """``(C + a d, X(a), cand)`` for the largest ``a = 0.9 amax / 2^k > 1e-3`` that lowers ``E + B``
        (``amax``: the CCD's collision-free fraction; ``cand``: the step's broad phase), or None."""
        pm, info = self.pm, self.info
        # one broad phase per step: the CCD, the held variant, the line search and the next
        # gradient all lie on the motion C -> C + d (boxes inflated by dhat cover the barrier)
        cand = pm.candidates(X, pm.stack(C + d, self.Xf), self.dhat)
        amax = self.ccd(C, C + d, cand)
        if amax < 0.3 and self.active.any():
            # a pair in contact range blocks the step: hold its cage vertices, move the others
            d2_ = np.where(self.active[:, None], 0.0, d)
            amax2 = self.ccd(C, C + d2_, cand)
            if amax2 > amax:
                d, amax = d2_, amax2
                info["held"] = info.get("held", 0) + 1
        if amax < 1.0:
            info["ccd_limited"] += 1
        a = 0.9 * amax
        while a > 1e-3:
            Cn = C + a * d
            Xn = pm.stack(Cn, self.Xf)
            if self.total(Xn, Cn, cand=cand) < f:
                return Cn, Xn, cand
            a *= 0.5
        return None
