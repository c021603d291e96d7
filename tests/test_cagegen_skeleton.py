"""Tests of the skeleton cage backend (cagegen.skeleton) on procedural articulated shapes.

Shapes: ``nestmg.shapes.star_of_capsules`` and ``stick_figure``, implicit unions of capsules meshed by
marching cubes, with their known skeletons (capsule axes).
"""

from __future__ import annotations

import igl
import numpy as np
import pytest

from cagegen import MeshInputError, build_cages, verify_nesting
from cagegen.skeleton import Skeleton, read_skeleton, skeleton_cage, write_skeleton
from cagegen.skeleton.cage import best_quad
from cagegen.skeleton.field import GuidingField
from nestmg.shapes import star_of_capsules, stick_figure


# ----------------------------------------------------------------------------- shapes
@pytest.fixture(scope="module")
def star():
    return star_of_capsules()


@pytest.fixture(scope="module")
def star_cage(star):
    V, F, S = star
    return skeleton_cage(V, F, S, bending="given")


# ----------------------------------------------------------------------------- skeleton graph / file
def test_skeleton_file_round_trip(tmp_path, star):
    _, _, S = star
    p = tmp_path / "star.skel"
    write_skeleton(p, S)
    T = read_skeleton(p)
    assert np.array_equal(T.nodes, S.nodes) and np.array_equal(T.edges, S.edges) and T.bending == S.bending
    with pytest.raises(FileExistsError):
        write_skeleton(p, S)
    assert len(S.leaves) == 4 and S.branching == [0] and len(S.chains()) == 4


@pytest.mark.parametrize("text, match", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\ne 0 1\ne 1 2\ne 2 0\n", "tree"),
    ("v 0 0 0\nv 1 0 0\ne 0 1\nb 0\n", "degree 1"),
    ("v 0 0 0\nv 1 0 x\ne 0 1\n", "cannot parse"),
    ("v 0 0 0\nv 1 0 0\ne 0 5\n", "out of range"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\ne 0 1\ne 2 3\ne 1 0\n", "duplicate"),
])
def test_bad_skeleton_files(tmp_path, text, match):
    p = tmp_path / "bad.skel"
    p.write_text(text)
    with pytest.raises(MeshInputError, match=match):
        read_skeleton(p)


def test_skeleton_outside_the_surface_is_rejected(star):
    V, F, S = star
    bad = Skeleton(S.nodes * 1.5, S.edges, S.bending)  # tips at 1.5: outside the arms (end at 1.2)
    with pytest.raises(MeshInputError, match="outside the surface"):
        skeleton_cage(V, F, bad, bending="given")


# ----------------------------------------------------------------------------- pieces
def test_best_quad_of_an_ellipse_is_its_diagonal_corners():
    th = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    G = np.column_stack([2.0 * np.cos(th), np.sin(th), np.zeros_like(th)])
    q, axis = best_quad(G, np.array([0.0, 0.0, 1.0]))
    assert abs(abs(axis[0]) - 1.0) < 1e-9  # first principal axis: the long one
    assert len({tuple(p) for p in q}) == 4
    # one corner per quadrant, counter-clockwise around +z
    ang = np.arctan2(q[:, 1], q[:, 0])
    quadrant = np.floor(np.mod(ang, 2 * np.pi) / (np.pi / 2)).astype(int)
    assert sorted(quadrant.tolist()) == [0, 1, 2, 3]
    assert np.all(np.diff(np.unwrap(ang)) > 0)
    # corner (+,+) maximises sx x + sy y (spreads sx = 2 sy): on x = 2cos t, y = sin t that is t = atan(1/4)
    # (14 deg; samples at 9 and 18 deg), i.e. the point at polar angle atan(tan(t)/2) in (4, 10) deg
    assert np.deg2rad(4) < ang[0] < np.deg2rad(10)


def test_harmonic_field_bounds_and_integral_lines(star):
    V, F, S = star
    c, d = 0.5 * (V.min(0) + V.max(0)), np.linalg.norm(np.ptp(V, 0))
    Vn = (V - c) / d
    Sn = S.transformed(1 / d, c).resampled(0.01)
    fld = GuidingField(Vn, F, Sn.nodes, edge_length=0.03)
    assert fld.f.min() >= -1e-9 and fld.f.max() <= 1 + 1e-9
    # f = 0 imposed within a tet edge of the skeleton
    assert fld.skeleton_offset["max"] < 0.03
    # lines from points around an arm axis end on M, farther from the axis than they started
    x = Sn.nodes[:, 0].max() * 0.6
    P = np.array([[x, 0.03, 0.0], [x, -0.03, 0.0], [x, 0.0, 0.03]])
    end, ok = fld.trace(P)
    assert ok.all()
    d2, _, _ = igl.point_mesh_squared_distance(end, Vn, F)
    assert np.sqrt(d2).max() < 1e-9
    assert np.all(np.linalg.norm(end[:, 1:], axis=1) > 0.05)  # arm radius 0.2/diag ~ 0.057


# ----------------------------------------------------------------------------- the cage
def test_star_cage_sections_and_certificate(star, star_cage):
    V, F, S = star
    c = star_cage
    # one quad section per control node: 4 bending + 4 leaves
    assert len(c.sections) == len(S.bending) + len(S.leaves) == 8
    diag = np.linalg.norm(np.ptp(V, 0))
    for s in c.sections:
        assert s["quad"].shape == (4, 3) and len({tuple(p) for p in s["quad"]}) == 4
        d2, _, _ = igl.point_mesh_squared_distance(s["quad"], V, F)
        assert np.sqrt(d2).max() < 1e-9 * diag  # tight-cage vertices lie on M
    # topology: 4 tubes of 4 side quads from the bending section to the tip, 4 leaf caps, one junction
    assert len(c.quads) == 4 * 4 + 4
    assert len(c.V) == 32 and len(c.F) == 2 * len(c.quads) + len(c.tris)
    rep = verify_nesting([(V, F), (c.V, c.F)])
    assert rep.ok, rep.pairs[0].reason
    assert rep.pairs[0].min_winding > 0.99
    assert c.info["verification"]["ok"]


def test_star_cage_quads_written_and_triangulation_consistent(tmp_path, star_cage):
    c = star_cage
    p = tmp_path / "cage.obj"
    c.write_obj(p, quads=True)
    lines = [ln.split() for ln in p.read_text().splitlines() if ln.startswith("f ")]
    assert sum(len(t) == 5 for t in lines) == len(c.quads) and sum(len(t) == 4 for t in lines) == len(c.tris)
    with pytest.raises(FileExistsError):
        c.write_obj(p)
    # every quad's boundary edges are edges of the certified triangles with the same orientation
    de = {(int(a), int(b)) for t in c.F for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    for q in c.quads:
        assert all((int(q[k]), int(q[(k + 1) % 4])) in de for k in range(4))


def _max_dist(Vc, Fc, V, F, n=20000):
    """Largest distance from the cage surface (vertices + area-uniform samples) to M, over M's diagonal."""
    rng = np.random.default_rng(0)
    a = np.linalg.norm(np.cross(Vc[Fc[:, 1]] - Vc[Fc[:, 0]], Vc[Fc[:, 2]] - Vc[Fc[:, 0]]), axis=1)
    f = rng.choice(len(Fc), size=n, p=a / a.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    P = np.einsum("ij,ijk->ik", np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1), Vc[Fc[f]])
    d2, _, _ = igl.point_mesh_squared_distance(np.vstack([Vc, P]), V, F)
    return float(np.sqrt(d2.max())) / float(np.linalg.norm(np.ptp(V, 0)))


@pytest.mark.slow
def test_star_cage_tightness_against_nested_at_equal_face_count(star, star_cage):
    """Measured (benchmarks/cages_skeleton.py): on this star the skeleton cage is NOT tighter than the
    nested cage with as many faces (max distance 0.090 vs 0.064 of the diagonal); it must stay within
    1.6x of it and below 0.12 of the diagonal (a regression guard on the inflation, not the issue's 'far coarser')."""
    V, F, _ = star
    c = star_cage
    d_skel = _max_dist(c.V, c.F, V, F)
    layers = build_cages(V, F, face_counts=[len(c.F)], method="nested", fallback=None)
    d_nest = _max_dist(*layers[1], V, F)
    assert d_skel < 0.12, d_skel
    assert d_skel < 1.6 * d_nest, (d_skel, d_nest)


@pytest.mark.slow
def test_stick_figure_cage_via_build_cages():
    V, F, S = stick_figure()
    layers, info = build_cages(V, F, face_counts=[100], method="skeleton", return_info=True,
                               skeleton=S, bending="given")
    assert info["certified"]
    sk = info["backend"]["skeleton"]
    # 4 bending + 5 leaves sections; 2 branching nodes (pelvis: 3 bones, neck: 4 bones)
    assert sk["skeleton"]["n_leaves"] == 5 and sk["skeleton"]["n_branching"] == 2
    assert sk["n_quads"] >= 4 * 4 + 5
    assert len(layers[1][1]) < 200
