"""Inputs too small for a cage (a 12-triangle CAD box): coarse levels by red refinement, exactly nested."""

import numpy as np
import pytest
import trimesh

from cagegen import MeshInputError
from nestmg import build_hierarchy, solve_on_hierarchy


def _box():
    b = trimesh.creation.box(extents=[30.0, 20.0, 10.0])  # an STL box in mm: 12 faces
    return np.asarray(b.vertices) + [100.0, 0.0, 0.0], np.asarray(b.faces, dtype=np.int64)


def test_a_box_of_twelve_triangles_gets_refined_levels_and_converges():
    V, F = _box()
    H = build_hierarchy(V, F, 3, cache=False, progress=False)
    assert H.levels == 3 and H.certified and H.cage_info["coarse_levels"] == "refinement"
    n = [len(T) for _, T in H.tets]
    assert n[0] == 8 * n[1] and n[1] == 8 * n[2]  # each finer level the red refinement of the next
    for k, P in enumerate(H.P):  # exact: linear functions reproduced, no node outside
        assert np.abs(P @ H.tets[k + 1][0] - H.tets[k][0]).max() < 1e-9 * np.abs(V).max()
    Vt, eps = H.tets[0][0], 1e-3 * np.linalg.norm(np.ptp(V, axis=0))  # TetWild's envelope
    assert np.all(Vt.min(axis=0) > V.min(axis=0) - eps) and np.all(Vt.max(axis=0) < V.max(axis=0) + eps)
    r = solve_on_hierarchy(H.tets_in("normalized"), H.P, "poisson-dirichlet")
    assert r["converged"] and r["factor"] <= 0.2
    assert build_hierarchy(V, F, 2, cache=False, progress=False).levels == 2
    with pytest.raises(MeshInputError):  # a broken small input is named as broken
        build_hierarchy(V, F[:-1], 3, cache=False, progress=False)
