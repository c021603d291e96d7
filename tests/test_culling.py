"""Conservative collision culling with nested layers (cagegen.culling)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cagegen import CageOptionError, cull_collisions, solids_intersect, verify_nesting


@pytest.fixture(scope="module")
def spheres():
    """Three nested layers: a bumpy sphere of radius ~1 inside spheres of radius 1.25 and 1.6."""
    s = trimesh.creation.icosphere(subdivisions=3)
    V = s.vertices * (1.0 + 0.08 * np.sin(5 * s.vertices[:, [0]]) * np.cos(3 * s.vertices[:, [1]]))
    c1, c2 = trimesh.creation.icosphere(subdivisions=2), trimesh.creation.icosphere(subdivisions=1)
    layers = [(V, s.faces), (1.25 * c1.vertices, c1.faces), (1.6 * c2.vertices, c2.faces)]
    assert verify_nesting(layers).ok
    return layers


def _moved(layers, t):
    return [(V + np.asarray(t, dtype=float), F) for V, F in layers]


def test_decides_at_the_coarsest_disjoint_pair(spheres):
    far = cull_collisions(spheres, _moved(spheres, [3.5, 0.2, 0.0]))  # 1.6 + 1.6 < 3.5
    assert far.separated and far.decided_at == (2, 2) and len(far.tests) == 1
    mid = cull_collisions(spheres, _moved(spheres, [2.8, 0.0, 0.0]))  # outer cages meet, middle ones not
    assert mid.separated and mid.decided_at == (1, 1)
    assert mid.tests[0]["crossing"] > 0 and not mid.tests[1]["intersect"]


def test_intersecting_inputs_and_containment(spheres):
    hit = cull_collisions(spheres, _moved(spheres, [1.5, 0.0, 0.0]))
    assert not hit.separated and hit.decided_at == (0, 0) and hit.tests[-1]["crossing"] > 0
    small = [(0.3 * V, F) for V, F in spheres]  # strictly inside the other object's input: no crossing
    inside = cull_collisions(spheres, small)
    assert not inside.separated and inside.tests[-1]["contained"] and inside.tests[-1]["crossing"] == 0


def test_agrees_with_the_direct_test_on_the_inputs(spheres, rng):
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    other = [(V @ rot.T * [0.7, 1.0, 0.8], F) for V, F in spheres]
    for _ in range(12):
        d = rng.standard_normal(3)
        t = d / np.linalg.norm(d) * rng.uniform(1.2, 3.0)
        B = _moved(other, t)
        rep = cull_collisions(spheres, B)
        direct = solids_intersect(*spheres[0], *B[0])
        assert rep.separated == (not direct["intersect"])
        if not rep.separated:  # the box filter keeps every crossing pair
            full = solids_intersect(*spheres[0], *B[0], box=np.array([[-1e9] * 3, [1e9] * 3]))
            assert rep.tests[-1]["crossing"] == full["crossing"] == direct["crossing"]


def test_layer_counts_may_differ_and_empty_is_refused(spheres):
    from cagegen.culling import _pairs

    assert _pairs(1, 3) == [(0, 2), (0, 1), (0, 0)] and _pairs(3, 2) == [(2, 1), (1, 0), (0, 0)]
    B = _moved(spheres, [2.4, 0.0, 0.0])
    rep = cull_collisions(spheres[:1], B)
    assert [t["layers"] for t in rep.tests] == [[0, 2], [0, 1], [0, 0]][: len(rep.tests)]
    direct = solids_intersect(*spheres[0], *B[0])
    assert rep.tests[0]["intersect"] and rep.separated == (not direct["intersect"])
    with pytest.raises(CageOptionError):
        cull_collisions([], spheres)
