"""``repair`` through the pipeline: overlapping bodies and pinches become the boundary of TetWild's solid
(:mod:`nestmg.solid`), and the CLI names ``--repair`` when it refuses such an input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from cagegen import MeshInputError, audit_mesh
from cagegen._geometry import signed_volume
from nestmg.solid import solid_surface


def _two_balls(shift: float = 1.0, subdivisions: int = 2):
    """Two unit icospheres whose centres are ``shift`` apart along x, as one (V, F): overlapping for < 2."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64)
    return np.vstack([V, V + [shift, 0.0, 0.0]]), np.vstack([F, F + len(V)])


def _union_volume(V, F, n: int = 64) -> float:
    """Volume where the winding number of either ball exceeds 1/2, on an n^3 grid of cell centres."""
    import igl

    lo, hi = V.min(axis=0), V.max(axis=0)
    axes = [lo[i] + (np.arange(n) + 0.5) * (hi[i] - lo[i]) / n for i in range(3)]
    Q = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    half = len(F) // 2
    inside = np.zeros(len(Q), dtype=bool)
    for G in (F[:half], F[half:]):
        inside |= np.abs(igl.fast_winding_number(V, G, Q)) > 0.5
    return float(inside.mean() * np.prod(hi - lo))


def test_overlapping_balls_become_one_clean_solid():
    V, F = _two_balls(1.0)
    problems = [p.split(":")[0] for p in audit_mesh(V, F).problems]
    assert "self-intersections" in problems and "several connected components" in problems
    W, G, info = solid_surface(V, F)
    assert audit_mesh(W, G).ok  # closed, manifold, one piece, outward, no self-intersection
    assert info["bodies"] == 1 and info["volume_filled"] < 1e-3 * info["volume"]
    union = _union_volume(V, F)  # two balls minus their lens: ~7.0, one ball ~4.1
    assert signed_volume(W, G) == pytest.approx(union, rel=0.01)
    assert info["volume"] == pytest.approx(signed_volume(W, G), rel=1e-6)
    # within TetWild's envelope (1e-3 of the diagonal) of the input where the input was a clean boundary
    far = np.linalg.norm(W - [0.5, 0.0, 0.0], axis=1) > 1.2  # away from the intersection circle
    r = np.minimum(np.linalg.norm(W, axis=1), np.linalg.norm(W - [1.0, 0.0, 0.0], axis=1))
    assert np.abs(r[far] - 1.0).max() < 0.02  # icosphere facets: radius 0.98-1 between vertices


def test_balls_touching_at_a_point_are_two_bodies():
    """A pinch (two solids meeting at one point) is opened, not kept as a non-manifold vertex."""
    V, F = _two_balls(2.0)
    W, G, info = solid_surface(V, F)
    problems = [p.split(":")[0] for p in audit_mesh(W, G).problems]
    assert problems == ["several connected components"] and info["bodies"] == 2
    assert info["pinch_rounds"] >= 1  # TetWild's mesh pinched at the contact; the smaller fan was removed
    assert signed_volume(W, G) == pytest.approx(_union_volume(V, F), rel=0.01)


def test_pipeline_refuses_disjoint_bodies_after_the_repair():
    import time

    from cagegen import NestedOptions
    from nestmg.hierarchy import build_cage_surfaces

    V, F = _two_balls(2.5)  # apart: refused before TetWild runs
    t = time.perf_counter()
    with pytest.raises(MeshInputError, match=r"2 disjoint bodies; .*build_body_hierarchies"):
        build_cage_surfaces(V, F, 2, "nested", cages=NestedOptions(repair=True), cache=False, progress=False)
    assert time.perf_counter() - t < 5.0
    V, F = _two_balls(2.0)  # touching at a point: TetWild's solid pinches there and comes out as two bodies
    with pytest.raises(MeshInputError, match=r"2 separate bodies \(after the repair of: .*build_body_hierarchies"):
        build_cage_surfaces(V, F, 2, "nested", cages=NestedOptions(repair=True), cache=False, progress=False)


def _write_obj(path, V, F) -> None:
    path.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in V.tolist())
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F.tolist()))


def test_cli_names_repair_then_cages_the_union(tmp_path, capsys):
    from nestmg.cli import main

    V, F = _two_balls(1.0)
    V = V * 40.0 + [100.0, -20.0, 5.0]  # the user's units: the files written must be in them
    src = tmp_path / "balls.obj"
    _write_obj(src, V, F)
    before = src.read_bytes()
    rc = main(["cages", str(src), "--levels", "2", "--out", str(tmp_path / "a"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "components 0 and 1 intersect each other" in err and "--repair" in err
    assert "\n" not in err.strip()
    rc = main(["cages", str(src), "--levels", "2", "--repair", "--out", str(tmp_path / "b"), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    assert src.read_bytes() == before
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert rep["certified"] is True and rep["solid"]["bodies"] == 1
    assert rep["solid"]["method"] == "union"  # two clean balls: their exact union, no TetWild envelope
    layer0 = trimesh.load(tmp_path / "b" / "layer_0.obj", process=False)
    W, G = np.asarray(layer0.vertices), np.asarray(layer0.faces)
    assert audit_mesh(W, G).ok
    assert signed_volume(W, G) == pytest.approx(_union_volume(V, F), rel=0.01)  # user's units (40^3)


def test_specks_touching_the_solid_at_a_vertex_are_dropped():
    """Tets are grouped through shared faces only: a tiny tet hanging from a corner is its own group."""
    from nestmg.solid import _drop_specks

    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    T = np.array([[0, 1, 3, 5], [0, 3, 2, 6], [0, 5, 4, 6], [3, 5, 7, 6], [0, 3, 6, 5]])  # 5 tets, volume 1
    speck = np.array([[1.0, 1, 1], [1.01, 1, 1], [1, 1.01, 1], [1, 1, 1.01]])  # shares vertex 7 only
    V = np.vstack([cube, speck[1:]])
    Ts = np.vstack([T, [[7, 8, 9, 10]]])
    kept, dropped = _drop_specks(V, Ts)
    np.testing.assert_array_equal(kept, T)
    assert dropped == pytest.approx(0.01**3 / 6)


def test_face_counts_that_cannot_be_met_fail_before_the_repair():
    """An explicit --face-counts is checked on the input as given, in well under a second: no TetWild run."""
    import time

    from cagegen import NestedOptions
    from nestmg import SizingOptions
    from nestmg.hierarchy import build_cage_surfaces
    from nestmg.sizing import LevelsError

    V, F = _two_balls(1.0)  # 640 faces, overlapping: the repair would run TetWild
    t = time.perf_counter()
    with pytest.raises(LevelsError, match="cannot be met"):
        build_cage_surfaces(V, F, 2, "nested", sizing=SizingOptions(face_counts=[5000]),
                            cages=NestedOptions(repair=True), cache=False, progress=False)
    assert time.perf_counter() - t < 1.0


def test_a_void_facing_outward_is_named_and_turned_by_the_repair():
    """A hollow ball whose inner sphere faces outward (an exporter's void): named before any work without
    --repair; with it the even-odd rule turns the inner sphere into a void, nothing is filled."""
    from cagegen import options_class
    from nestmg.cli import _bodies
    from nestmg.hierarchy import build_cage_surfaces

    s = trimesh.creation.icosphere(subdivisions=3)
    Vs, Fs = np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int64)
    V, F = np.vstack([Vs, 0.5 * Vs]), np.vstack([Fs, Fs + len(Vs)])
    with pytest.raises(MeshInputError, match=r"component 1 lies inside component 0 and faces outward.*--repair"):
        _bodies(V, F, repair=False)
    layers, info = build_cage_surfaces(V, F, 2, "decimate", cages=options_class("decimate")(repair=True),
                                       cache=False, progress=False)
    assert info["voids"]["count"] == 1 and "solid" not in info  # no TetWild solid: the void is kept
    W, G = layers[0]
    assert signed_volume(W, G) == pytest.approx(signed_volume(Vs, Fs) * (1 - 0.125), rel=1e-12)
    assert np.array_equal(G[len(Fs):], Fs[:, ::-1] + len(Vs)) and np.array_equal(V, W)


def test_a_large_repair_input_is_decimated_within_half_the_envelope_first():
    """TetWild's time grows with its input's faces: above REPAIR_MAX_FACES the repair meshes a QEM
    decimation whose Hausdorff distance is at most its envelope, or the input when that fails."""
    from nestmg.solid import REPAIR_MAX_FACES, lighter_input

    s = trimesh.creation.icosphere(subdivisions=6)  # 81,920 faces
    V, F = np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int64)
    U, G, info = lighter_input(V, F, epsilon=1e-3)  # 81,920 -> 50,000 in one halving step
    assert info["refused"] is None and len(G) == REPAIR_MAX_FACES and info["hausdorff"] <= 1e-3
    assert signed_volume(U, G) == pytest.approx(signed_volume(V, F), rel=1e-3)
    U, G, info = lighter_input(V, F, epsilon=1e-9)  # no decimation meets that: the input itself
    assert U is V and G is F and info["refused"]["hausdorff"] > 1e-9 and info["faces_out"] == len(F)
    small = trimesh.creation.icosphere(subdivisions=2)
    assert lighter_input(np.asarray(small.vertices), np.asarray(small.faces), 1e-3)[2] is None


def _box(lo, hi):
    m = trimesh.creation.box(bounds=[lo, hi])
    return np.asarray(m.vertices, dtype=float), np.asarray(m.faces, dtype=np.int64)


def _stack(*meshes):
    offsets = np.cumsum([0] + [len(V) for V, _ in meshes])
    return (np.vstack([V for V, _ in meshes]), np.vstack([F + o for (_, F), o in zip(meshes, offsets)]))


def test_overlapping_clean_parts_become_their_exact_union():
    """CAD parts exported together (plates overlapping, faces coplanar): the union is exact, sharp edges and
    all, with no envelope; a piece that is not clean by itself leaves the repair to TetWild (None)."""
    from nestmg.solid import exact_union

    a, b = _box([0, 0, 0], [2, 1, 1]), _box([1, 0, 0], [3, 1, 0.5])  # coplanar bottom, front and back faces
    V, F = _stack(a, b)
    W, G, info = exact_union(V, F)
    assert audit_mesh(W, G).ok and info["method"] == "union" and info["bodies"] == 1
    assert signed_volume(W, G) == pytest.approx(2.5, rel=1e-12)  # 2 + 1 - 0.5 of overlap
    assert info["volume"] == pytest.approx(2.5, rel=1e-12) and info["volume_filled"] == pytest.approx(0.0, abs=1e-12)
    corners = np.array([[3, 1, 0.5], [2, 0, 1], [2, 1, 0.5], [0, 0, 0]], dtype=float)
    assert np.abs(W[:, None, :] - corners[None]).max(axis=2).min(axis=0).max() < 1e-12  # corners kept exactly
    # every vertex on the input's surface (no envelope, no rounding of the sharp edges)
    import igl

    d2 = igl.point_mesh_squared_distance(W, V, F)[0]
    assert np.sqrt(d2.max()) < 1e-12
    # a third box apart: two bodies
    W, G, info = exact_union(*_stack(a, b, _box([5, 0, 0], [6, 1, 1])))
    assert info["bodies"] == 2 and signed_volume(W, G) == pytest.approx(3.5, rel=1e-12)
    # six overlapping wall plates of a sealed box: one solid with one void (kept: the box's inside is air)
    plates = [_box([0, 0, 0], [0.5, 3, 3]), _box([2.5, 0, 0], [3, 3, 3]),
              _box([0.2, -0.1, 0.2], [2.8, 0.5, 2.8]), _box([0.2, 2.5, 0.2], [2.8, 3.1, 2.8]),
              _box([0.1, 0.1, -0.2], [2.9, 2.9, 0.5]), _box([0.1, 0.1, 2.5], [2.9, 2.9, 3.2])]
    W, G, info = exact_union(*_stack(*plates))
    assert info["bodies"] == 1 and info["voids"] == 1
    from nestmg.cavities import hollow_solid

    outer, void, _ = hollow_solid(W, G)
    assert signed_volume(*void) == pytest.approx(-8.0, rel=1e-12)  # the box's inside, [0.5, 2.5]^3
    assert info["volume"] == pytest.approx(signed_volume(*outer) - 8.0, rel=1e-12)
    # flush plates (every outer face coplanar with three others): the batch union triangulates two coplanar
    # faces into an overlap, the one-by-one union does not
    flush = [_box([0, 0, 0], [0.5, 3, 3]), _box([2.5, 0, 0], [3, 3, 3]), _box([0, 0, 0], [3, 0.5, 3]),
             _box([0, 2.5, 0], [3, 3, 3]), _box([0, 0, 0], [3, 3, 0.5]), _box([0, 0, 2.5], [3, 3, 3])]
    W, G, info = exact_union(*_stack(*flush))
    assert audit_mesh(*hollow_solid(W, G)[0]).ok and info["voids"] == 1
    assert signed_volume(W, G) == pytest.approx(27.0 - 8.0, rel=1e-12)
    assert exact_union(*a) is None  # one piece: nothing to unite
    Vb, Fb = b
    assert exact_union(*_stack(a, (Vb, Fb[:, ::-1]))) is None  # an inward piece (a cavity): TetWild decides
    m = trimesh.creation.icosphere(subdivisions=2)
    Vs, Fs = np.array(m.vertices), np.asarray(m.faces, dtype=np.int64)
    Vs[0] *= -1.5  # one vertex pushed through the ball: its fan crosses the faces opposite
    assert "self-intersections" in audit_mesh(Vs, Fs).problems[0]
    assert exact_union(*_stack((Vs, Fs), _box([0.5, 0, 0], [2, 1, 1]))) is None  # not clean: TetWild decides


def test_cli_unites_crossing_parts_into_disjoint_bodies(tmp_path, capsys):
    """With --repair, overlapping parts become their union; when that leaves several bodies, each gets its
    own hierarchy (the multi-body path), in the user's coordinates."""
    from nestmg.cli import _bodies

    V, F = _stack(_box([0, 0, 0], [2, 1, 1]), _box([1, 0, 0], [3, 1, 0.5]), _box([5, 0, 0], [6, 1, 1]))
    V = V * 10.0 + [100.0, 0.0, 0.0]
    with pytest.raises(MeshInputError, match=r"components 0 and 1 intersect each other.*--repair"):
        _bodies(V, F, repair=False)
    W, _, bodies = _bodies(V, F, repair=True)
    assert len(bodies) == 2
    vols = sorted(signed_volume(Wb, Gb) for Wb, Gb in bodies)
    assert vols == pytest.approx([1000.0, 2500.0], rel=1e-12)  # user's units: 10^3 scale
    assert W.min(axis=0) == pytest.approx([100.0, 0.0, 0.0])


def _holed_ball(holes: int = 3, subdivisions: int = 3):
    """An icosphere with the faces around ``holes`` vertices removed (a scan's missing patches)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64)
    centres = [0, 5, 9][:holes]  # icosahedron vertices, far apart
    F = F[~np.isin(F, centres).any(axis=1)]
    used, F = np.unique(F, return_inverse=True)
    return V[used], F.reshape(-1, 3)


def test_a_scans_small_holes_are_closed_an_open_sheet_is_refused():
    """fill_holes: every loop closed without new vertices, orientation following the surface, the patches a
    few percent of the area; a hemisphere (an open sheet) is refused: its 'hole' is as large as itself."""
    from nestmg.solid import fill_holes

    V, F = _holed_ball()
    assert audit_mesh(V, F).problems[0].startswith("open boundary")
    W, G, info = fill_holes(V, F)
    assert info["holes"] == 3 and audit_mesh(W, G).ok and np.array_equal(G[:len(F)], F)
    assert 0.0 < info["patch_area_fraction"] < 0.02  # 3 of 320 faces were 5-triangle fans: ~1.1%
    full = trimesh.creation.icosphere(subdivisions=3)
    assert signed_volume(W, G) == pytest.approx(full.volume, rel=2e-3)  # the five-triangle fans, flattened
    Vh, Fh = np.asarray(full.vertices), np.asarray(full.faces)
    cap = Fh[(Vh[Fh][:, :, 2] > -1e-9).all(axis=1)]  # the upper half: an open sheet
    with pytest.raises(MeshInputError, match=r"would take \d+% of its area to close"):
        fill_holes(Vh, cap)


def test_cli_closes_the_holes_with_repair_only(tmp_path, capsys, monkeypatch):
    import cagegen.audit
    from nestmg.cli import main

    V, F = _holed_ball()
    src = tmp_path / "scan.obj"
    _write_obj(src, 20.0 * V, F)
    rc = main(["cages", str(src), "--levels", "2", "--out", str(tmp_path / "a"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "open boundary" in err and "--repair closes small holes" in err
    tested = []  # the surfaces the audits run the exact self-intersection test on
    exact = cagegen.audit.self_intersection_pairs
    monkeypatch.setattr(cagegen.audit, "self_intersection_pairs", lambda V, F: tested.append(len(F)) or exact(V, F))
    rc = main(["cages", str(src), "--levels", "2", "--repair", "--out", str(tmp_path / "b"), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert rep["verification"]["ok"] and rep["solid"]["method"] == "holes" and rep["solid"]["holes"] == 3
    # once, on the closed surface (not on the open scan, nor again by the cages' own audit of the same arrays)
    assert tested == [rep["faces"][0]] and rep["audit"]["n_self_intersections"] == 0
    assert rep["solid"]["repair_seconds"] >= rep["solid"]["seconds"] > 0  # the whole repair, audits included
    layer0 = trimesh.load(tmp_path / "b" / "layer_0.obj", process=False)
    assert audit_mesh(np.asarray(layer0.vertices), np.asarray(layer0.faces)).ok
    assert np.abs(np.asarray(layer0.vertices)).max() == pytest.approx(20.0, rel=1e-9)  # the user's units
