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


# ----------------------------------------------------------------------------- robustness additions
def _junction_star(seed: int, n_arms: int):
    """A star skeleton (centre 0; arm k: bending node 1+2k at distance 1, leaf 2+2k at distance 2) with
    random quad sections (random radii and corner angles) in the planes orthogonal to the arms."""
    from cagegen.skeleton.cage import CrossSection, _frame

    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n_arms, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    nodes, edges, bend = [np.zeros(3)], [], []
    for d in dirs:
        nodes += [d, 2 * d]
        b = len(nodes) - 2
        edges += [(0, b), (b, b + 1)]
        bend.append(b)
    S = Skeleton(np.array(nodes), np.array(edges), bend)
    sections = {}
    for k, d in enumerate(dirs):
        u, w = _frame(d)
        th = rng.uniform(0, 2 * np.pi) + np.array([0, 0.5, 1, 1.5]) * np.pi + rng.uniform(-0.3, 0.3, 4)
        rad = rng.uniform(0.2, 1.0, 4)
        for nd, dist in ((1 + 2 * k, 1.0), (2 + 2 * k, 2.0)):
            q = d * dist + rad[:, None] * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * w)
            sections[nd] = CrossSection(nd, d * dist, d, 1.0, q, q, q)
    cc = [(ch, [n for n in ch.nodes if n in bend or S.degree[n] == 1]) for ch in S.chains()]
    return S, sections, cc


def test_junction_steiner_vertex_fix():
    """Paper Sec. 3.3: a junction hull that misses a section edge gets the edge's midpoint as a Steiner
    vertex. On this random 4-arm junction (found by search: the first hull misses one edge) the fix
    adds exactly one vertex and the tight cage is closed and manifold; without it, JunctionError."""
    from cagegen.skeleton.cage import JunctionError, tight_cage

    S, sections, cc = _junction_star(15, 4)
    with pytest.raises(JunctionError, match="junction at node 0"):
        tight_cage(S, sections, cc, max_steiner_rounds=0)
    tc = tight_cage(S, sections, cc)
    assert tc["n_steiner"] == 1
    assert len(tc["V"]) == 8 * 4 + 1
    steiner = 32
    owner = [nd for nd, r in tc["section_rings"].items() if steiner in r]
    assert len(owner) == 1
    r = tc["section_rings"][owner[0]]
    i = r.index(steiner)
    a, b = r[i - 1], r[(i + 1) % len(r)]
    assert np.allclose(tc["V"][steiner], 0.5 * (tc["V"][a] + tc["V"][b]))  # midpoint of a section edge
    # the two tube sides along the split edge became triangles; closed surface: V - E + F = 2
    F = tc["F"]
    E = {tuple(sorted(e)) for t in F for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert len(tc["V"]) - len(E) + len(F) == 2
    assert len(tc["quads"]) == 4 * 4 + 4 - 1  # one side quad of the split edge's tube is now a strip
    assert tc["n_steiner_per_junction"] == {0: 1}


def test_junction_steiner_vertex_cap():
    """The Steiner vertices of one junction are capped: a hull that would need more raises a
    JunctionError naming the cap (on spot a junction once took 431 midpoints before failing)."""
    from cagegen.skeleton.cage import JunctionError, tight_cage

    S, sections, cc = _junction_star(15, 4)
    with pytest.raises(JunctionError, match=r"Steiner-vertex cap reached \(0 added, 1 more needed, cap 0") as e:
        tight_cage(S, sections, cc, max_steiner_per_junction=0)
    assert (e.value.junction, e.value.section) == (0, e.value.section) and e.value.section in S.bending
    tc = tight_cage(S, sections, cc, max_steiner_per_junction=1)  # exactly enough
    assert tc["n_steiner"] == 1 and tc["n_steiner_per_junction"] == {0: 1}


def test_merge_close_branching_nodes():
    """Two branching nodes 0.6 apart inside a unit sphere (inscribed radius ~0.7) merge into one junction
    of degree 4 at the middle with merge=2 (0.6 < 1.4), and stay apart with merge=0.5 (0.6 > 0.35)."""
    import trimesh

    from cagegen.skeleton.extract import _merge_close_branching

    s = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(s.vertices), np.asarray(s.faces, np.int64)
    P = np.array([[-0.3, 0, 0], [0.3, 0, 0], [-0.6, 0.4, 0], [-0.6, -0.4, 0], [0.6, 0.4, 0], [0.6, -0.4, 0]])
    E = np.array([[0, 1], [0, 2], [0, 3], [1, 4], [1, 5]])
    P2, E2, merged = _merge_close_branching(P, E, V, F, merge=2.0)
    assert len(P2) == 5 and len(E2) == 4 and len(merged) == 1
    deg = np.bincount(E2.ravel())
    assert deg.max() == 4
    assert np.allclose(P2[deg.argmax()], 0.0)
    assert abs(merged[0]["length"] - 0.6) < 1e-12
    P3, E3, merged3 = _merge_close_branching(P, E, V, F, merge=0.5)
    assert len(P3) == 6 and len(E3) == 5 and merged3 == []


def test_move_without_intersection_freezes_offending_vertices():
    """A move that pushes one corner of a cube through the opposite side: the vertices of the faces
    still intersecting after the step-backs do not move, the others do, and the result is free of
    self-intersections."""
    import trimesh

    from cagegen._geometry import self_intersection_pairs
    from cagegen.skeleton.inflate import _move_without_intersection

    c = trimesh.creation.box()
    V, F = np.asarray(c.vertices, float), np.asarray(c.faces, np.int64)
    dv = 0.1 * V
    i = int(np.argmin(V.sum(axis=1)))  # corner (-.5,-.5,-.5)
    dv[i] = -2.2 * V[i]  # through the cube to beyond the opposite corner
    assert len(self_intersection_pairs(V + dv, F))
    V1, used, _, partly = _move_without_intersection(V, F, dv, backoff=0.1, max_backoff=0)
    assert partly and len(self_intersection_pairs(V1, F)) == 0
    assert np.allclose(V1[i], V[i])
    moved = np.flatnonzero(np.linalg.norm(V1 - V, axis=1) > 1e-12)
    assert len(moved) >= 1 and np.allclose(V1[moved], 1.1 * V[moved])


def test_section_positions_order():
    """Relocation order of a failing section: the node itself, then alternately both sides within one
    radius (bending node), or inwards up to half the chain (leaf)."""
    from cagegen.skeleton.backend import _section_positions
    from cagegen.skeleton.graph import Chain

    nodes = np.column_stack([np.arange(11) * 0.1, np.zeros(11), np.zeros(11)])
    S = Skeleton(nodes, np.column_stack([np.arange(10), np.arange(1, 11)]))
    ch = Chain(list(range(11)))  # arc length 0 .. 1
    assert list(_section_positions(S, ch, 5, 0.25, False)) == [5, 4, 6, 3, 7]
    assert list(_section_positions(S, ch, 0, 0.25, True)) == [0, 1, 2, 3, 4, 5]
    assert list(_section_positions(S, ch, 10, 0.25, True)) == [10, 9, 8, 7, 6, 5]
    assert list(_section_positions(S, ch, 5, 0.25, None)) == [5]


def _mirror_error(P, point, normal):
    """Largest distance from the mirror image of each point to the nearest point of the set."""
    from scipy.spatial import cKDTree

    from cagegen.skeleton.symmetry import reflect

    d, _ = cKDTree(P).query(reflect(P, np.asarray(point), np.asarray(normal)))
    return float(d.max())


def test_symmetry_detection_and_enforcement_on_the_stick_figure():
    """Paper Sec. 3.4 on the stick figure (mirror-symmetric about x = 0 by construction): the detected
    plane is x = 0; with symmetry="auto" the tight cage's sections are exact mirror images (two arm and
    two leg pairs; torso and head crossed by the plane), without it they are not; both certified."""
    from cagegen.skeleton.symmetry import detect_mirror_plane

    V, F, S = stick_figure()
    diag = float(np.linalg.norm(np.ptp(V, 0)))
    plane = detect_mirror_plane(V, F)
    assert plane["symmetric"] and plane["score"] < 0.005
    assert abs(plane["normal"][0]) > 0.999 and abs(plane["point"][0]) < 1e-3 * diag
    c0 = skeleton_cage(V, F, S, bending="given")
    c1 = skeleton_cage(V, F, S, bending="given", symmetry="auto")
    assert c0.info["verification"]["ok"] and c1.info["verification"]["ok"]
    si = c1.info["symmetry"]
    assert si["detected"] and len(si["pairs"]) >= 4 and len(si["self"]) >= 1
    assert c1.info["tight_cage_shrink_steps"] == 0 and not c1.info["assembly_dropped"]
    n = np.array(si["normal"])
    p = np.array(si["point"])
    err1 = _mirror_error(c1.tight_V, p, n)
    err0 = _mirror_error(c0.tight_V, p, n)
    assert err1 < 1e-9 * diag, err1
    assert err0 > 1e-4 * diag, err0  # the enforcement did something
    # the inflation does not enforce it, but the certified cage stays far more symmetric (measured:
    # 0.0072 vs 0.058 of the diagonal)
    assert _mirror_error(c1.V, p, n) < 0.5 * _mirror_error(c0.V, p, n)
    assert len(c1.F) == len(c0.F)


def test_unfold_opens_a_folded_vertex():
    """unfold: a coarse sphere whose top vertex is dragged past a ring neighbour (6 faces folded over,
    smallest normal cosine -0.93, no self-intersection) is unfolded in one round."""
    import igl

    from cagegen._geometry import self_intersection_pairs
    from cagegen.skeleton.inflate import _fold_cosines, unfold
    from nestmg.shapes import sphere

    V, F = sphere(6)
    V = V / np.linalg.norm(V, axis=1, keepdims=True)
    top = int(np.argmax(V[:, 2]))
    nb = igl.adjacency_list(F)[top][0]
    V[top] = V[top] + 1.5 * (V[nb] - V[top]) + np.array([0.0, 0.0, -0.075])
    c = _fold_cosines(V, F)
    assert len(self_intersection_pairs(V, F)) == 0
    assert (c < -0.3).any(axis=1).sum() == 6 and c.min() < -0.9
    V2, rounds, left = unfold(V, F)
    assert (rounds, left) == (1, 0)
    assert len(self_intersection_pairs(V2, F)) == 0
    assert _fold_cosines(V2, F).min() > 0.8


def test_crease_push_contains_a_dented_sphere():
    """crease_push: a coarse cage (102 vertices) around a unit sphere M (1,806 vertices) with one
    vertex dented to 0.1 of its radius (17 vertices of M outside, max signed distance 0.185) ends with
    M inside, no self-intersection, no fold."""
    import igl

    from cagegen._geometry import self_intersection_pairs
    from cagegen.skeleton.inflate import crease_push
    from nestmg.shapes import sphere

    Vm, Fm = sphere(20)
    Vc, Fc = sphere(6)
    Vc = 1.08 * Vc / np.linalg.norm(Vc, axis=1, keepdims=True)
    Vc[np.argmax(Vc[:, 2])] *= 0.1
    s0, *_ = igl.signed_distance(Vm, Vc, Fc)
    assert (s0 > 0).sum() == 17 and s0.max() > 0.18
    V2, info = crease_push(Vc, Fc, Vm)
    assert info["outside_per_round"][0] == 17 and info["outside"] == 0 and info["folds"] == 0
    assert info["best_round"] == len(info["outside_per_round"]) - 1 <= 8
    s, *_ = igl.signed_distance(Vm, V2, Fc)
    assert s.max() < 0 and len(self_intersection_pairs(V2, Fc)) == 0
    assert np.abs(V2 - Vc).max() < 1.0  # only the dent moved far
    assert np.sort(np.linalg.norm(V2 - Vc, axis=1))[-10] < 0.1


def test_extraction_that_collapses_to_one_node_is_a_named_cage_error(star, monkeypatch):
    """When pruning leaves a single node (a limbless shape), extraction raises a CageError naming the
    step and the remedy, not a MeshInputError from the Skeleton constructor."""
    pytest.importorskip("pygel3d")
    from cagegen.errors import CageError, MeshInputError
    from cagegen.skeleton import extract

    V, F, _ = star
    monkeypatch.setattr(extract, "_prune", lambda P, E, r, prune: (P[:1], E[:0], len(P) - 1))
    with pytest.raises(CageError, match="1 node.*no edge.*give a skeleton") as ei:
        extract.extract_skeleton(V, F)
    assert not isinstance(ei.value, MeshInputError)


def test_move_without_intersection_fin_guard():
    """fin_cos: dragging the top vertex of a coarse sphere past a ring neighbour folds 6 faces over
    (normal cosine -0.93, no self-intersection); without the guard the move is taken whole, with
    fin_cos=-0.9 it steps back until no new fin is left (and the vertex still moves)."""
    import igl

    from cagegen._geometry import self_intersection_pairs
    from cagegen.skeleton.inflate import _fold_cosines, _move_without_intersection
    from nestmg.shapes import sphere

    V, F = sphere(6)
    V = V / np.linalg.norm(V, axis=1, keepdims=True)
    top = int(np.argmax(V[:, 2]))
    nb = igl.adjacency_list(F)[top][0]
    dv = np.zeros_like(V)
    dv[top] = 1.5 * (V[nb] - V[top]) + np.array([0.0, 0.0, -0.075])
    V0, _, _, partly0 = _move_without_intersection(V, F, dv, backoff=0.1, max_backoff=40)
    assert not partly0 and np.allclose(V0, V + dv) and _fold_cosines(V0, F).min() < -0.9
    V1, _, n_back, _ = _move_without_intersection(V, F, dv, backoff=0.1, max_backoff=40, fin_cos=-0.9)
    assert _fold_cosines(V1, F).min() >= -0.9 and n_back >= 1
    assert 0 < np.linalg.norm(V1[top] - V[top]) < np.linalg.norm(dv[top])
    assert len(self_intersection_pairs(V1, F)) == 0


def test_crease_push_keeps_its_input_when_no_round_beats_it(monkeypatch):
    """crease_push: when the first unfold and every round leave more vertices of M outside than the
    input (here: an unfold that shrinks the cage), the input is returned (best_round -1)."""
    from cagegen.skeleton import inflate
    from nestmg.shapes import sphere

    Vm, _ = sphere(20)
    Vc, Fc = sphere(6)
    Vc = 1.08 * Vc / np.linalg.norm(Vc, axis=1, keepdims=True)
    Vc[np.argmax(Vc[:, 2])] *= 0.5  # a dent: some of M outside the input
    monkeypatch.setattr(inflate, "unfold", lambda V, F, *a, **k: (0.8 * np.asarray(V), 0, 0))
    V2, info = inflate.crease_push(Vc, Fc, Vm, rounds=3)
    assert 0 < info["outside_input"] < min(info["outside_per_round"])
    assert info["best_round"] == -1 and info["outside"] == info["outside_input"]
    assert info["fins_input"] == 0 and np.array_equal(V2, Vc)
    # the same input with a fin (the bottom vertex dragged past a ring neighbour, normal cosine < -0.9)
    # is not kept: a fin traps the Nested Cages flow
    import igl

    from cagegen.skeleton.inflate import _fold_cosines

    bot = int(np.argmin(Vc[:, 2]))
    nb = igl.adjacency_list(Fc)[bot][0]
    Vf = Vc.copy()
    Vf[bot] = Vf[bot] + 1.5 * (Vf[nb] - Vf[bot]) + np.array([0.0, 0.0, 0.08])
    assert _fold_cosines(Vf, Fc).min() < -0.9
    V3, info3 = inflate.crease_push(Vf, Fc, Vm, rounds=3)
    assert info3["fins_input"] > 0 and 0 < info3["outside_input"] < min(info3["outside_per_round"])
    assert info3["best_round"] >= 0 and not np.array_equal(V3, Vf)


def _dented_sphere_cage():
    """A unit sphere M and a coarse cage 1.08 x around it whose top vertex is dented 0.14 inside M."""
    from nestmg.shapes import sphere

    Vm, Fm = sphere(20)
    Vm = Vm / np.linalg.norm(Vm, axis=1, keepdims=True)
    Vc, Fc = sphere(6)
    Vc = 1.08 * Vc / np.linalg.norm(Vc, axis=1, keepdims=True)
    top = int(np.argmax(Vc[:, 2]))
    Vc[top] *= 0.8
    return Vm, Fm, Vc, Fc, top


def test_polish_contains_a_dented_sphere_and_moves_cage_vertices_out_of_M():
    """polish: a coarse cage around a unit sphere M with one vertex dented inside M (vertices of M
    outside) ends with M inside, every cage vertex outside M, no fin and no self-intersection."""
    import igl

    from cagegen._geometry import self_intersection_pairs
    from cagegen.skeleton.inflate import _fold_cosines, polish

    Vm, Fm, Vc, Fc, top = _dented_sphere_cage()
    s0, *_ = igl.signed_distance(Vm, Vc, Fc)
    sv0, *_ = igl.signed_distance(Vc, Vm, Fm)
    assert (s0 > 0).sum() > 5 and sv0[top] < -0.1
    V2, info = polish(Vc, Fc, Vm, Fm)
    s, *_ = igl.signed_distance(Vm, V2, Fc)
    sv, *_ = igl.signed_distance(V2, Vm, Fm)
    assert info["outside"] == 0 and s.max() < 0 and sv.min() > 0
    # the first containment pass alone gets M inside but leaves the dented vertex inside M (measured:
    # 0.027 deep; M's triangles then cross the cage): the vertex round moved it out
    assert info["outside_per_round"][0][-1] == 0 and info["cage_vertices_inside"][0] >= 1
    assert info["fins"] == 0 and _fold_cosines(V2, Fc).min() > -0.9
    assert len(self_intersection_pairs(V2, Fc)) == 0
