"""Mirror symmetry of skeleton cages (Casti et al. 2019, Sec. 3.4).

* :func:`detect_mirror_plane`: extrinsic mirror plane of a surface. The paper uses the method of its
  reference [10]; we test the planes through the area centroid whose normals are the principal axes
  of the surface (and the coordinate axes), scoring each by the distance of the reflected surface
  samples to the surface (a plane is accepted when the 95th percentile is below ``tol`` of the
  bounding-box diagonal).
* :func:`symmetrize_sections`: the paper's enforcement on the quad sections: each section Q_i is
  reflected, the section Q_j closest to the reflection (over the vertex pairings) is found; if
  j != i both become the average and its reflection; if j == i (a section crossed by the plane) it
  becomes the average of itself and its paired reflection, which makes its vertices on the plane stay
  on it and the others (or its edges not crossing the plane) mirror images (paper Fig. 6).
"""

from __future__ import annotations

import igl
import numpy as np

__all__ = ["detect_mirror_plane", "reflect", "symmetrize_sections"]


def reflect(P: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror image of the points ``P`` through the plane (point, unit normal)."""
    P = np.atleast_2d(P)
    return P - 2.0 * ((P - point) @ normal)[:, None] * normal[None, :]


def _surface_samples(V, F, n, seed=0):
    rng = np.random.default_rng(seed)
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    f = rng.choice(len(F), size=n, p=a / a.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.column_stack([1 - r1, r1 * (1 - r2), r1 * r2])
    return np.einsum("ij,ijk->ik", bary, V[F[f]]), a


def detect_mirror_plane(V: np.ndarray, F: np.ndarray, tol: float = 0.01, n_samples: int = 4000) -> dict:
    """The best mirror plane of the closed surface ``(V, F)`` among the candidates described above.

    Returns
    -------
    dict with ``point``, ``normal`` (unit), ``score`` (95th percentile of the reflected samples'
    distance to the surface over the diagonal), ``symmetric`` (score < tol) and ``candidates`` (scores).
    """
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64)
    P, a = _surface_samples(V, F, n_samples)
    c = (V[F].mean(axis=1) * a[:, None]).sum(0) / a.sum()
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    _, U = np.linalg.eigh(np.cov((P - c).T))
    normals = list(U.T) + list(np.eye(3))
    best, scores = None, []
    for n in normals:
        n = n / np.linalg.norm(n)
        d2, _, _ = igl.point_mesh_squared_distance(reflect(P, c, n), V, F)
        s = float(np.percentile(np.sqrt(d2), 95)) / diag
        scores.append(s)
        if best is None or s < best[0]:
            best = (s, n)
    return {"point": c, "normal": best[1], "score": best[0], "symmetric": bool(best[0] < tol),
            "candidates": scores}


def _pairing(A: np.ndarray, B: np.ndarray, involution: bool = False) -> tuple[float, np.ndarray]:
    """Best vertex pairing of two quads: permutation p (cyclic shift, either direction) minimising
    sum |A[k] - B[p[k]]|; ``involution``: only p with p[p] = identity (a quad paired with its own
    reflection, so that the average is exactly symmetric)."""
    best = None
    for rev in (False, True):
        base = np.array([0, 3, 2, 1]) if rev else np.arange(4)
        for s in range(4):
            p = np.roll(base, -s)
            if involution and not np.array_equal(p[p], np.arange(4)):
                continue
            cost = float(np.linalg.norm(A - B[p], axis=1).sum())
            if best is None or cost < best[0]:
                best = (cost, p)
    return best


def symmetrize_sections(quads: dict, point: np.ndarray, normal: np.ndarray) -> tuple[dict, dict]:
    """Enforce the mirror symmetry on the quad sections (paper Sec. 3.4).

    Parameters
    ----------
    quads : dict node -> (4,3) float array
        Quad sections (corner order kept in the output).
    point, normal : the mirror plane.

    Returns
    -------
    quads : dict node -> (4,3)
        The symmetrised quads.
    info : dict
        ``pairs`` (node pairs mirrored onto each other), ``self`` (sections crossed by the plane),
        ``max_move`` (largest corner displacement).
    """
    nodes = sorted(quads)
    out = {n: np.array(quads[n], float) for n in nodes}
    done: set = set()
    pairs, selfs = [], []
    for i in nodes:
        if i in done:
            continue
        R = reflect(out[i], point, normal)
        cand = [(j, *_pairing(out[j], R, involution=j == i)) for j in nodes if j not in done]
        j, _, p = min(cand, key=lambda t: t[1])
        avg = 0.5 * (out[j] + R[p])  # avg[k] pairs with corner p[k] of section i
        if j == i:
            out[i] = avg
            selfs.append(int(i))
            done.add(i)
            continue
        out[j] = avg
        Qi = np.empty((4, 3))
        Qi[p] = reflect(avg, point, normal)
        out[i] = Qi
        pairs.append((int(i), int(j)))
        done.update((i, j))
    move = max(float(np.linalg.norm(out[n] - np.asarray(quads[n]), axis=1).max()) for n in nodes)
    return out, {"pairs": pairs, "self": selfs, "max_move": move}
