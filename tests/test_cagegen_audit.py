"""cagegen.audit: every defect of an input surface is detected, named, and (where safe) repaired."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cagegen.audit import audit_mesh, audit_self_intersections, check_mesh, repair_mesh
from cagegen.errors import CageOptionError, MeshInputError


def _ico(sub: int = 2, r: float = 1.0, c=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices, dtype=np.float64) + np.asarray(c), np.asarray(s.faces, dtype=np.int64)


@pytest.fixture(scope="module")
def ball():
    return _ico(2)  # 162 vertices, 320 faces


def _raises(V, F, *words, **kw):
    with pytest.raises(MeshInputError) as ei:
        check_mesh(V, F, **kw)
    msg = str(ei.value).lower()
    for w in words:
        assert w.lower() in msg, f"{w!r} not in message: {msg}"
    return msg


def test_clean_shapes_pass_with_right_figures():
    from nestmg import shapes

    V, F = shapes.sphere()
    a = audit_mesh(V, F, name="sphere")
    assert a.ok, str(a)
    assert a.genus == 0 and a.n_components == 1 and a.n_self_intersections == 0
    assert a.volume == pytest.approx(4.0 / 3.0 * np.pi, rel=0.02)  # marching-cubes unit sphere
    V, F = shapes.torus()
    a = audit_mesh(V, F, name="torus")
    assert a.ok, str(a)
    assert a.genus == 1
    # torus volume 2 pi^2 R r^2 with R = 1, r = 0.35
    assert a.volume == pytest.approx(2 * np.pi**2 * 0.35**2, rel=0.03)
    assert "ok" in str(a)


def test_open_mesh(ball):
    V, F = ball
    a = audit_mesh(V, F[1:])
    assert a.n_boundary_edges == 3 and not a.ok
    _raises(V, F[1:], "open boundary", "3 boundary edges")


def test_nan_vertex(ball):
    V, F = ball
    V = V.copy()
    V[7, 1] = np.nan
    a = audit_mesh(V, F)
    assert a.n_nonfinite_vertices == 1 and a.volume is None
    _raises(V, F, "NaN", "first: [7]")
    V[7, 1] = np.inf
    _raises(V, F, "infinite")


def test_duplicate_vertices_detected_and_merged(ball):
    V, F = ball
    # split vertex F[0,0] for face 0: same position, new index -> cracks the surface open
    V2 = np.vstack([V, V[F[0, 0]]])
    F2 = F.copy()
    F2[0, 0] = len(V)
    a = audit_mesh(V2, F2)
    assert a.n_duplicate_vertices == 1 and a.n_boundary_edges == 4  # 2 edges on each side of the crack
    _raises(V2, F2, "duplicate vertices: 1")
    V3, F3 = check_mesh(V2, F2, repair=True)
    assert V3.shape == V.shape and F3.shape == F.shape
    assert audit_mesh(V3, F3).ok
    assert F2[0, 0] == len(V)  # caller's array untouched


def test_degenerate_faces(ball):
    V, F = ball
    F2 = F.copy()
    F2[5] = [F[5, 0], F[5, 0], F[5, 1]]
    msg = _raises(V, F2, "degenerate (zero-area) faces: 1")
    assert "first: [5]" in msg
    # geometric degeneracy: three distinct, collinear corners (vertex moved onto the opposite edge)
    V2 = V.copy()
    a_, b_, c_ = F[10]
    V2[c_] = 0.5 * (V[a_] + V[b_])
    a = audit_mesh(V2, F)
    assert a.n_degenerate_faces >= 1
    _raises(V2, F, "degenerate")


def test_two_components_and_self_intersection():
    Va, Fa = _ico(2)
    Vb, Fb = _ico(2, c=(3.0, 0, 0))
    V = np.vstack([Va, Vb])
    F = np.vstack([Fa, Fb + len(Va)])
    a = audit_mesh(V, F)
    assert a.n_components == 2 and a.n_self_intersections == 0
    _raises(V, F, "several connected components: 2")
    # overlapping copies: components AND intersecting faces
    Vb, Fb = _ico(2, c=(0.5, 0, 0))
    V = np.vstack([Va, Vb])
    a = audit_mesh(V, F)
    assert a.n_self_intersections > 0
    _raises(V, F, "self-intersections", "components")
    assert audit_mesh(V, F, self_intersections=False).n_self_intersections is None


@pytest.mark.parametrize("shift", [0.5, 3.0])
def test_audit_completed_with_the_self_intersection_test_equals_the_full_audit(shift):
    """audit_self_intersections(audit_mesh(..., self_intersections=False)) is audit_mesh with the test, field
    for field, on overlapping (shift 0.5) and disjoint copies; the audit it completes is left as it was."""
    Va, Fa = _ico(2)
    Vb, Fb = _ico(2, c=(shift, 0, 0))
    V, F = np.vstack([Va, Vb]), np.vstack([Fa, Fb + len(Va)])
    cheap = audit_mesh(V, F, self_intersections=False)
    before = cheap.to_dict()
    done = audit_self_intersections(cheap, V, F)
    assert done.to_dict() == audit_mesh(V, F).to_dict()
    assert (done.n_self_intersections > 0) == (shift < 2) and cheap.to_dict() == before
    with pytest.raises(CageOptionError, match="self_intersections=False"):
        audit_self_intersections(done, V, F)  # already tested
    with pytest.raises(CageOptionError, match="self_intersections=False"):
        audit_self_intersections(cheap, Va, Fa)  # not an audit of these arrays


def test_flipped_orientation_and_repair(ball):
    V, F = ball
    Ff = F[:, ::-1].copy()
    a = audit_mesh(V, Ff)
    assert a.volume < 0 and a.n_inconsistent_edges == 0
    _raises(V, Ff, "inside-out", "negative volume")
    Vr, Fr = check_mesh(V, Ff, repair=True)
    ar = audit_mesh(Vr, Fr)
    assert ar.ok and ar.volume == pytest.approx(-a.volume)
    assert np.array_equal(Ff, F[:, ::-1])  # input not modified


def test_inconsistent_orientation_and_repair(ball):
    V, F = ball
    F2 = F.copy()
    F2[[3, 40, 100]] = F2[[3, 40, 100]][:, ::-1]
    a = audit_mesh(V, F2)
    assert a.n_inconsistent_edges == 9  # 3 isolated flipped faces x 3 edges
    _raises(V, F2, "inconsistent orientation: 9 edges")
    Vr, Fr = repair_mesh(V, F2)
    ar = audit_mesh(Vr, Fr)
    assert ar.ok and ar.volume > 0
    assert np.array_equal(Fr, F)  # the majority orientation is the outward one


def test_nonmanifold_edge(ball):
    V, F = ball
    a_, b_ = F[0, 0], F[0, 1]
    V2 = np.vstack([V, [[3.0, 3.0, 3.0]]])
    F2 = np.vstack([F, [[a_, b_, len(V)]]])  # a fin on an existing edge
    a = audit_mesh(V2, F2)
    assert a.n_nonmanifold_edges == 1
    _raises(V2, F2, "non-manifold edges: 1")


def test_nonmanifold_vertex():
    Va, Fa = _ico(1)
    Vb, Fb = _ico(1)
    # second ball touches the first at vertex 0: translate so its vertex 0 lands on Va[0] mirrored
    Vb = -Vb + 2 * Va[0]
    Fb = Fb[:, ::-1]  # mirroring flips orientation; undo it
    V = np.vstack([Va, np.delete(Vb, 0, axis=0)])
    remap = np.concatenate([[0], np.arange(1, len(Vb)) + len(Va) - 1])
    F = np.vstack([Fa, remap[Fb]])
    a = audit_mesh(V, F, self_intersections=False)
    assert a.n_nonmanifold_vertices == 1 and a.n_nonmanifold_edges == 0 and a.n_boundary_edges == 0
    _raises(V, F, "non-manifold vertices: 1", self_intersections=False)


def test_unreferenced_vertex_dropped_by_repair(ball):
    V, F = ball
    V2 = np.vstack([V, [[9.0, 9.0, 9.0]]])
    _raises(V2, F, "unreferenced vertices: 1")
    Vr, Fr = check_mesh(V2, F, repair=True)
    assert Vr.shape == V.shape and np.array_equal(Fr, F)


def test_structural_errors(ball):
    V, F = ball
    _raises(V[:, :2], F, "shape (n, 3)")
    _raises(V, F[:, :2], "shape (m, 3)")
    _raises(V, F.astype(float), "integer")
    _raises(V, np.zeros((0, 3), int), "empty")
    _raises(np.zeros((0, 3)), F, "empty")
    F2 = F.copy()
    F2[0, 0] = len(V)
    _raises(V, F2, "out of range")
    F2[0, 0] = -1
    _raises(V, F2, "out of range")
    with pytest.raises(MeshInputError, match="at least 4"):
        check_mesh(V, F[:2])


def test_absurd_sizes_and_zero_volume(ball):
    V, F = ball
    _raises(V * 1e10, F, "absurd size")
    _raises(V + 1e9, F, "absurd size", "origin")
    _raises(V * 0.0, F, "absurd size")
    # two-sided triangle pair: closed and manifold, but encloses nothing
    Vt = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    Ft = np.array([[0, 1, 2], [0, 2, 1]])
    a = audit_mesh(Vt, Ft)
    assert a.volume == 0.0
    _raises(Vt, Ft, "zero volume")


def test_check_mesh_returns_copies(ball):
    V, F = ball
    V0, F0 = V.copy(), F.copy()
    V2, F2, audit = check_mesh(V, F, return_audit=True)
    assert audit.ok and V2 is not V and F2 is not F
    V2[:] = 0
    F2[:] = 0
    assert np.array_equal(V, V0) and np.array_equal(F, F0)
    d = audit.to_dict()
    assert d["ok"] is True and d["n_faces"] == 320


def test_edge_counts_match_trimesh_on_random_holes():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from cagegen._geometry import edge_stats

    V, F = _ico(2)

    @settings(max_examples=25, deadline=None)
    @given(st.sets(st.integers(0, len(F) - 1), min_size=1, max_size=60))
    def check(removed):
        G = np.delete(F, sorted(removed), axis=0)
        es = edge_stats(G, len(V))
        m = trimesh.Trimesh(V, G, process=False)
        n_boundary = len(trimesh.grouping.group_rows(m.edges_sorted, require_count=1))
        assert es.n_boundary_edges == n_boundary
        assert es.n_edges == len(m.edges_unique)
        assert es.n_inconsistent_edges == 0 and es.n_nonmanifold_edges == 0

    check()


def _with_a_cap(V, F):
    """Insert the midpoint c of an edge ab on one side only and close the T-junction with the cap (a, b, c)."""
    a, b, x = (int(i) for i in F[0])
    c = len(V)
    V2 = np.vstack([V, 0.5 * (V[a] + V[b])])
    F2 = np.vstack([F[1:], [[a, c, x], [c, b, x], [a, b, c]]])
    return V2, F2


def test_repair_flips_zero_area_caps_of_stl_exports():
    """CAD STL exports carry caps (a corner on the opposite edge, area 0): refused by the audit with a hint,
    repaired exactly by an edge flip (same surface area and volume, audit clean)."""
    import igl

    from cagegen.audit import flip_cap_faces
    from nestmg.shapes import sphere

    V, F = sphere(8)
    V2, F2 = _with_a_cap(V, F)
    a = audit_mesh(V2, F2)
    assert not a.ok and a.n_degenerate_faces == 1 and "--repair" in str(a)
    F3 = flip_cap_faces(V2, F2)
    assert len(F3) == len(F2)
    b = audit_mesh(V2, F3)
    assert b.ok, str(b)
    np.testing.assert_allclose(igl.doublearea(V2, F3).sum(), igl.doublearea(V, F).sum(), rtol=1e-12)
    assert b.volume == pytest.approx(audit_mesh(V, F).volume, rel=1e-12)
    V4, F4 = repair_mesh(V2, F2)  # the default repair does it too
    assert audit_mesh(V4, F4).ok
