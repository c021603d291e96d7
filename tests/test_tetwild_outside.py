"""fTetWild's coarse outside (``nestmg.tetmesh.outer_sizing_field``): same solid, fewer tets worked on."""

import numpy as np
import pytest

pytest.importorskip("pytetwild")

from nestmg import shapes  # noqa: E402
from nestmg import tetmesh  # noqa: E402
from nestmg.tetmesh import (  # noqa: E402
    box_ratio, outer_sizing_field, tetrahedralize)


def _unit(V):
    lo, hi = V.min(axis=0), V.max(axis=0)
    return (V - (lo + hi) / 2) / np.linalg.norm(hi - lo)


def test_sizing_field_is_fine_on_the_solid_and_coarse_away_from_it():
    V, F = shapes.torus(res=24)
    V = _unit(V)
    h = 0.02
    kw = outer_sizing_field(V, F, h, 3.0)
    G, val = kw["bg_vertices"], kw["bg_values"]
    assert kw["edge_length_abs"] == pytest.approx(3 * h)
    assert kw["bg_tets"].min() == 0 and kw["bg_tets"].max() == len(G) - 1
    import igl

    wn = igl.fast_winding_number(V, F.astype(np.int64), G)
    assert np.all(val[wn > 0.5] == h)  # every node inside asks for h
    assert val.max() == pytest.approx(3 * h)  # far outside: the global (coarse) edge
    assert val.min() == pytest.approx(h)
    # Kuhn tets tile the grid: their volumes sum to the box's
    P = G[kw["bg_tets"]]
    vol = np.abs(np.einsum("ij,ij->i", P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]))) / 6
    assert vol.sum() == pytest.approx(float(np.prod(G.max(axis=0) - G.min(axis=0))), rel=1e-9)


def test_graded_mesh_has_the_uniform_meshs_solid(monkeypatch):
    monkeypatch.setattr(tetmesh, "OUTER_BOX_RATIO", 0.0)  # the torus is compact: force the coarse outside
    V, F = shapes.torus(res=24)
    h = 0.05 * np.linalg.norm(V.max(axis=0) - V.min(axis=0))
    meshes = {f: tetrahedralize(V, F, edge_length_abs=h, outer_edge_factor=f, time_limit=None)
              for f in (1.0, 3.0)}
    vols = {}
    for f, (Vt, T) in meshes.items():
        P = Vt[T]
        vols[f] = np.einsum("ij,ij->i", P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0])) / 6
        assert vols[f].min() > 0
        L = np.linalg.norm(Vt[T[:, [0, 0, 0, 1, 1, 2]]] - Vt[T[:, [1, 2, 3, 2, 3, 3]]], axis=2)
        assert 0.7 * h < L.mean() < 1.2 * h  # the solid is meshed at h either way
    assert vols[3.0].sum() == pytest.approx(vols[1.0].sum(), rel=2e-3)
    assert 0.8 < len(meshes[3.0][1]) / len(meshes[1.0][1]) < 1.25


def _box(a, b, c):
    """Closed triangulated box with sides a, b, c (12 triangles, outward)."""
    V = np.array([[x, y, z] for x in (0, a) for y in (0, b) for z in (0, c)], dtype=float)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return V, F


def test_box_ratio_of_a_cube_and_of_a_rod():
    g = 2 * np.sqrt(3) / 15  # fTetWild's box: the bounding box grown by diag / 15 on every side
    assert box_ratio(*_box(1, 1, 1)) == pytest.approx((1 + g) ** 3, rel=1e-12)
    d = np.sqrt(1 + 1 + 100)
    assert box_ratio(*_box(1, 1, 10)) == pytest.approx((1 + 2 * d / 15) ** 2 * (10 + 2 * d / 15) / 10, rel=1e-12)


def test_coarse_outside_only_where_the_box_is_mostly_outside(monkeypatch):
    """The coarse outside is asked of fTetWild for a slender solid (a rod along the box diagonal), not a cube."""
    calls = []
    real = tetmesh.outer_sizing_field
    monkeypatch.setattr(tetmesh, "outer_sizing_field", lambda *a: calls.append(a[3]) or real(*a))
    tetrahedralize(*_box(1, 1, 1), edge_length=0.2, time_limit=None)
    assert calls == []
    V, F = _box(0.1, 0.1, 1)
    from scipy.spatial.transform import Rotation

    V = Rotation.align_vectors([[1, 1, 1]], [[0, 0, 1]])[0].apply(V)  # the rod along the box's diagonal
    assert box_ratio(V, F) > tetmesh.OUTER_BOX_RATIO
    Vt, T = tetrahedralize(V, F, edge_length=0.05, time_limit=None)
    assert calls == [tetmesh.OUTER_EDGE_FACTOR]
    P = Vt[T]
    vol = np.einsum("ij,ij->i", P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0])) / 6
    assert vol.sum() == pytest.approx(0.01, rel=2e-3)  # the rod's solid, nothing of the outside
