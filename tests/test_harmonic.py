"""Harmonic coordinates of a cage (nestmg.harmonic): partition of unity, linear precision, deformation."""

from __future__ import annotations

import numpy as np
import pytest

from nestmg import NestmgInputError
from nestmg.harmonic import harmonic_coordinates
from solvers.fem import boundary_faces
from solvers.gallery import kuhn_cube_mesh


def _cube_cage(scale: float = 1.0):
    """A Kuhn tet mesh of the unit cube and its boundary, scaled about the centre by ``scale`` as the cage
    (so the mesh's boundary lies inside the cage and is moved onto it)."""
    V, T = kuhn_cube_mesh(4)
    F, _ = boundary_faces(T)
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return (V[used] - 0.5) * scale + 0.5, remap[F], (V, T)


@pytest.fixture(scope="module")
def cube_coords():
    cV, cF, tets = _cube_cage(1.002)
    pts = np.random.default_rng(3).uniform(0.02, 0.98, (300, 3))
    return {s: harmonic_coordinates(cV, cF, pts, tets, refine=2, solver=s) for s in ("multigrid", "direct")}


def test_partition_of_unity_and_linear_precision(cube_coords):
    for hc in cube_coords.values():
        assert hc.info["max_snap"] > 1e-4  # the boundary nodes were moved onto the cage
        assert hc.partition_of_unity_error() < 1e-8
        assert hc.linear_precision_error() < 1e-8
        assert hc.W.min() > -1e-12  # Kuhn meshes satisfy the discrete maximum principle
    mg, direct = cube_coords["multigrid"], cube_coords["direct"]
    assert np.abs(mg.W - direct.W).max() < 1e-8
    assert max(mg.info["iterations"]) <= 15


def test_deform_follows_an_affine_map_of_the_cage(cube_coords, rng):
    hc = cube_coords["multigrid"]
    M = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    t = rng.standard_normal(3)
    assert np.abs(hc.deform(hc.cage_V @ M.T + t) - (hc.points @ M.T + t)).max() < 1e-8
    moved = hc.cage_V.copy()
    moved[np.argmax(moved[:, 0])] += [0.5, 0.0, 0.0]  # one vertex pulled: only points feel it, smoothly
    d = np.linalg.norm(hc.deform(moved) - hc.points, axis=1)
    assert 0 < d.max() < 0.5 and np.all(d >= 0)
    with pytest.raises(NestmgInputError, match="shape"):
        hc.deform(moved[:-1])


def test_curved_cage_of_a_torus():
    """A marching-cubes cage around a torus, its interior meshed by TetGen (boundary on the cage)."""
    pytest.importorskip("tetgen")
    from nestmg import shapes
    from nestmg import MeshingOptions, SizingOptions
    from nestmg.hierarchy import tet_hierarchy

    S = shapes.nested_isosurfaces("torus", [0.0, 0.12], [20, 8])
    tets, P, reps, _ = tet_hierarchy(S, sizing=SizingOptions(coarsening=None),
                                  meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    (cV, cF), pts = S[-1], S[0][0]
    hc = harmonic_coordinates(cV, cF, pts, tets[-1], refine=1)
    assert hc.info["n_outside"] == 0 and hc.W.shape == (len(pts), len(cV))
    assert hc.partition_of_unity_error() < 1e-8 and hc.linear_precision_error() < 1e-8
    # the same from a Hierarchy, whose frame is the input's (a shifted, scaled copy: coordinates are affine
    # invariant, so the weights do not change)
    from nestmg import Hierarchy
    from nestmg.harmonic import hierarchy_harmonic_coordinates

    frame = {"center": [0.3, -0.2, 1.0], "scale": 2.5}
    user = lambda X: np.asarray(X) * frame["scale"] + frame["center"]  # noqa: E731
    h = Hierarchy([(user(V), F) for V, F in S], [(user(V), T) for V, T in tets], P, reps, "iso", frame=frame)
    hh = hierarchy_harmonic_coordinates(h, refine=1)
    assert np.abs(hh.W - hc.W).max() < 1e-8 and np.abs(hh.points - user(pts)).max() < 1e-12
    assert np.abs(hh.deform(hh.cage_V) - hh.points).max() < 1e-7 * frame["scale"]


def test_bad_inputs_are_refused():
    cV, cF, (V, T) = _cube_cage()
    pts = np.full((2, 3), 0.5)
    with pytest.raises(NestmgInputError, match="solver"):
        harmonic_coordinates(cV, cF, pts, (V, T), solver="cg")
    with pytest.raises(NestmgInputError, match="points"):
        harmonic_coordinates(cV, cF, pts[:, :2], (V, T))
    with pytest.raises(NestmgInputError, match="refine"):
        harmonic_coordinates(cV, cF, pts, (V, T), refine=0)
    with pytest.raises(NestmgInputError, match="flattens or inverts"):  # a cage far from the mesh's boundary
        harmonic_coordinates((cV - 0.5) * 0.5 + 0.5, cF, pts, (V, T))
