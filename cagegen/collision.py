"""ipctk helpers shared by the backends (nested's flow and re-inflation, sdf's optimisation): one
CollisionMesh holding both surfaces.

The coarse cage C comes first (vertices ``0..nc-1``), the fine surface F after it. The fine surface
may self-intersect while it is flowed (paper Sec. 3.1: "we do not care ... whether it self-
intersects"), so fine-fine pairs are filtered out; cage-cage pairs are kept (the cage must stay free
of self-intersections) and so are cage-fine pairs.

ipctk's log lines (spdlog, printed on stdout by the C++ side) go to the ``cagegen.ipctk`` logger:
the calls below run inside :func:`cagegen._log.ipctk_to_log`, and ipctk stays at level ``error``
outside them (set at import of this module).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import ipctk
import numpy as np

from ._log import ipctk_to_log, setup_ipctk

__all__ = ["PairMesh", "close_edge_pairs", "ipctk_threads", "ipctk_to_log", "min_distance",
           "self_collision_free_step"]

setup_ipctk()


@contextlib.contextmanager
def ipctk_threads(n: int | None) -> Iterator[None]:
    """ipctk's threads limited to ``n`` inside the block (None: unchanged), restored after.

    ipctk sums barrier potentials, gradients and Hessians in parallel (TBB), in an order that differs run
    to run; the re-inflation's Newton iterations and the flows amplify those last bits into other outcomes
    (featuretype.stl's second cage: volume ratio 1.317 and 1.421 over two runs of the same command,
    ``benchmarks/results/cages/ab_cage_threads_5fa2610_run*.json``). On one thread the cages are the same bytes
    every run (6 of 6 meshes there), 1.08-1.32x the wall time on 2 cores.
    """
    if n is None:
        yield
        return
    old = ipctk.get_num_threads()
    ipctk.set_num_threads(int(n))
    try:
        yield
    finally:
        ipctk.set_num_threads(old)


def _i32(F: np.ndarray) -> np.ndarray:
    return np.asarray(F, dtype=np.int32, order="C")


class PairMesh:
    """A :class:`ipctk.CollisionMesh` of a cage C and a fine surface F (fine-fine pairs ignored).

    Parameters
    ----------
    Vc : (nc,3) float array
        Cage vertices (used as rest positions for ipctk's area weights).
    Fc : (mc,3) int array
        Cage triangles.
    Vf : (nf,3) float array
        Fine vertices.
    Ff : (mf,3) int array
        Fine triangles.
    cage_fine_only : bool
        If True, also ignore cage-cage pairs (used to measure the cage-to-fine gap).
    """

    def __init__(self, Vc: np.ndarray, Fc: np.ndarray, Vf: np.ndarray, Ff: np.ndarray,
                 cage_fine_only: bool = False):
        self.nc, self.nf = len(Vc), len(Vf)
        X = np.vstack([Vc, Vf]).astype(float)
        faces = _i32(np.vstack([Fc, np.asarray(Ff) + self.nc]))
        self.mesh = ipctk.CollisionMesh(X, ipctk.edges(faces), faces)
        if cage_fine_only:
            labels = np.r_[np.zeros(self.nc), np.ones(self.nf)].astype(np.int32)
            self.mesh.can_collide = ipctk.make_vertex_patches_filter(labels)
        else:
            # vertices >= nc are "static": static-static (fine-fine) pairs are rejected
            self.mesh.can_collide = ipctk.make_static_obstacle_filter(self.nc)

    def stack(self, Vc: np.ndarray, Vf: np.ndarray) -> np.ndarray:
        """Positions ``(nc+nf, 3)`` of the collision mesh."""
        return np.ascontiguousarray(np.vstack([Vc, Vf]), dtype=float)

    def intersects(self, X: np.ndarray) -> bool:
        """True if the cage intersects itself or the fine surface at positions ``X``."""
        with ipctk_to_log():
            return bool(ipctk.has_intersections(self.mesh, X))

    def stepsize(self, X0: np.ndarray, X1: np.ndarray, min_distance: float = 0.0,
                 candidates: ipctk.Candidates | None = None) -> float:
        """Largest collision-free fraction in [0, 1] of the linear motion ``X0 -> X1`` (CCD).

        Additive CCD (Li et al. 2021, conservative: the returned step keeps a positive distance)
        with an LBVH broad phase: ~10-25x faster here than the default Tight-Inclusion CCD.
        ``candidates`` (from :meth:`candidates` of a motion containing this one) skips the broad phase.
        """
        with ipctk_to_log():
            if candidates is not None:
                return float(candidates.compute_collision_free_stepsize(self.mesh, X0, X1, min_distance,
                                                                        ipctk.AdditiveCCD()))
            return float(ipctk.compute_collision_free_stepsize(
                self.mesh, X0, X1, min_distance, ipctk.LBVH(), ipctk.AdditiveCCD()))

    def candidates(self, X0: np.ndarray, X1: np.ndarray, inflation: float) -> ipctk.Candidates:
        """Broad-phase candidates of the linear motion ``X0 -> X1``, boxes inflated by ``inflation``.

        Every pair closer than ``inflation`` at some point of the motion, and every pair the motion
        makes collide, is among them: the CCD of any sub-motion (a prefix, or some vertices held) and
        the barrier collision set (``dhat <= inflation``) at any point on it can be computed from them
        (IPC's line search, Li et al. 2020, Alg. 1), one broad phase per step instead of one per call.
        """
        cand = ipctk.Candidates()
        with ipctk_to_log():
            cand.build(self.mesh, X0, X1, float(inflation), ipctk.LBVH())
        return cand

    def collisions(self, X: np.ndarray, dhat: float,
                   candidates: ipctk.Candidates | None = None) -> ipctk.NormalCollisions:
        """Barrier collision set (pairs closer than ``dhat``) at positions ``X`` (``candidates``: see
        :meth:`candidates`)."""
        col = ipctk.NormalCollisions()
        with ipctk_to_log():
            if candidates is not None:
                col.build(candidates, self.mesh, X, dhat, 0.0)
            else:
                col.build(self.mesh, X, dhat, 0.0, ipctk.LBVH())
        return col


def self_collision_free_step(V0: np.ndarray, F: np.ndarray, V1: np.ndarray) -> float:
    """Largest fraction of the linear motion ``V0 -> V1`` of the surface ``(V0, F)`` free of self-contact.

    ipctk's additive CCD with an LBVH broad phase (as :meth:`PairMesh.stepsize`), on this one surface;
    1.0 when the whole motion is free. Its log lines go to ``cagegen.ipctk``.
    """
    faces = _i32(F)
    cm = ipctk.CollisionMesh(np.asarray(V0, dtype=float), ipctk.edges(faces), faces)
    with ipctk_to_log():
        return float(ipctk.compute_collision_free_stepsize(cm, V0, V1, 0.0, ipctk.LBVH(), ipctk.AdditiveCCD()))


#: :func:`min_distance`'s first search radius, relative to the bounding-box diagonal (clearances asked
#: of cages are 0.001-0.01 of it).
MIN_DISTANCE_START = 1e-3


def close_edge_pairs(Vc: np.ndarray, Fc: np.ndarray, Vf: np.ndarray, Ff: np.ndarray,
                     radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges of C closer than ``radius`` to an edge of F (edge-edge pairs; the vertex-face ones are
    point-mesh distances), with those distances and directions.

    A cage edge passing over a sharp edge of F (a CAD part's convex crease) can be the closest pair of the
    two surfaces while every vertex of each is farther from the other surface.

    Returns
    -------
    edges : (k,2) int array
        Vertex indices of C.
    distance : (k,) float array
    direction : (k,3) float array
        Unit vector from F's closest point to C's (moving the C edge along it separates the pair).
    """
    pm = PairMesh(Vc, Fc, Vf, Ff, cage_fine_only=True)
    X = pm.stack(Vc, Vf)
    col = ipctk.NormalCollisions()
    with ipctk_to_log():
        col.build(pm.mesh, X, float(radius))
    E, F = pm.mesh.edges, pm.mesh.faces
    edges, dist, dirs = [], [], []
    for c in col.ee_collisions:
        ids = np.asarray(c.vertex_ids(E, F))
        dof = c.dof(X, E, F)
        d = float(np.sqrt(c.compute_distance(dof)))  # ipctk's distances are squared
        if 0.0 < d < radius:
            v = np.asarray(c.compute_distance_vector(dof), dtype=float).ravel()  # edge 1 -> edge 0
            edges.append(ids[ids < pm.nc])
            dist.append(d)
            dirs.append(v / d if ids[0] < pm.nc else -v / d)
    return (np.array(edges, dtype=np.int64).reshape(-1, 2), np.array(dist, dtype=float),
            np.array(dirs, dtype=float).reshape(-1, 3))


def min_distance(Vc: np.ndarray, Fc: np.ndarray, Vf: np.ndarray, Ff: np.ndarray,
                 upper: float | None = None) -> float:
    """Smallest distance between the surfaces C and F (vertex-face and edge-edge pairs).

    Parameters
    ----------
    Vc, Fc : (nc,3) float, (mc,3) int
        First surface.
    Vf, Ff : (nf,3) float, (mf,3) int
        Second surface.
    upper : float, optional
        Initial search radius (default :data:`MIN_DISTANCE_START` of the joint bounding-box diagonal);
        doubled until a pair is found (the pairs within the radius, hence the cost, grow with it: on
        lucy.ply against its first cage one search at 0.01 cost more than the three from 0.001 up).

    Returns
    -------
    float
        The minimum distance (0 if they intersect; computed with ipctk's exact point-triangle and
        edge-edge distances between every pair within the search radius).
    """
    pm = PairMesh(Vc, Fc, Vf, Ff, cage_fine_only=True)
    X = pm.stack(Vc, Vf)
    if pm.intersects(X):
        return 0.0
    diag = float(np.linalg.norm(X.max(0) - X.min(0)))
    r = MIN_DISTANCE_START * diag if upper is None else float(upper)
    col = ipctk.NormalCollisions()
    while True:
        with ipctk_to_log():
            col.build(pm.mesh, X, r)
        if len(col) > 0 or r > 4 * diag:
            break
        r *= 2.0
    if len(col) == 0:
        return float("inf")
    # compute_minimum_distance returns a squared distance
    return float(np.sqrt(col.compute_minimum_distance(pm.mesh, X)))
