"""Tet meshing of one closed surface layer (TetWild by default, TetGen optional).

Sizing rule for a hierarchy: layer ``k`` is meshed with target edge length ``edge_length * 2**k``
(``edge_length`` = ``edge_length_fac`` x the *input's* bounding-box diagonal). Halving the
resolution per level gives ~8x fewer tets per coarser layer when the layers enclose similar volumes;
the cage backends use 4x fewer surface faces per level to match (``cagegen.default_face_counts``).

TetWild's boundary is only within ``epsilon`` (relative to the layer's bounding-box diagonal) of the
input surface, so a cage that touches the finer surface can leave a few fine nodes outside the coarse
tet mesh: the prolongation extrapolates and counts them (``n_outside``). TetGen keeps the input
boundary exactly.
"""

from __future__ import annotations

import numpy as np

from cagegen._geometry import as_mesh_arrays, bbox_diagonal
from cagegen._tempdir import in_temp_dir
from cagegen.errors import MeshInputError, NestmgError

__all__ = ["MESHERS", "TetMeshError", "orient_tets", "tet_quality", "tet_volumes", "tetrahedralize"]

MESHERS = ("tetwild", "tetgen")


class TetMeshError(NestmgError, RuntimeError):
    """The mesher failed or produced an unusable tet mesh."""


def tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed volumes (t,) of tets ``T`` (t,4) of nodes ``V`` (n,3); positive = right-handed."""
    a, b, c, d = (V[T[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def orient_tets(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Return a copy of ``T`` with every tet positively oriented (swap two indices where negative)."""
    T = np.array(T, dtype=np.int64, copy=True)
    neg = tet_volumes(V, T) < 0
    T[neg, 2], T[neg, 3] = T[neg, 3].copy(), T[neg, 2].copy()
    return T


def tet_quality(V: np.ndarray, T: np.ndarray, sliver_deg: float = 5.0) -> dict:
    """Dihedral-angle quality of a tet mesh.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
    sliver_deg : float
        A tet whose smallest dihedral angle is below this (degrees) counts as a sliver.

    Returns
    -------
    dict
        ``min_dihedral_deg`` (smallest over the mesh), ``p01_min_dihedral_deg`` (1st percentile of the
        per-tet minimum), ``max_dihedral_deg``, ``n_slivers`` and ``sliver_fraction``.
    """
    V = np.asarray(V, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if len(T) == 0:
        return {"min_dihedral_deg": float("nan"), "p01_min_dihedral_deg": float("nan"),
                "max_dihedral_deg": float("nan"), "n_slivers": 0, "sliver_fraction": 0.0}
    P = V[T]
    # outward-or-inward face normals of the 4 faces (face i is opposite vertex i)
    faces = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
    N = np.stack([np.cross(P[:, b] - P[:, a], P[:, c] - P[:, a]) for a, b, c in faces], axis=1)
    N /= np.maximum(np.linalg.norm(N, axis=2, keepdims=True), 1e-300)
    # the dihedral angle at the edge shared by faces i and j is pi - angle(n_i, n_j)
    ang = np.stack([np.pi - np.arccos(np.clip(np.einsum("ij,ij->i", N[:, i], N[:, j]), -1.0, 1.0))
                    for i in range(4) for j in range(i + 1, 4)], axis=1)
    dmin = np.degrees(ang.min(axis=1))
    dmax = np.degrees(ang.max(axis=1))
    n_sl = int((dmin < sliver_deg).sum())
    return {"min_dihedral_deg": float(dmin.min()), "p01_min_dihedral_deg": float(np.percentile(dmin, 1)),
            "max_dihedral_deg": float(dmax.max()), "n_slivers": n_sl, "sliver_fraction": n_sl / len(T)}


def _flat(V: np.ndarray, T: np.ndarray, rtol: float = 1e-12) -> np.ndarray:
    """Mask of flat tets: |volume| <= ``rtol`` x (longest edge)^3 (a regular tet has 0.118)."""
    P = V[T]
    longest = np.max([np.linalg.norm(P[:, i] - P[:, j], axis=1)
                      for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], axis=0)
    return np.abs(tet_volumes(V, T)) <= rtol * longest**3


def _has_flat_tets(V: np.ndarray, T: np.ndarray) -> bool:
    """True if some tet is flat (FEM-unusable: unbounded cotangent weights)."""
    return bool(len(T) and _flat(V, T).any())


def _drop_boundary_slivers(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove flat tets whose four nodes all lie on the boundary surface.

    TetGen keeps the input surface exactly; where that surface has nearly coplanar neighbouring
    triangles it may fill the gap between them with a sliver of ~zero volume. Such a tet adds nothing
    to the domain, and its cotangent weights are unbounded, so it is dropped. Flat tets with an
    interior node are left for the caller to reject.
    """
    from solvers.fem import boundary_nodes

    flat = _flat(V, T)
    on_bnd = np.zeros(len(V), dtype=bool)
    on_bnd[boundary_nodes(T)] = True
    drop = flat & on_bnd[T].all(axis=1)
    if not drop.any():
        return V, T
    return _compact(V, T[~drop])


def _compact(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(T)
    if len(used) == len(V):
        return V, T
    remap = -np.ones(len(V), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[T]


def tetrahedralize(
    V: np.ndarray,
    F: np.ndarray,
    *,
    mesher: str = "tetwild",
    edge_length: float | None = None,
    edge_length_fac: float = 0.05,
    epsilon: float = 1e-3,
    minratio: float = 1.5,
    threads: int = 0,
    stop_energy: float = 10.0,
    max_opt_iter: int = 80,
    coarsen: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Tet-mesh the solid bounded by the closed surface ``(V, F)``.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, outward-oriented surface.
    mesher : {"tetwild", "tetgen"}
        ``tetwild`` (pytetwild / fTetWild, robust, boundary within ``epsilon``) or ``tetgen``
        (fast, keeps the boundary exactly; needs the ``tetgen`` extra and a clean input).
    edge_length : float, optional
        Absolute target edge length. Defaults to ``edge_length_fac`` x bounding-box diagonal of ``V``.
    edge_length_fac : float
        Target edge length relative to the bounding-box diagonal when ``edge_length`` is None.
    epsilon : float
        TetWild envelope, relative to the bounding-box diagonal (ignored by tetgen).
    minratio : float
        TetGen radius-edge quality bound (ignored by tetwild).
    threads : int
        TetWild threads (0 = all cores).
    stop_energy, max_opt_iter
        TetWild's optimisation stops when the largest conformal AMIPS energy of a tet is below
        ``stop_energy`` or after ``max_opt_iter`` passes (fTetWild's defaults: 10 and 80).
    coarsen : bool
        TetWild: coarsen the output as far as the quality allows. Without it the boundary triangles of a
        coarse cage keep ~2-8x more tets than the target edge length asks (measured on the demo torus's
        cages: 4,400 instead of 2,354; with it 2,260, no tet below 5 degrees).

    Returns
    -------
    Vt : (p,3) float64 array
        Nodes (every node used by a tet).
    T : (t,4) int64 array
        Positively oriented tets.

    Raises
    ------
    MeshInputError
        Wrong shapes or dtypes, no faces, indices out of range, NaN/inf coordinates (checked before
        the mesher runs).
    TetMeshError
        If the mesher fails or returns an empty / degenerate mesh.
    """
    # structural checks before any C++ code sees the arrays: pytetwild segfaults on an empty face
    # array, and out-of-range indices would be read out of bounds
    V, F = as_mesh_arrays(V, F, "surface")
    if not np.isfinite(V).all():
        raise MeshInputError(f"surface: {int((~np.isfinite(V)).any(axis=1).sum())} vertices have NaN/inf coordinates")
    if mesher not in MESHERS:
        raise ValueError(f"unknown mesher {mesher!r}; choose from {MESHERS}")
    lo, hi = V.min(axis=0), V.max(axis=0)
    diag = bbox_diagonal(V)  # overflow-safe
    if not (np.isfinite(diag) and diag > 0):
        raise MeshInputError(f"surface: bounding-box diagonal {diag} (all vertices coincide, or overflow)")
    h = float(edge_length) if edge_length is not None else edge_length_fac * diag
    if not np.isfinite(h) or h <= 0:
        raise ValueError(f"edge length must be positive, got {h}")
    try:
        if mesher == "tetwild":
            import pytetwild

            # fTetWild writes __tracked_surface.stl into the working directory: keep it out of the user's
            with in_temp_dir():
                # pytetwild segfaults on small inputs (diagonal 1e-9): mesh a unit-diagonal copy, map back
                c = (lo + hi) / 2
                Vt, T = pytetwild.tetrahedralize(
                    (V - c) / diag, F.astype(np.int32), edge_length_abs=h / diag, epsilon=epsilon,
                    num_threads=threads, quiet=True, stop_energy=float(stop_energy),
                    num_opt_iter=int(max_opt_iter), coarsen=bool(coarsen),
                )
                Vt = np.asarray(Vt, dtype=np.float64) * diag + c
        else:
            try:
                import tetgen
            except ImportError as exc:  # optional extra
                raise TetMeshError("mesher='tetgen' needs the optional 'tetgen' package (pip install tetgen)") from exc
            # TetGen's maxvolume is only honoured with fixedvolume=True (ENVIRONMENT.md); the volume of a
            # regular tet of edge h is h^3 / (6 sqrt 2). Its radius-edge bound does not remove slivers;
            # when one is left, retry with a dihedral-angle bound (TetGen's -q/d switch).
            for mindihedral in (0.0, 10.0, 18.0):
                Vt, T, _, _ = tetgen.TetGen(V, F.astype(np.int32)).tetrahedralize(
                    quality=True, minratio=minratio, mindihedral=mindihedral, fixedvolume=True,
                    maxvolume=h**3 / (6 * np.sqrt(2)), steinerleft=-1,
                    # TetGen merges nearly coplanar facets / nearby vertices by default, which moves the
                    # boundary of a cage that touches the finer surface (lost volume, fine nodes outside)
                    nomergefacet=True, nomergevertex=True,
                )
                if not _has_flat_tets(np.asarray(Vt, float), np.asarray(T, np.int64)):
                    break
    except TetMeshError:
        raise
    except Exception as exc:  # the meshers raise RuntimeError / their own types on bad input
        raise TetMeshError(f"{mesher} failed on a surface with {len(V)} vertices / {len(F)} faces: {exc}") from exc
    Vt = np.asarray(Vt, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if len(T) == 0:
        raise TetMeshError(f"{mesher} returned no tets (surface {len(V)} vertices / {len(F)} faces)")
    Vt, T = _compact(Vt, T)
    T = orient_tets(Vt, T)
    if mesher == "tetgen" and _has_flat_tets(Vt, T):
        Vt, T = _drop_boundary_slivers(Vt, T)
    if _has_flat_tets(Vt, T):
        n_flat = int(_flat(Vt, T).sum())
        raise TetMeshError(f"{mesher} returned {n_flat} flat (near-zero volume) tets; try mesher='tetwild'")
    return Vt, T
