"""The fine edge follows the solid (its mean thickness), not a CAD export's arbitrary triangles."""

import numpy as np
import pytest

from nestmg.sizing import plan_hierarchy


def _box(a, b, c, n=1):
    """A closed box a x b x c whose faces are n x n grids of two long triangles per cell."""
    import trimesh

    m = trimesh.creation.box(extents=(a, b, c))
    for _ in range(n - 1):
        m = m.subdivide()
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def test_thin_plate_of_twelve_triangles_is_sized_by_its_thickness():
    V, F = _box(1.0, 1.0, 0.04)  # 12 faces: mean edge ~0.9, thickness 0.04
    plan = plan_hierarchy(V, F, 2, meshed_fraction=1 / 8, mesh_edge_factor=2.0, mesh_time_budget=None)
    vol, area = 0.04, 2 * (1 + 0.04 + 0.04)
    assert plan.rule == "thickness"
    assert plan.edge_lengths[0] == pytest.approx(vol / area / 2.0, rel=1e-9)  # two meshed edges across


def test_finely_triangulated_solid_keeps_the_input_resolution():
    V, F = _box(1.0, 1.0, 1.0, n=5)  # 3,072 faces, edges ~1/16: finer than the thickness 1/6
    plan = plan_hierarchy(V, F, 2, meshed_fraction=1 / 8, mesh_edge_factor=2.0, mesh_time_budget=None)
    E = V[F[:, [1, 2, 0]]] - V[F]
    assert plan.rule == "input resolution"
    assert plan.edge_lengths[0] == pytest.approx(np.linalg.norm(E, axis=2).mean() / 2.0, rel=1e-9)


def test_a_budget_still_caps_a_very_thin_part():
    V, F = _box(1.0, 1.0, 0.002)
    plan = plan_hierarchy(V, F, 2, meshed_fraction=1 / 8, mesh_edge_factor=2.0, mesh_time_budget=None,
                          max_tets=200_000)
    assert plan.rule == "max_tets"
    assert plan.edge_lengths[0] > 0.002 / 2.004 / 2.0
