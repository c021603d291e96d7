"""cagegen.verify: the nesting verifier certifies nested layers and names the layer that is not."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from cagegen.errors import CageError
from cagegen.verify import WINDING_THRESHOLD, verify_nesting


def _ico(sub: int, r: float = 1.0, c=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices, dtype=np.float64) + np.asarray(c), np.asarray(s.faces, dtype=np.int64)


@pytest.fixture(scope="module")
def fine():
    return _ico(4, 1.0)  # 2562 vertices, 5120 faces


def _fail(rep, layer: int, *words):
    assert not rep.ok
    with pytest.raises(CageError) as ei:
        rep.raise_if_failed()
    assert ei.value.layer == layer
    msg = str(ei.value)
    assert f"layer {layer}" in msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    return ei.value


def test_concentric_spheres_are_nested(fine):
    coarse = _ico(3, 1.3)
    rep = verify_nesting([fine, coarse])
    assert rep.ok, str(rep)
    p = rep.pairs[0]
    assert p.min_winding == pytest.approx(1.0, abs=1e-9)  # exact winding number
    assert p.n_outside_vertices == 0 and p.n_coarse_inside_vertices == 0 and p.n_intersecting_pairs == 0
    assert p.self_intersections_fine == 0 and p.self_intersections_coarse == 0
    # radial gap 0.3 minus the chordal sag of the 1280-face coarse sphere (< 0.01)
    assert p.min_gap == pytest.approx(0.3, abs=1e-2)
    assert p.min_gap < 0.3
    diag = np.linalg.norm(fine[0].max(0) - fine[0].min(0))
    assert rep.bbox_diagonal == pytest.approx(diag)
    assert p.min_gap_rel == pytest.approx(p.min_gap / diag, rel=1e-12)
    rep.raise_if_failed()  # no error
    assert p.volume_coarse > p.volume_fine > 0


def test_three_concentric_layers_and_report_formats(fine):
    rep = verify_nesting([fine, _ico(3, 1.2), _ico(2, 1.5)])
    assert rep.ok and len(rep.pairs) == 2
    assert [p.fine for p in rep.pairs] == [0, 1]
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["ok"] is True and len(d["pairs"]) == 2
    assert d["pairs"][1]["n_faces_coarse"] == 320
    text = str(rep)
    assert "nested" in text and text.count("yes") == 2


def test_poking_layer_is_rejected(fine):
    coarse = _ico(3, 1.1, c=(0.3, 0.0, 0.0))  # shifted: pokes through on the -x side
    rep = verify_nesting([fine, coarse])
    p = rep.pairs[0]
    assert p.n_intersecting_pairs > 0
    assert p.n_outside_vertices > 0 and p.min_winding < 0.1
    assert p.min_gap == 0.0  # crossing surfaces are at distance 0
    err = _fail(rep, 1, "intersects layer 0", "does not contain layer 0")
    assert "intersecting" in err.reason


def test_smaller_cage_does_not_contain(fine):
    rep = verify_nesting([fine, _ico(3, 0.5)])
    p = rep.pairs[0]
    assert p.min_winding == pytest.approx(0.0, abs=1e-2)
    assert p.n_outside_vertices == len(fine[0])
    assert p.n_intersecting_pairs == 0
    _fail(rep, 1, "does not contain layer 0")


def test_second_pair_failure_names_layer_2(fine):
    rep = verify_nesting([fine, _ico(3, 1.5), _ico(2, 1.2)])
    assert rep.pairs[0].ok and not rep.pairs[1].ok
    _fail(rep, 2, "does not contain layer 1")


def test_self_intersecting_layer(fine):
    Va, Fa = _ico(3, 1.5, c=(-0.3, 0, 0))
    Vb, Fb = _ico(3, 1.5, c=(0.3, 0, 0))
    coarse = (np.vstack([Va, Vb]), np.vstack([Fa, Fb + len(Va)]))  # one F, two overlapping spheres
    rep = verify_nesting([fine, coarse])
    p = rep.pairs[0]
    assert p.self_intersections_coarse > 0 and p.self_intersections_fine == 0
    # every fine vertex is inside both spheres: winding 2, not a containment failure
    assert p.min_winding == pytest.approx(2.0, abs=2e-2) and p.n_outside_vertices == 0
    _fail(rep, 1, "layer 1 self-intersects")
    # with check_self=False the same (overlapping) layer passes the containment rule
    assert verify_nesting([fine, coarse], check_self=False).ok


def test_fine_layer_self_intersection_blames_fine_layer():
    Va, Fa = _ico(2, 1.0, c=(-0.3, 0, 0))
    Vb, Fb = _ico(2, 1.0, c=(0.3, 0, 0))
    bad_fine = (np.vstack([Va, Vb]), np.vstack([Fa, Fb + len(Va)]))
    rep = verify_nesting([bad_fine, _ico(3, 2.0)])
    _fail(rep, 0, "layer 0 self-intersects")


def test_cavity_inside_fine_solid_is_caught(fine):
    # coarse = big sphere + an inward-facing small sphere (a cavity) hidden inside the fine solid:
    # no crossing and every fine vertex has winding 1, yet the fine solid is not inside the coarse one
    Vo, Fo = _ico(3, 2.0)
    Vi, Fi = _ico(2, 0.3)
    coarse = (np.vstack([Vo, Vi]), np.vstack([Fo, Fi[:, ::-1] + len(Vo)]))
    rep = verify_nesting([fine, coarse])
    p = rep.pairs[0]
    assert p.n_intersecting_pairs == 0 and p.n_outside_vertices == 0
    assert p.n_coarse_inside_vertices == len(Vi)
    _fail(rep, 1, f"{len(Vi)} vertices inside layer 0")


def test_touching_layers_fail_and_clearance_passes():
    box = trimesh.creation.box(extents=(1, 1, 1))
    Vf, Ff = np.asarray(box.vertices, float), np.asarray(box.faces, np.int64)
    # coarse box shares three face planes with the fine box: touching is not strict nesting
    touching = (2.0 * Vf + 0.5, Ff)
    rep = verify_nesting([(Vf, Ff), touching])
    assert rep.pairs[0].n_intersecting_pairs > 0 and rep.pairs[0].min_gap == 0.0
    _fail(rep, 1, "touching")
    clear = (1.2 * Vf, Ff)  # 0.1 clearance on every side
    rep = verify_nesting([(Vf, Ff), clear])
    assert rep.ok and rep.pairs[0].min_gap == pytest.approx(0.1, abs=1e-12)


def test_min_gap_requirement(fine):
    layers = [fine, _ico(3, 1.3)]
    diag = np.linalg.norm(fine[0].max(0) - fine[0].min(0))
    assert verify_nesting(layers, min_gap=0.25 / diag).ok
    rep = verify_nesting(layers, min_gap=0.35 / diag)
    assert rep.min_gap_required == pytest.approx(0.35 / diag)
    _fail(rep, 1, "closer than min_gap")


def test_inside_out_and_open_coarse_layers(fine):
    V, F = _ico(3, 1.3)
    rep = verify_nesting([fine, (V, F[:, ::-1])])
    assert rep.pairs[0].min_winding == pytest.approx(-1.0, abs=1e-2)
    _fail(rep, 1, "inside-out")
    rep = verify_nesting([fine, (V, F[1:])])
    assert rep.pairs[0].boundary_edges_coarse == 3
    _fail(rep, 1, "not a closed manifold")


def test_bad_arguments(fine):
    with pytest.raises(ValueError, match="at least two layers"):
        verify_nesting([fine])
    with pytest.raises(CageError) as ei:
        verify_nesting([fine, (np.zeros((4, 2)), np.zeros((4, 3), int))])
    assert ei.value.layer == 1
    V, F = _ico(3, 1.3)
    V = V.copy()
    V[0] = np.nan
    _fail(verify_nesting([fine, (V, F)]), 1, "NaN")


def test_inputs_not_modified(fine):
    V, F = _ico(3, 1.3)
    V0, F0 = V.copy(), F.copy()
    verify_nesting([fine, (V, F)])
    assert np.array_equal(V, V0) and np.array_equal(F, F0)


def test_procedural_nested_isosurfaces_of_a_torus():
    from nestmg.shapes import nested_isosurfaces

    layers = nested_isosurfaces("torus", offsets=[0.0, 0.08, 0.2], resolutions=[40, 24, 14])
    rep = verify_nesting(layers)
    assert rep.ok, str(rep)
    for p in rep.pairs:
        assert p.min_winding > 0.99
    # the offset step bounds the gap from above (vertex-to-surface distances of level sets)
    assert 0 < rep.pairs[0].min_gap < 0.08 + 1e-3


@pytest.mark.parametrize("eps", [2e-6, 1e-10])
def test_nearly_touching_layers_are_certified(eps):
    # nested cages come within ~2e-6 of the diagonal; the exact winding number stays 1 far below that
    V, F = _ico(4, 1.0)
    rep = verify_nesting([(V, F), ((1.0 + eps) * V, F)])
    assert rep.ok, str(rep)
    p = rep.pairs[0]
    assert p.min_winding == pytest.approx(1.0, abs=1e-9)
    # distance from a fine vertex to the planes of the coarse faces around its scaled copy: eps * cos(tilt)
    assert p.min_gap == pytest.approx(eps * 0.9989, rel=1e-3)
    if eps <= 1e-8:
        # the Barnes-Hut approximation misclassifies points this close (the reason exact is the default
        # where every vertex is evaluated); the per-piece decision sums exactly at the farthest vertex
        import igl

        assert igl.fast_winding_number((1.0 + eps) * V, F, V).min() < WINDING_THRESHOLD
        assert verify_nesting([(V, F), ((1.0 + eps) * V, F)], exact_winding=False).ok


def test_figures_invariant_under_similarity_transforms(fine):
    from scipy.spatial.transform import Rotation

    layers = [fine, _ico(3, 1.3)]
    ref = verify_nesting(layers).pairs[0]
    rng = np.random.default_rng(7)
    for _ in range(2):
        R = Rotation.random(random_state=rng).as_matrix()
        s = 10.0 ** rng.uniform(-3, 3)
        t = rng.uniform(-5, 5, size=3) * s
        moved = [(s * V @ R.T + t, F) for V, F in layers]
        p = verify_nesting(moved).pairs[0]
        assert p.ok and p.min_winding == pytest.approx(1.0, abs=1e-9)
        assert p.min_gap == pytest.approx(s * ref.min_gap, rel=1e-6)
        # relative to layer 0's axis-aligned box, which rotates: same order of magnitude only
        assert 0.5 * ref.min_gap_rel < p.min_gap_rel < 1.5 * ref.min_gap_rel


def _tet(V):
    from cagegen._geometry import signed_volume

    F = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    return F if signed_volume(V, F) > 0 else F[:, ::-1].copy()


@pytest.mark.parametrize("delta", [1e-3, 1e-6, 0.01])
def test_gap_found_between_edge_interiors(delta):
    # two tetrahedra whose closest features are crossing edges: the vertex-to-surface distances
    # (0.71) miss it; the edge-edge search finds delta exactly when below 1e-3 of the diagonal (3)
    VA = np.array([[-1.0, 0, 0], [1, 0, 0], [0, -1, -1], [0, 1, -1]])  # top edge along x at z = 0
    VB = np.array([[0.0, -1, delta], [0, 1, delta], [-1, 0, 1 + delta], [1, 0, 1 + delta]])  # along y
    p = verify_nesting([(VA, _tet(VA)), (VB, _tet(VB))]).pairs[0]
    assert p.n_intersecting_pairs == 0
    if delta < 3e-3:
        assert p.min_gap_exact and p.min_gap == pytest.approx(delta, rel=1e-9)
    else:  # beyond the exact-search threshold: reported as an upper bound
        assert not p.min_gap_exact and p.min_gap == pytest.approx(0.7142, abs=1e-3)
        # ...unless clearance is demanded, which searches up to min_gap and finds the edge pair
        rep = verify_nesting([(VA, _tet(VA)), (VB, _tet(VB))], min_gap=0.02 / 3)
        assert rep.pairs[0].min_gap == pytest.approx(delta, rel=1e-9) and rep.pairs[0].min_gap_exact
        assert "closer than min_gap" in rep.pairs[0].reason


def test_segment_distances_match_ipctk():
    import ipctk

    from cagegen._geometry import segment_segment_sqdist

    rng = np.random.default_rng(3)
    P0, P1, Q0, Q1 = (rng.normal(size=(400, 3)) for _ in range(4))
    Q1[:100] = Q0[:100] + (P1[:100] - P0[:100]) * rng.uniform(0.1, 2.0, size=(100, 1))  # parallel
    d = segment_segment_sqdist(P0, P1, Q0, Q1)
    ref = np.array([ipctk.edge_edge_distance(P0[i], P1[i], Q0[i], Q1[i]) for i in range(400)])
    assert np.allclose(d, ref, rtol=1e-10, atol=1e-13)


def test_winding_numbers_one_vertex_per_piece(monkeypatch):
    """Without crossings every connected piece of a layer lies in one region of the other layer's
    complement, so one winding number per piece decides it (summed directly at its farthest vertex): a
    fine layer of two spheres, one of them outside the cage, has exactly that sphere's vertices counted
    outside, with 2 + 1 evaluations; a crossing pair evaluates every vertex (libigl)."""
    import igl

    import cagegen.verify as verify

    calls: list = []
    exact, direct = igl.winding_number, verify._solid_angle_sum

    def spy(V, F, O):
        calls.append(("igl", len(O)))
        return exact(V, F, O)

    def spy_direct(V, F, q):
        calls.append(("direct", 1))
        return direct(V, F, q)

    monkeypatch.setattr(igl, "winding_number", spy)
    monkeypatch.setattr(verify, "_solid_angle_sum", spy_direct)
    a, b = _ico(2, 0.3, (0.0, 0.0, 0.0)), _ico(2, 0.3, (3.0, 0.0, 0.0))
    fine2 = (np.vstack([a[0], b[0]]), np.vstack([a[1], b[1] + len(a[0])]))
    rep = verify_nesting([fine2, _ico(3, 1.0)])
    p = rep.pairs[0]
    assert calls == [("direct", 1)] * 3 and p.n_intersecting_pairs == 0
    assert p.n_outside_vertices == len(b[0]) and p.n_coarse_inside_vertices == 0
    assert p.min_winding == pytest.approx(0.0, abs=1e-9)
    _fail(rep, 1, f"{len(b[0])} of {len(fine2[0])} fine vertices outside")
    calls.clear()
    inside = verify_nesting([a, _ico(3, 1.0)])
    assert inside.ok and len(calls) == 2 and inside.pairs[0].min_winding == pytest.approx(1.0, abs=1e-9)
    calls.clear()
    crossing = verify_nesting([a, _ico(3, 0.3, (0.2, 0.0, 0.0))])
    assert not crossing.ok and crossing.pairs[0].n_intersecting_pairs > 0
    assert calls == [("igl", len(a[0])), ("igl", len(_ico(3, 0.3)[0]))]


@pytest.mark.parametrize("seed", range(6))
def test_edge_edge_distance_matches_brute_force(seed):
    """The verifier's edge-edge search (length groups on both meshes, pairs of k-d trees) returns the minimum
    over every pair of edges, or ``bound`` when none is closer, on perturbed spheres of unequal edge lengths."""
    from cagegen._geometry import min_edge_edge_distance, segment_segment_sqdist

    rng = np.random.default_rng(seed)
    VA, FA = _ico(2, 1.0)
    VB, FB = _ico(1, 1.05 + 0.1 * rng.random(), rng.normal(0.0, 0.02, 3))
    VA = VA + rng.normal(0.0, 0.004, VA.shape)
    VB[rng.integers(len(VB))] *= 1.3  # a few long edges: more than one length group

    def edges(F):
        return np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)

    EA, EB = edges(FA), edges(FB)
    i, j = (g.ravel() for g in np.meshgrid(np.arange(len(EA)), np.arange(len(EB)), indexing="ij"))
    brute = float(np.sqrt(segment_segment_sqdist(VA[EA[i, 0]], VA[EA[i, 1]], VB[EB[j, 0]], VB[EB[j, 1]]).min()))
    for bound in (0.5 * brute, 1.5 * brute, 10.0):
        got = min_edge_edge_distance(VA, FA, VB, FB, bound)
        assert got == pytest.approx(min(bound, brute), rel=1e-14, abs=0.0), (bound, brute)
    assert min_edge_edge_distance(VA, FA, VB, FB, 10.0, chunk=7) == pytest.approx(brute, rel=1e-14)
