"""cagegen.intersect: filtered exact triangle intersection tests (the verifier's default, no copyleft code)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cagegen import verify_nesting
from cagegen._geometry import cross_intersection_pairs, self_intersection_pairs
from cagegen.intersect import _candidates, _grid_candidates, cross_pairs, face_grid, orient3d, self_pairs

TRI = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
F1 = np.array([[0, 1, 2]])


def _ico(sub=3):
    s = trimesh.creation.icosphere(subdivisions=sub)
    return np.asarray(s.vertices, float), np.asarray(s.faces, np.int64)


def test_orient3d_signs_and_exact_zero():
    a, b, c = TRI[None, 0], TRI[None, 1], TRI[None, 2]
    assert orient3d(a, b, c, np.array([[0.2, 0.2, -1.0]]))[0] == 1
    assert orient3d(a, b, c, np.array([[0.2, 0.2, 1.0]]))[0] == -1
    assert orient3d(a, b, c, np.array([[0.3, 0.3, 0.0]]))[0] == 0
    # a point 1e-300 off a plane through large coordinates: the sign cannot be certified -> 0
    big = 1e8 + TRI
    assert orient3d(big[None, 0], big[None, 1], big[None, 2], np.array([[1e8 + 0.3, 1e8 + 0.3, 1e8 + 1e-300]]))[0] == 0


def test_vectorised_exact_orientation_matches_the_scalar_one():
    """The exact fallback of ``orient3d(exact=True)`` (vectorised in numpy object arrays) gives the same
    signs as the row-by-row integer evaluation on degenerate rows: exact midpoints (coplanar), points
    1e-17 off, coordinates spanning 1e-200..1e200 and subnormals, repeated points, all-zero rows; and
    orient3d certifies the midpoint rows as exactly 0 where the float filter cannot."""
    from cagegen.intersect import _exact_det3, _exact_det3_rows

    rng = np.random.default_rng(1)
    k = 400
    A, B, C = (rng.normal(size=(k, 3)) for _ in range(3))
    Z = np.zeros((k, 3))
    Z[:, 1] = rng.normal(size=k) * 1e-310  # subnormals
    cases = [(A, B, C, 0.5 * (A + B)), (A, B, C, A + 1e-17 * rng.normal(size=(k, 3))),
             (A * 1e200, B * 1e-200, C, Z), (Z, Z, Z, Z), (A, A, B, C), (A, B, C, rng.normal(size=(k, 3)))]
    for a, b, c, d in cases:
        ref = np.array([_exact_det3(a[i], b[i], c[i], d[i]) for i in range(k)], dtype=np.int8)
        assert np.array_equal(_exact_det3_rows(a, b, c, d), ref)
        assert np.array_equal(orient3d(a, b, c, d, exact=True), ref)
    # dyadic coordinates: the midpoint of AB is exact, so (A, B, C, mid) is exactly coplanar: 0 in every row
    Ai, Bi, Ci = (rng.integers(-10**6, 10**6, size=(k, 3)) / 1024.0 for _ in range(3))
    s = orient3d(Ai, Bi, Ci, 0.5 * (Ai + Bi), exact=True)
    assert np.all(s == 0)
    assert np.all(orient3d(Ai, Bi, Ci, 0.5 * (Ai + Bi) + [0, 0, 2.0**-20], exact=True) != 0)


def test_shared_coordinates_are_exact_zeros_without_integer_arithmetic(monkeypatch):
    """Four points with one coordinate equal bit for bit (an axis-aligned plane) or two equal points give
    det 0 exactly (``x - y == 0`` iff ``x == y``): ``orient3d(exact=True)`` and the 2D test certify them
    without the integer path, which then sees only the other uncertain rows; every sign is the scalar
    reference's, in a mix with rows 1e-17 off such a plane."""
    import cagegen.intersect as I

    rng = np.random.default_rng(7)
    k = 300
    a, b, c, d = (rng.normal(size=(k, 3)) for _ in range(4))
    for p in (a, b, c, d):
        p[:, 2] = 0.3  # an axis-aligned plane: the difference column is exactly zero
    a[:100] = d[:100] + [0, 1e-17, 0]  # rounds to d's coordinates: a zero row
    off = d.copy()
    off[:, 2] += 1e-17 * rng.normal(size=k)  # not exactly in the plane: must reach the exact path
    A = np.vstack([a, a])
    B, C, D = np.vstack([b, b]), np.vstack([c, c]), np.vstack([d, off])
    ref = np.array([I._exact_det3(A[i], B[i], C[i], D[i]) for i in range(2 * k)], dtype=np.int8)
    seen = []
    real = I._exact_det3_rows
    monkeypatch.setattr(I, "_exact_det3_rows", lambda *r: seen.append(len(r[0])) or real(*r))
    assert np.array_equal(I.orient3d(A, B, C, D, exact=True), ref)
    assert np.all(ref[:k] == 0) and sum(seen) <= k  # the plane's rows never reach the integer path
    # 2D: collinear on a shared coordinate, or a repeated point
    p2, q2 = rng.normal(size=(k, 2)), rng.normal(size=(k, 2))
    p2[:, 1] = q2[:, 1] = 0.7
    r2 = np.c_[rng.normal(size=k), np.full(k, 0.7)]
    assert np.all(I._orient2d(p2, q2, r2, exact=True) == 0)
    assert np.all(I._orient2d(p2, p2, q2, exact=True) == 0)
    assert np.array_equal(I._orient2d(p2, q2, r2 + [0, 1e-9], exact=True),
                          np.sign((p2[:, 0] - r2[:, 0]) * (q2[:, 1] - r2[:, 1] - 1e-9)
                                  - (p2[:, 1] - r2[:, 1] - 1e-9) * (q2[:, 0] - r2[:, 0])).astype(np.int8))


@pytest.mark.parametrize(
    "offset, expected",
    [
        ([[0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [0.2, 0.7, 0.5]], 1),  # pierces the interior
        ([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 1.0]], 1),  # touches at a vertex
        ([[0.5, 0.5, 0.0], [0.5, 0.5, 1.0], [1.0, 1.0, 1.0]], 1),  # touches an edge
        ([[2.0, 2.0, -0.5], [2.0, 2.0, 0.5], [2.0, 3.0, 0.5]], 0),  # far
        ([[0.2, 0.2, 1e-9], [0.3, 0.2, 1.0], [0.2, 0.3, 1.0]], 0),  # 1e-9 above: certified disjoint
    ],
)
def test_cross_pairs_single_triangles(offset, expected):
    W = np.array(offset)
    assert len(cross_pairs(TRI, F1, W, F1)) == expected


def test_coplanar_cases():
    # overlapping coplanar triangles meet, disjoint coplanar ones do not
    assert len(cross_pairs(TRI, F1, TRI + [0.2, 0.2, 0.0], F1)) == 1
    assert len(cross_pairs(TRI, F1, TRI + [0.6, 0.6, 0.0], F1)) == 0
    # a subdivided box: flat fans of coplanar neighbours are not self-intersections
    b = trimesh.creation.box().subdivide().subdivide()
    assert len(self_pairs(b.vertices, b.faces)) == 0


def test_folds_and_shared_vertex_overlaps_are_found():
    # two faces sharing edge 0-1, folded onto each other (third vertices on the same side)
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0.3, 1, 0], [0.6, 0.8, 0]])
    assert self_pairs(V, np.array([[0, 1, 2], [1, 0, 3]])).tolist() == [[0, 1]]
    # same edge, third vertex on the other side: a flat valid pair
    V2 = V.copy()
    V2[3] = [0.6, -0.8, 0]
    assert len(self_pairs(V2, np.array([[0, 1, 2], [1, 0, 3]]))) == 0
    # sharing vertex 0 only, coplanar, angles overlapping -> found; angles apart -> not
    W = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0.5, 0], [0.5, 1, 0], [-1, 0.2, 0], [-1, -0.5, 0]])
    assert self_pairs(W, np.array([[0, 1, 2], [0, 3, 4]])).tolist() == [[0, 1]]
    assert len(self_pairs(W, np.array([[0, 1, 2], [0, 5, 6]]))) == 0
    # sharing vertex 0, not coplanar, the second face crossing the first one's interior
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.6, 0.6, -0.3], [0.6, 0.6, 0.3]])
    assert self_pairs(X, np.array([[0, 1, 2], [0, 3, 4]])).tolist() == [[0, 1]]
    X[3:, 0] = -0.6  # now behind the shared vertex
    assert len(self_pairs(X, np.array([[0, 1, 2], [0, 3, 4]]))) == 0


def test_injected_self_intersections_match_cgal(rng):
    cgal = pytest.importorskip("igl.copyleft.cgal")
    V, F = _ico(3)
    for _ in range(4):
        W = V.copy()
        idx = rng.choice(len(V), size=3, replace=False)
        W[idx] *= -0.3 + 0.2 * rng.random((3, 1))  # push three vertices through the sphere
        ours = {tuple(p) for p in self_pairs(W, F).tolist()}
        ref = {tuple(sorted(p)) for p in np.asarray(cgal.remesh_self_intersections(W, F, detect_only=True)[2])
               .reshape(-1, 2).tolist()}
        assert ours == ref and len(ours) > 10


def test_rounding_level_contacts_are_reported_as_touching():
    """Edges that cross to within ~1e-16 count as touching; CGAL (exact on the rounded input) may not."""
    cgal = pytest.importorskip("igl.copyleft.cgal")
    from cagegen._geometry import segment_segment_sqdist

    V, F = _ico(3)
    W = 0.99 * V + [0.0, 0.0, 0.05]  # some edge pairs meet at ~1e-16 here
    ours = {tuple(p) for p in cross_pairs(V, F, W, F).tolist()}
    ref = {tuple(p) for p in np.asarray(cgal.intersect_other(V, F, W, F, detect_only=True)[0]).reshape(-1, 2).tolist()}
    extra = np.array(sorted(ours - ref))
    assert ref <= ours and 0 < len(extra) <= 10
    A, B = V[F[extra[:, 0]]], W[F[extra[:, 1]]]
    d = np.full(len(extra), np.inf)
    for i in range(3):
        for k in range(3):
            d = np.minimum(d, segment_segment_sqdist(A[:, i], A[:, (i + 1) % 3], B[:, k], B[:, (k + 1) % 3]))
    assert np.sqrt(d.max()) < 1e-12  # each extra pair really meets, to rounding


def test_cross_pairs_match_cgal_on_generic_positions(rng):
    cgal = pytest.importorskip("igl.copyleft.cgal")
    V, F = _ico(3)
    for _ in range(3):
        R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
        W = (V @ R.T) * (0.97 + 0.06 * rng.random()) + 0.02 * rng.standard_normal(3)
        ours = {tuple(p) for p in cross_pairs(V, F, W, F).tolist()}
        ref = {tuple(p) for p in np.asarray(cgal.intersect_other(V, F, W, F, detect_only=True)[0])
               .reshape(-1, 2).tolist()}
        assert ours == ref and len(ours) > 10


def test_cross_pairs_with_a_face_grid_finds_the_same_pairs(rng):
    """The indexed input (face_grid, cells built once) gives cross_pairs' own pairs: small patches inside
    the grid, a cage larger than the grid (boxes clipped to its border cells), and touching triangles."""
    V, F = _ico(4)
    grid = face_grid(V, F)
    Vs, Fs = _ico(1)
    n_hit = 0
    for _ in range(12):
        W = Vs * rng.uniform(0.05, 0.5) + rng.uniform(-1.2, 1.2, 3)
        a, b = cross_pairs(W, Fs, V, F), cross_pairs(W, Fs, V, F, grid=grid)
        assert np.array_equal(a, b)
        n_hit += len(a)
    Vc, Fc = _ico(2)
    W = Vc * 1.02 + 0.03 * rng.standard_normal(Vc.shape)
    a, b = cross_pairs(W, Fc, V, F), cross_pairs(W, Fc, V, F, grid=grid)
    assert np.array_equal(a, b) and len(a) > 10
    assert n_hit > 0
    touch = cross_pairs(V[F[0]], F1, V, F, grid=grid)  # a copy of face 0 touches it and its neighbours
    assert {0} <= set(touch[:, 1].tolist())


def _overlapping_boxes(VA, FA, VB, FB, slop):
    """All (a, b) face pairs whose boxes (grown by ``slop``) overlap, by brute force, sorted."""
    TA, TB = VA[FA], VB[FB]
    loA, hiA, loB, hiB = TA.min(1) - slop, TA.max(1) + slop, TB.min(1) - slop, TB.max(1) + slop
    hit = ((loA[:, None] <= hiB[None]) & (loB[None] <= hiA[:, None])).all(axis=2)
    return np.argwhere(hit)


def test_broad_phase_finds_every_overlapping_pair_once(rng):
    """The grid broad phase keeps each pair in one shared cell (no duplicate removal): its pairs are exactly
    the brute-force box overlaps, in order, for two meshes, one mesh against itself (a < b) and the
    indexed grid; boxes of very different sizes span many cells, and some share their faces' corners."""
    V, F = _ico(2)
    Vs, Fs = _ico(1)
    long = np.array([[0, 1, 2], [3, 4, 5]])
    for _ in range(6):
        W = np.vstack([Vs * rng.uniform(0.2, 0.6) + rng.uniform(-0.8, 0.8, 3),
                       rng.uniform(-1.1, 1.1, (6, 3))])  # two long thin triangles across the sphere
        G = np.vstack([Fs, long + len(Vs)])
        want = _overlapping_boxes(W, G, V, F, 1e-9)
        assert len(want) > 20
        assert np.array_equal(_candidates(W, G, V, F, 1e-9), want)
        assert np.array_equal(_grid_candidates(W, G, face_grid(V, F), 1e-9), want)
        U = np.vstack([V, W])
        H = np.vstack([F, G + len(V)])
        both = _overlapping_boxes(U, H, U, H, 1e-9)
        assert np.array_equal(_candidates(U, H, U, H, 1e-9, upper=True), both[both[:, 0] < both[:, 1]])


def test_engines_agree_in_the_verifier():
    pytest.importorskip("igl.copyleft.cgal")
    V, F = _ico(3)
    good = [(V, F), (1.05 * V, F)]
    R = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))[0]  # generic position: no
    bad = [(V, F), (0.99 * V @ R.T + [0.0, 0.0, 0.05], F)]  # rounding-level contacts; pokes out
    for layers, ok in ((good, True), (bad, False)):
        a = verify_nesting(layers)
        b = verify_nesting(layers, intersection_engine="cgal")
        assert a.ok is b.ok is ok
        assert a.pairs[0].n_intersecting_pairs == b.pairs[0].n_intersecting_pairs
    with pytest.raises(ValueError, match="engine"):
        verify_nesting(good, intersection_engine="bogus")
    assert len(self_intersection_pairs(V, F, "filtered")) == 0
    assert len(cross_intersection_pairs(V, F, V, F)) > 0  # identical surfaces touch everywhere


def _sat_2d_disjoint(A, B) -> bool:
    """Ground truth in rationals: closed triangles of one plane z = const are disjoint iff one of their six
    edge normals separates them strictly (separating axis theorem)."""
    from fractions import Fraction

    A = [[Fraction(float(x)) for x in p[:2]] for p in A]
    B = [[Fraction(float(x)) for x in p[:2]] for p in B]
    for T in (A, B):
        for i in range(3):
            p, q = T[i], T[(i + 1) % 3]
            n = (q[1] - p[1], p[0] - q[0])
            pa = [n[0] * x[0] + n[1] * x[1] for x in A]
            pb = [n[0] * x[0] + n[1] * x[1] for x in B]
            if max(pa) < min(pb) or max(pb) < min(pa):
                return True
    return False


def test_separation_certificate_sound_and_exact_on_coplanar_triangles():
    """Disjoint faces: the floating-point separation certificate only skips pairs that are disjoint, and with
    the exact rest the answer is the rational one on exactly coplanar triangles (z = 0.3 bit for bit), touching
    and nearly touching ones included. The in-plane test used to be a conservative float test: it reported
    disjoint coplanar neighbours of a finely split CAD part (fandisk split twice) as crossing."""
    from cagegen.intersect import _disjoint_hits, _separated, _unit

    rng = np.random.default_rng(7)
    k = 400
    TA = np.concatenate([rng.random((k, 3, 2)), np.full((k, 3, 1), 0.3)], axis=2)
    TB = TA + np.concatenate([rng.uniform(-0.6, 0.6, (k, 1, 2)) * rng.random((k, 1, 1)), np.zeros((k, 1, 1))], axis=2)
    TB[: k // 4, 0] = TA[: k // 4, 0] + (TA[: k // 4, 1] - TA[: k // 4, 0]) * 2.0  # a vertex on an edge's line
    TB[: k // 4, 0, 2] = 0.3
    truth = np.array([not _sat_2d_disjoint(a, b) for a, b in zip(TA, TB)])
    assert 0.2 < truth.mean() < 0.9
    assert np.array_equal(_disjoint_hits(TA, TB), truth)
    A, B = [TA[:, i] for i in range(3)], [TB[:, i] for i in range(3)]
    n = _unit(np.cross(A[1] - A[0], A[2] - A[0]))
    cert = _separated(A[0], A, B, [np.cross(n, A[(i + 1) % 3] - A[i]) for i in range(3)])
    assert cert.any() and not (cert & truth).any()


def test_degenerate_and_fan_pairs_are_not_reported_as_crossing():
    """A zero-area face (three collinear vertices, as in a CAD export) strictly on one side of another face's
    plane is disjoint from it: the exact tests found its plane undefined and called it crossing (11 of the 27
    pairs of 42400-IDGH.stl were such); the certificate decides it. Triangles sharing one vertex: certified or exact, the
    same answers as the exact test alone."""
    from cagegen.intersect import _disjoint_hits, _shared_vertex_exact, _shared_vertex_hits

    A = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    needle = np.array([[[0.2, 0.2, 0.1], [0.3, 0.3, 0.1], [0.25, 0.25, 0.1]]])
    assert not _disjoint_hits(A, needle)[0]
    assert _disjoint_hits(A, needle - [0, 0, 0.1])[0]  # in A's plane: it does cross
    rng = np.random.default_rng(3)
    k = 2000
    S = rng.random((k, 3))
    D = rng.standard_normal((k, 4, 3)) * [1.0, 1.0, 0.05]  # nearly flat fans, some folded
    V = np.concatenate([S, *(S + D[:, i] for i in range(4))])
    FA = np.stack([np.arange(k), np.arange(k) + k, np.arange(k) + 2 * k], axis=1)
    FB = np.stack([np.arange(k), np.arange(k) + 3 * k, np.arange(k) + 4 * k], axis=1)
    eq = FA[:, :, None] == FB[:, None, :]
    got = _shared_vertex_hits(V, FA, FB, eq)
    ref = _shared_vertex_exact(S, S + D[:, 0], S + D[:, 1], S + D[:, 2], S + D[:, 3])
    assert np.array_equal(got, ref) and 0.05 < ref.mean() < 0.95


def test_flat_split_surface_needs_no_exact_arithmetic(monkeypatch):
    """A closed surface whose faces are split in their planes (a turned box split four times: 3,072 faces, the
    neighbours coplanar up to the midpoints' rounding, where the floating-point filter cannot decide) is certified free of self-intersections without one exact determinant: the
    separation certificates decide every pair (before them: one exact row per pair of nearby faces)."""
    import igl

    import cagegen.intersect as I

    rows = []
    orig = I._exact_det3_rows
    monkeypatch.setattr(I, "_exact_det3_rows", lambda *a: (rows.append(len(a[0])), orig(*a))[1])
    box = trimesh.creation.box()
    R = trimesh.transformations.random_rotation_matrix(np.random.default_rng(1).random(3))[:3, :3]
    V, F = igl.upsample((np.asarray(box.vertices, float) * [1.0, 0.7, 0.3]) @ R.T + 0.1, np.asarray(box.faces), 4)
    assert len(F) == 3072
    assert len(self_pairs(V, F)) == 0
    assert sum(rows) == 0
