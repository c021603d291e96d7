"""Gauss-Newton Hessian of ipctk's barrier potential, assembled in numpy.

ipctk's ``BarrierPotential.hessian`` builds, for every contact, the full 12x12 Hessian of
``w m(x) b(d(x)^2)`` (distance Hessian, mollifier terms) and projects it to PSD with an eigen-
decomposition: on homer.obj's first layer it was 0.6 of the 0.7 s of a re-inflation Newton iteration,
70x its gradient. Re-inflation only needs an SPD Newton matrix (the gradient, the objective, the
CCD-bounded line search stay ipctk's), so this module uses the Gauss-Newton part

    H ~ sum_k  w_k m_k h''(d_k)^+  grad d_k  grad d_k^T,      h(d) = kappa b(d^2, dhat^2),

PSD by construction (Nocedal & Wright, Sec. 10.3). For every distance type the closest points are
``sum_i c_i x_i = 0``-combinations of the contact's vertices with coefficients ``c`` (1 for the point,
minus its barycentric coordinates on the other primitive), so ``grad_{x_i} d = c_i n`` with ``n`` the
unit vector between the closest points (envelope theorem: the coefficients are optimal). The
dropped term ``h'(d) grad^2 d`` has ``h' < 0`` and a PSD ``grad^2 d`` for the tangential directions,
i.e. it is the part the PSD projection of the full Hessian mostly removes.
"""

from __future__ import annotations

from operator import attrgetter

import ipctk
import numpy as np
import scipy.sparse as sp

from ..errors import CageError

__all__ = ["ContactArrays", "barrier_derivatives", "collision_lists", "contact_arrays", "contact_gradients",
           "gauss_newton_hessian", "subset"]


class ContactArrays:
    """Vertex indices, weights and kinds of a :class:`ipctk.NormalCollisions` as arrays.

    Attributes
    ----------
    ids : (k,4) int array
        Contact vertices, the point first (``-1`` pads edge-vertex and vertex-vertex contacts):
        face-vertex ``[v, f0, f1, f2]``, edge-edge ``[a0, a1, b0, b1]``, edge-vertex ``[v, e0, e1, -1]``,
        vertex-vertex ``[v0, v1, -1, -1]``.
    kind : (k,) int array
        0 face-vertex, 1 edge-edge, 2 edge-vertex, 3 vertex-vertex.
    weight : (k,) float array
        ipctk's collision weights (multiplicities of the edge-vertex and vertex-vertex pairs).
    """

    FV, EE, EV, VV = 0, 1, 2, 3

    def __init__(self, ids: np.ndarray, kind: np.ndarray, weight: np.ndarray):
        self.ids, self.kind, self.weight = ids, kind, weight

    def __len__(self) -> int:
        return len(self.kind)


def collision_lists(col: ipctk.NormalCollisions) -> tuple[list, list, list, list]:
    """ipctk's face-vertex, edge-edge, edge-vertex and vertex-vertex collision objects of ``col``, in the
    order of :class:`ContactArrays` (reading them is most of :func:`contact_arrays`' cost)."""
    return col.fv_collisions, col.ee_collisions, col.ev_collisions, col.vv_collisions


def subset(lists: tuple[list, list, list, list], keep: np.ndarray) -> ipctk.NormalCollisions:
    """A collision set of the contacts ``keep`` (bool, in :class:`ContactArrays` order) of ``lists``."""
    out = ipctk.NormalCollisions()
    o = np.cumsum([0, *map(len, lists)])
    picked = [[lst[i] for i in np.flatnonzero(keep[o[k]:o[k + 1]])] for k, lst in enumerate(lists)]
    out.fv_collisions, out.ee_collisions, out.ev_collisions, out.vv_collisions = picked
    return out


def contact_arrays(col: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh,
                   lists: tuple[list, list, list, list] | None = None) -> ContactArrays:
    """The contacts of ``col`` as index arrays (see :class:`ContactArrays`).

    Only the plain IPC collision set without area weighting is supported (face-vertex and edge-edge
    weights are then 1; the edge-vertex and vertex-vertex ones count duplicates and are read).
    ``lists``: :func:`collision_lists` of ``col`` when the caller has read them already.
    """
    if col.use_area_weighting or col.collision_set_type != ipctk.NormalCollisions.CollisionSetType.IPC:
        raise CageError("contact_arrays: only the IPC collision set without area weighting is supported")
    E, Fm = np.asarray(mesh.edges), np.asarray(mesh.faces)
    fvl, eel, evl, vvl = collision_lists(col) if lists is None else lists
    fv_v, fv_f = _ints(fvl, "vertex_id"), _ints(fvl, "face_id")
    ee_a, ee_b = _ints(eel, "edge0_id"), _ints(eel, "edge1_id")
    ev_v, ev_e = _ints(evl, "vertex_id"), _ints(evl, "edge_id")
    vv_a, vv_b = _ints(vvl, "vertex0_id"), _ints(vvl, "vertex1_id")
    ids = np.full((len(fvl) + len(eel) + len(evl) + len(vvl), 4), -1, dtype=np.int64)
    o = np.cumsum([0, len(fvl), len(eel), len(evl), len(vvl)])
    ids[o[0]:o[1], 0], ids[o[0]:o[1], 1:] = fv_v, Fm[fv_f]
    ids[o[1]:o[2], :2], ids[o[1]:o[2], 2:] = E[ee_a], E[ee_b]
    ids[o[2]:o[3], 0], ids[o[2]:o[3], 1:3] = ev_v, E[ev_e]
    ids[o[3]:o[4], 0], ids[o[3]:o[4], 1] = vv_a, vv_b
    kind = np.repeat(np.arange(4), np.diff(o))
    weight = np.ones(len(ids))
    weight[o[2]:o[3]] = np.fromiter(map(attrgetter("weight"), evl), float, len(evl))
    weight[o[3]:o[4]] = np.fromiter(map(attrgetter("weight"), vvl), float, len(vvl))
    return ContactArrays(ids, kind, weight)


def _ints(objs: list, name: str) -> np.ndarray:
    return np.fromiter(map(attrgetter(name), objs), np.int64, len(objs))


def _coefficients(X: np.ndarray, ca: ContactArrays) -> np.ndarray:
    """(k,4) coefficients c with ``sum_i c_i x_i`` the vector between the closest points."""
    ids, kind = ca.ids, ca.kind
    P = X[np.maximum(ids, 0)]  # (k,4,3); padded rows are ignored through zero coefficients
    c = np.zeros(ids.shape)
    m = kind == ContactArrays.FV  # point-triangle interior: projection barycentrics
    if m.any():
        p, a, b, q = P[m, 0], P[m, 1], P[m, 2], P[m, 3]
        e1, e2, r = b - a, q - a, p - a
        d11, d12, d22 = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
        r1, r2 = _dot(r, e1), _dot(r, e2)
        det = d11 * d22 - d12 * d12
        u = (d22 * r1 - d12 * r2) / det
        v = (d11 * r2 - d12 * r1) / det
        c[m] = np.c_[np.ones(m.sum()), -(1 - u - v), -u, -v]
    m = kind == ContactArrays.EE  # clamped segment-segment closest points
    if m.any():
        s, t = _segment_segment(P[m, 0], P[m, 1], P[m, 2], P[m, 3])
        c[m] = np.c_[1 - s, s, -(1 - t), -t]
    m = kind == ContactArrays.EV
    if m.any():
        p, a, b = P[m, 0], P[m, 1], P[m, 2]
        e = b - a
        t = np.clip(_dot(p - a, e) / np.maximum(_dot(e, e), 1e-300), 0.0, 1.0)
        c[m, :3] = np.c_[np.ones(m.sum()), -(1 - t), -t]
    m = kind == ContactArrays.VV
    c[m, :2] = [1.0, -1.0]
    return c


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _segment_segment(a0, a1, b0, b1) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (s, t) of the closest points of segments a0a1, b0b1 (Ericson, Real-Time Collision
    Detection, Sec. 5.1.9), vectorised; parallel pairs take s = 0."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c, b = _dot(d1, r), _dot(d1, d2)
    den = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den > 1e-14 * a * e, np.clip((b * f - c * e) / den, 0.0, 1.0), 0.0)
        t = (b * s + f) / e
        s = np.where(t < 0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1, np.clip((b - c) / a, 0.0, 1.0), s))
    return s, np.clip(t, 0.0, 1.0)


def barrier_derivatives(d: np.ndarray, dhat: float, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """h'(d), h''(d) of ``h(d) = kappa b(d^2, dhat^2)`` with IPC's log barrier
    ``b(s, s^) = -(s - s^)^2 ln(s / s^)`` for ``s < s^`` (Li et al. 2020, Eq. 6), zero beyond."""
    s, sh = d * d, dhat * dhat
    inside = s < sh
    s = np.where(inside, s, sh)
    lg = np.log(s / sh)
    b1 = -2.0 * (s - sh) * lg - (s - sh) ** 2 / s
    b2 = -2.0 * lg - 4.0 * (s - sh) / s + (s - sh) ** 2 / (s * s)
    h1 = np.where(inside, kappa * 2.0 * d * b1, 0.0)
    h2 = np.where(inside, kappa * (4.0 * s * b2 + 2.0 * b1), 0.0)  # chain rule through s = d^2
    return h1, h2


def _mollifier(X: np.ndarray, rest: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """ipctk's edge-edge mollifier m(x) (Li et al. 2020, Eq. 12): ``x = |ea x eb|^2`` against
    ``eps_x = 1e-3 |ea_rest|^2 |eb_rest|^2``; ``m = (2 - x/eps_x) x/eps_x`` below it, else 1."""
    ea, eb = X[ids[:, 1]] - X[ids[:, 0]], X[ids[:, 3]] - X[ids[:, 2]]
    x = np.sum(np.cross(ea, eb) ** 2, axis=1)
    ra, rb = rest[ids[:, 1]] - rest[ids[:, 0]], rest[ids[:, 3]] - rest[ids[:, 2]]
    eps = 1e-3 * np.sum(ra * ra, axis=1) * np.sum(rb * rb, axis=1)
    r = x / np.maximum(eps, 1e-300)
    return np.where(r < 1.0, (2.0 - r) * r, 1.0)


def contact_gradients(X: np.ndarray, ca: ContactArrays, rest: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distances d (k,), unit-free gradients ``grad d`` as (k,4,3) blocks and weights ``w m`` (k,)."""
    c = _coefficients(X, ca)
    P = X[np.maximum(ca.ids, 0)]
    r = np.einsum("ki,kij->kj", c, P)
    d = np.linalg.norm(r, axis=1)
    n = r / np.maximum(d, 1e-300)[:, None]
    g = c[:, :, None] * n[:, None, :]
    w = ca.weight.copy()
    m = ca.kind == ContactArrays.EE
    if m.any():
        w[m] *= _mollifier(X, rest, ca.ids[m])
    return d, g, w


def gauss_newton_hessian(X: np.ndarray, ca: ContactArrays, rest: np.ndarray, dhat: float, kappa: float,
                         dofs: np.ndarray | None = None, grads: tuple | None = None,
                         mask: np.ndarray | None = None) -> sp.csr_matrix:
    """Gauss-Newton barrier Hessian ``sum_k w_k m_k max(h''(d_k), 0) grad d_k grad d_k^T``.

    Parameters
    ----------
    X : (N,3) float array
        Positions of the collision mesh.
    ca : ContactArrays
        Contacts (:func:`contact_arrays` of the collision set at ``X``).
    rest : (N,3) float array
        Rest positions of the collision mesh (edge-edge mollifier thresholds).
    dhat, kappa : float
        The barrier's activation distance and stiffness (as ``ipctk.BarrierPotential(dhat, kappa)``).
    dofs : (n,) int array, optional
        DOFs (``3 vertex + axis``) to keep: the result is ``H[dofs][:, dofs]``; the other DOFs are held
        fixed (their columns dropped). Default: all ``3N``.
    grads : tuple, optional
        :func:`contact_gradients` of ``(X, ca, rest)`` when the caller has them already.
    mask : (k,) bool array, optional
        Only the contacts where it is True contribute (the others' terms are zero).

    Returns
    -------
    (n,n) csr matrix, symmetric positive semi-definite.
    """
    n3 = 3 * len(X)
    dofs = np.arange(n3) if dofs is None else np.asarray(dofs)
    if len(ca) == 0:
        return sp.csr_matrix((len(dofs), len(dofs)))
    d, g, w = contact_gradients(X, ca, rest) if grads is None else grads
    _, h2 = barrier_derivatives(d, dhat, kappa)
    a = w * np.maximum(h2, 0.0)
    if mask is not None:
        a = np.where(mask, a, 0.0)
    # H = (J^T diag(a)) J with J the (k, 3N) Jacobian of the distances (12 nonzeros a row); J^T diag(a) is
    # assembled as a csr matrix of its own, so the product is one csr x csr (no csc conversions)
    where = np.full(n3, -1, dtype=np.int64)
    where[dofs] = np.arange(len(dofs))
    cols = where[(3 * np.maximum(ca.ids, 0)[:, :, None] + np.arange(3)).reshape(len(ca), 12)]
    valid = np.repeat(ca.ids >= 0, 3, axis=1) & (cols >= 0)
    rows = np.broadcast_to(np.arange(len(ca))[:, None], cols.shape)[valid]
    cols, vals = cols[valid], g.reshape(len(ca), 12)[valid]
    J = sp.csr_matrix((vals, (rows, cols)), shape=(len(ca), len(dofs)))
    JtA = sp.csr_matrix((vals * a[rows], (cols, rows)), shape=(len(dofs), len(ca)))
    return (JtA @ J).tocsr()
