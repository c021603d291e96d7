"""fTetWild's coarse outside (``nestmg.tetmesh.outer_sizing_field``): same solid, fewer tets worked on."""

import numpy as np
import pytest

pytest.importorskip("pytetwild")

from nestmg import shapes  # noqa: E402
from nestmg.tetmesh import (  # noqa: E402
    outer_sizing_field, tetrahedralize)


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


def test_graded_mesh_has_the_uniform_meshs_solid():
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
