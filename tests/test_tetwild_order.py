"""The surface fTetWild gets is renumbered along a Morton curve (``nestmg.tetmesh.spatial_order``)."""

import numpy as np
import pytest

from nestmg import shapes, tetmesh
from nestmg.tetmesh import spatial_order


def _shuffled(V, F, seed=0):
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(V))
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(perm))
    return V[perm], rank[F][rng.permutation(len(F))]


def _face_jump(V, F):
    """Median distance between consecutive faces' centroids over the mean edge length."""
    C = V[F].mean(axis=1)
    edge = np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean()
    return float(np.median(np.linalg.norm(np.diff(C, axis=0), axis=1)) / edge)


def _oriented_triangles(V, F):
    """Each face as its three corner points, rotated to start at the smallest (orientation kept)."""
    out = set()
    for f in F:
        tri = [tuple(V[i]) for i in f]
        k = tri.index(min(tri))
        out.add(tuple(tri[k:] + tri[:k]))
    return out


def test_spatial_order_is_the_same_surface_renumbered_locally():
    V, F = _shuffled(*shapes.torus(res=24))
    assert _face_jump(V, F) > 10  # a random order: consecutive faces far apart
    W, G = spatial_order(V, F)
    assert sorted(map(tuple, W)) == sorted(map(tuple, V))  # a permutation of the vertices
    assert _oriented_triangles(W, G) == _oriented_triangles(V, F)  # the same faces, same orientation
    assert _face_jump(W, G) < 2.0
    # already ordered: a second pass changes nothing
    W2, G2 = spatial_order(W, G)
    assert np.array_equal(W2, W) and np.array_equal(G2, G)


def test_tetrahedralize_hands_fTetWild_the_ordered_surface(monkeypatch):
    seen = {}

    def fake(mesher, V, F, opts, deadline, cpu_budget=None):
        seen["V"], seen["F"] = V, F
        raise tetmesh.TetMeshError("stop here")

    monkeypatch.setattr(tetmesh, "_mesher_call", fake)
    V, F = _shuffled(*shapes.torus(res=24))
    with pytest.raises(tetmesh.TetMeshError, match="stop here"):
        tetmesh.tetrahedralize(V, F, edge_length=0.1, time_limit=None)
    assert len(seen["F"]) == len(F) and _face_jump(seen["V"], seen["F"]) < 2.0
