"""Tests of the cage tightening post-step (cagegen.skeleton.tighten, issue 29 item 5).

Procedural shapes only.
"""

from __future__ import annotations

import igl
import numpy as np
import trimesh

from cagegen import verify_nesting
from cagegen.skeleton.tighten import tighten_cage
from nestmg.shapes import sphere


def _spiky_cage():
    """M: the unit sphere; cage: an icosphere of radius 1.6 with one vertex pulled out to radius 3.5 (a
    spike, as the pre-inflation leaves on the zoo's skeleton cages)."""
    V, F = sphere(16)
    ico = trimesh.creation.icosphere(subdivisions=1)
    C = 1.6 * np.asarray(ico.vertices, float)
    C[0] *= 3.5 / 1.6
    return V, F, C, np.asarray(ico.faces, np.int64)


def test_tighten_pulls_a_spike_in_and_keeps_the_certificate():
    V, F, C, Fc = _spiky_cage()
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    gap = 0.0025 * diag
    assert verify_nesting([(V, F), (C, Fc)], min_gap=0.0025).ok
    C2, info = tighten_cage(C, Fc, V, F, gap)
    rep = verify_nesting([(V, F), (C2, Fc)], min_gap=0.0025)
    assert rep.ok and info["distance"] >= gap * (1 - 1e-9)
    d0 = np.sqrt(igl.point_mesh_squared_distance(C, V, F)[0])
    d1 = np.sqrt(igl.point_mesh_squared_distance(C2, V, F)[0])
    # the spike's tip (2.5 away) comes in to a few gaps; no vertex moves away from M
    assert d0[0] > 2.4 and d1[0] < 0.1 * d0[0]
    assert (d1 <= d0 + 1e-12).all() and d1.max() < 0.5 * d0.max()
    assert info["vertex_distance_after"][1] < info["vertex_distance_before"][1]


def test_tighten_stops_at_the_gap_where_the_cage_is_already_close():
    """A cage already within ``keep`` gaps of M everywhere does not move."""
    V, F = sphere(16)
    ico = trimesh.creation.icosphere(subdivisions=2)
    gap = 0.0025 * float(np.linalg.norm(np.ptp(V, axis=0)))
    C = 1.05 * np.asarray(ico.vertices, float) / 0.95  # ~0.1 off M: far less than keep x gap = 0.87
    C2, info = tighten_cage(C, np.asarray(ico.faces, np.int64), V, F, gap, keep=100.0)
    assert info["rounds"] == 0 and np.array_equal(C2, C)
