"""Tests of the Nested Cages backend (cagegen.nested): quadrature, energies, flow, re-inflation,
multi-layer hierarchies with certification, recovery and the min_gap option.

Shapes are small procedural surfaces (nestmg.shapes, ~2.4k-2.7k faces) so the file runs in well
under a minute.
"""

from __future__ import annotations

import json

import igl
import numpy as np
import pytest
import scipy.sparse.linalg as spla
import threadpoolctl

from cagegen import build_cages, verify_nesting
from cagegen.decimate import decimate_surface
from cagegen.nested import backend as nested_backend_module
from cagegen.nested import (
    flow_inside,
    make_energy,
    nested_backend,
    offset_surface,
    quadrature_matrix,
    quadrature_points,
    reinflate,
    triangle_rule,
)
from cagegen.collision import PairMesh, min_distance
from cagegen.nested.energies import signed_volume
from conftest import blas_threads, record_blas_threads
from nestmg import shapes


def _unit(V):
    lo, hi = V.min(0), V.max(0)
    return (V - 0.5 * (lo + hi)) / np.linalg.norm(hi - lo)


@pytest.fixture(scope="module")
def neck():
    V, F = shapes.neck_blobs(res=28)
    return V, F


@pytest.fixture(scope="module")
def genus2():
    V, F = shapes.genus2(res=30)
    return V, F


@pytest.fixture(scope="module")
def neck_pair(neck):
    """Unit-diagonal neck surface and its decimation to a quarter of the faces."""
    V, F = neck
    Vn = _unit(V)
    U, G, _ = decimate_surface(Vn, F, len(F) // 4)
    return Vn, F, U, G


@pytest.fixture(scope="module")
def neck_flow(neck_pair):
    Vn, F, U, G = neck_pair
    V_before = Vn.copy()
    res = flow_inside(Vn, F, U, G)
    assert np.array_equal(Vn, V_before), "flow_inside modified its input"
    return res


# ----------------------------------------------------------------------------- quadrature
@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
def test_triangle_rule_integrates_polynomials_exactly(order):
    b, w = triangle_rule(order)
    assert np.isclose(w.sum(), 1.0) and np.allclose(b.sum(1), 1.0)
    # ∫_T λ1^i λ2^j dA / |T| = 2 i! j! / (i + j + 2)!  for every i + j <= order
    from math import factorial

    for i in range(order + 1):
        for j in range(order + 1 - i):
            exact = 2.0 * factorial(i) * factorial(j) / factorial(i + j + 2)
            assert np.isclose(w @ (b[:, 0] ** i * b[:, 1] ** j), exact, rtol=1e-9, atol=1e-12)


def test_quadrature_points_area_and_centroid(neck):
    V, F = neck
    P, W = quadrature_points(V, F, order=2)
    area = 0.5 * igl.doublearea(V, F).sum()
    assert np.isclose(W.sum(), area, rtol=1e-12)
    # degree-1 exactness: ∫ x dA over the surface equals Σ area × centroid
    A = 0.5 * igl.doublearea(V, F)
    assert np.allclose(W @ P, A @ V[F].mean(1), rtol=1e-10, atol=1e-12)
    B, _ = quadrature_matrix(F, len(V), 2)
    assert B.shape == (3 * len(F), len(V)) and np.allclose(B.sum(1), 1.0)


def test_triangle_rule_rejects_bad_order():
    with pytest.raises(ValueError):
        triangle_rule(0)


# ----------------------------------------------------------------------------- energies
@pytest.mark.parametrize("name", ["step", "volume", "surface_arap", "volumetric_arap"])
def test_energy_gradients_match_finite_differences(neck_pair, name):
    _, _, U, G = neck_pair
    rng = np.random.default_rng(0)
    # volumetric ARAP eliminates its interior nodes iteratively: converge them for an exact gradient
    E = make_energy(name, U, G, inner_iters=200) if name == "volumetric_arap" else make_energy(name, U, G)
    C = U + 2e-3 * rng.standard_normal(U.shape)
    g = E.gradient(C)
    D = rng.standard_normal(U.shape)
    h = 1e-6
    fd = (E.value(C + h * D) - E.value(C - h * D)) / (2 * h)
    assert np.isclose(fd, np.sum(g * D), rtol=1e-5, atol=1e-10)
    M = E.metric(C)
    assert M.shape == (3 * len(U), 3 * len(U))
    x = rng.standard_normal(3 * len(U))
    assert x @ (M @ x) > 0  # positive definite metric


def test_volume_energy_is_enclosed_volume(neck_pair):
    Vn, F, _, _ = neck_pair
    # divergence theorem vs. libigl's tet volumes of a cone from the centroid
    c = Vn.mean(0)
    T = np.c_[F, np.full(len(F), len(Vn))]
    vol = igl.volume(np.vstack([Vn, c]), T).sum()
    assert np.isclose(signed_volume(Vn, F), -vol, rtol=1e-10) or np.isclose(signed_volume(Vn, F), vol, rtol=1e-10)
    assert signed_volume(Vn, F) > 0  # outward orientation


def test_volume_step_moves_small_and_large_triangles_alike():
    """The volume energy's unconstrained step is its L2 gradient flow: every vertex of a sphere moves about
    ``max_move`` along its normal, whatever the size of its triangles. (With the Euclidean metric scaled
    by the largest gradient, a vertex moved in proportion to its area: on a sphere whose triangles differ
    10x in area the small ones' vertices moved a tenth as far, and lucy.ply's first cage took 42 final
    iterations.)"""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(s.vertices, float), np.asarray(s.faces)
    V = V + [0.0, 0.0, 0.5]  # seen from (0, 0, -0.5): the vertices crowd towards the north pole
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    area = np.bincount(F.ravel(), np.repeat(igl.doublearea(V, F) / 6.0, 3))
    assert area.max() > 10 * area.min()
    E = make_energy("volume", V, F)
    step = -spla.spsolve(E.metric(V).tocsc(), E.gradient(V).ravel()).reshape(-1, 3)
    length = np.linalg.norm(step, axis=1)
    assert length.max() == pytest.approx(E.max_move, rel=1e-9)
    assert length.min() > 0.9 * E.max_move
    assert np.all(np.einsum("ij,ij->i", step, V) < -0.99 * length)  # inward, along the normal


def test_a_snap_smaller_than_half_the_gap_needs_no_ccd():
    """The reverse steps' snap (the fine surface alone onto its target) skips the CCD when every fine vertex
    moves less than half the smallest pair distance within dhat (concentric spheres 0.1 apart, dhat 0.2);
    a longer motion runs it, and is counted."""
    import importlib

    import trimesh

    from cagegen.collision import PairMesh

    R = importlib.import_module("cagegen.nested.reinflate")  # the package re-exports the function's name
    s = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(s.vertices, float), np.asarray(s.faces)
    pair = PairMesh(1.1 * V, F, V, F)
    prob = R._Problem(pair, make_energy("step", 1.1 * V, F), 0.2, 1e4, 1e3)
    X = pair.stack(1.1 * V, V)
    gap = float(np.sqrt(prob._collisions(X).compute_minimum_distance(pair.mesh, X)))
    assert 0.09 < gap <= 0.1
    near = X.copy()
    near[pair.nc:] *= 1 + 0.45 * gap  # every fine vertex moves 0.45 gap outwards
    far = X.copy()
    far[pair.nc:] *= 1 + 0.55 * gap
    assert prob.snap_is_free(X, near) and prob.n_ccd == 0 and prob.n_snap_free == 1
    assert not prob.snap_is_free(X, far) and prob.n_ccd == 1
    assert pair.stepsize(X, far) == 1.0  # free in fact, but the bound cannot tell: the CCD decides


def test_complete_clearance_falls_back_to_the_tightest_clear_looser_cage(monkeypatch):
    """When ``push_out`` is blocked, :func:`complete_clearance` returns the tightest of the final phase's
    looser cages that keeps ``gap / GAP_AIM`` (concentric spheres around a unit sphere: radius 1.3 for a
    clearance of 0.25), by bisection; without looser cages, or when even the loosest is too close, the
    cage itself and its distance, as before."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3)
    Vf, Ff = np.asarray(s.vertices, float), np.asarray(s.faces)
    radii = [1.6, 1.5, 1.4, 1.3, 1.2, 1.1]
    looser = [r * Vf for r in radii]
    C = 1.02 * Vf
    gap = 0.25 * nested_backend_module.GAP_AIM
    monkeypatch.setattr(nested_backend_module, "push_out", lambda *a, **k: (None, {"reason": "blocked"}))
    C2, d2, rec = nested_backend_module.complete_clearance(C, Ff, Vf, Ff, gap, looser)
    assert np.array_equal(C2, looser[3]) and d2 == pytest.approx(min_distance(C2, Ff, Vf, Ff), rel=1e-12)
    assert 0.25 <= d2 < 0.3 and rec["looser_iterate"] == 3 and rec["looser_tried"] <= 4
    C3, d3, _ = nested_backend_module.complete_clearance(C, Ff, Vf, Ff, gap)
    assert C3 is C and d3 < 0.25
    C4, d4, rec4 = nested_backend_module.complete_clearance(C, Ff, Vf, Ff, gap, [1.1 * Vf])
    assert C4 is C and d4 < 0.25 and "looser_iterate" not in rec4


def test_unknown_energy_is_rejected(neck):
    V, F = neck
    with pytest.raises(ValueError, match="energy"):
        nested_backend(V, F, [500], energy="bogus")
    with pytest.raises(ValueError, match="unknown option"):
        nested_backend(V, F, [500], not_an_option=1)


# ----------------------------------------------------------------------------- flow
def test_flow_moves_fine_surface_strictly_inside(neck_pair, neck_flow):
    Vn, F, U, G = neck_pair
    res = neck_flow
    assert res.success, res.reason
    assert res.history[0] is not Vn and np.array_equal(res.history[0], Vn)
    Fbar = res.history[-1]
    # the flow really moved the surface (the decimation pokes out of the fine surface)
    S0, _, _, _ = igl.signed_distance(Vn, U, G)
    assert S0.max() > 1e-3
    assert np.abs(Fbar - Vn).max() > 1e-3
    # every flowed vertex and quadrature point has winding number 1 w.r.t. Ĉ (exact evaluation)
    P, _ = quadrature_points(Fbar, F, order=2)
    w = igl.winding_number(U, G, np.vstack([Fbar, P]))
    assert w.min() > 0.999 and w.max() < 1.001
    assert res.max_signed_distance < 0
    pm = PairMesh(U, G, Fbar, F)
    assert not pm.intersects(pm.stack(U, Fbar))


def test_flow_reports_failure_when_capped(neck_pair):
    Vn, F, U, G = neck_pair
    res = flow_inside(Vn, F, U, G, max_iter=1)
    assert not res.success and "1 iterations" in res.reason


# ----------------------------------------------------------------------------- re-inflation
@pytest.mark.parametrize("energy", ["step", "volume"])
def test_reinflation_returns_fine_surface_to_rest_and_nests(neck_pair, neck_flow, energy):
    Vn, F, U, G = neck_pair
    U_before = U.copy()
    rr = reinflate(neck_flow.history, F, U, G, energy=energy)
    assert rr.success, rr.reason
    assert np.array_equal(U, U_before), "reinflate modified the target cage"
    # exact: the fine surface is back at its rest positions bit for bit
    assert np.array_equal(rr.fine, Vn)
    rep = verify_nesting([(Vn, F), (rr.cage, G)])
    assert rep.ok, str(rep)
    vol_ratio = signed_volume(rr.cage, G) / signed_volume(Vn, F)
    assert 1.0 < vol_ratio < 1.15
    if energy == "volume":
        assert rr.stats["volume_after_final"] < rr.stats["volume_before_final"]


def test_reverse_steps_dhat_at_most_half_the_fine_mean_edge(neck_pair, neck_flow):
    """dhat and max_move of the reverse steps shrink by one factor to half the fine surface's mean edge
    (DHAT_PER_EDGE), and only when they exceed it; the cage still nests."""
    import importlib

    rf = importlib.import_module("cagegen.nested.reinflate")
    Vn, F, U, G = neck_pair
    h = float(np.mean([np.linalg.norm(Vn[F[:, i]] - Vn[F[:, (i + 1) % 3]], axis=1).mean() for i in range(3)]))
    diag = float(np.linalg.norm(np.ptp(Vn, axis=0)))
    assert rf.DHAT_PER_EDGE == 0.5 and 0.5 * h / diag > 5e-3  # the default dhat is below half an edge here
    rr = reinflate(neck_flow.history, F, U, G, final_iters=0)
    assert (rr.stats["dhat"], rr.stats["max_move"]) == (5e-3, 5e-3)
    rr = reinflate(neck_flow.history, F, U, G, dhat=0.04, max_move=0.02, final_iters=0)
    assert rr.success, rr.reason
    assert rr.stats["dhat"] == pytest.approx(0.5 * h / diag, rel=1e-12)
    assert rr.stats["max_move"] == pytest.approx(0.25 * h / diag, rel=1e-12)
    assert rr.stats["reverse_steps"] == len(rf.resample_history(neck_flow.history, 0.25 * h)) - 1
    assert verify_nesting([(Vn, F), (rr.cage, G)]).ok


def test_reinflation_snaps_onto_the_rest_pose_from_a_tenth_of_dhat(neck_pair, neck_flow):
    """The last reverse step puts F onto its rest pose once within 0.1 dhat (if the CCD allows; the others
    within 0.01): on the clearance path (rest pose = the offset surface) F still ends at it bit for bit,
    and the cage keeps the gap."""
    import inspect

    Vn, F, U, G = neck_pair
    params = inspect.signature(reinflate).parameters
    assert (params["snap_tol"].default, params["last_snap_tol"].default) == (0.01, 0.1)
    gap = 0.0025
    target = offset_surface(Vn, F, 1.1 * gap)
    rr = reinflate([target, *neck_flow.history], F, U, G)
    assert rr.success, rr.reason
    assert np.array_equal(rr.fine, target)
    assert verify_nesting([(Vn, F), (rr.cage, G)]).ok
    assert min_distance(rr.cage, G, Vn, F) >= gap


@pytest.mark.parametrize("energy", ["surface_arap", "volumetric_arap"])
def test_arap_energies_nest(neck_pair, neck_flow, energy):
    Vn, F, U, G = neck_pair
    rr = reinflate(neck_flow.history, F, U, G, energy=energy, final_iters=20)
    assert rr.success and np.array_equal(rr.fine, Vn)
    assert verify_nesting([(Vn, F), (rr.cage, G)]).ok


# ----------------------------------------------------------------------------- multi-layer backend
@pytest.fixture(scope="module")
def neck_layers(neck):
    V, F = neck
    V0, F0 = V.copy(), F.copy()
    layers, info = nested_backend(V, F, [600, 150, 40])
    assert np.array_equal(V, V0) and np.array_equal(F, F0), "backend modified its input"
    return layers, info


def test_neck_three_cages_certified(neck, neck_layers):
    V, F = neck
    layers, info = neck_layers
    assert len(layers) == 3
    rep = verify_nesting([(V, F)] + layers)
    assert rep.ok, str(rep)
    for (Vk, Fk), target, li in zip(layers, [600, 150, 40], info["layers"]):
        assert Vk.dtype == np.float64 and Fk.dtype == np.int64
        assert abs(len(Fk) - target) <= 4
        assert li["min_gap_absolute"] > 0
        assert li["volume_ratio"] > 1.0
        assert li["verification"]["ok"]
        assert {"flow", "reinflate", "final_energy", "decimate", "verify"} <= set(li["seconds"])
    # the finest cage is tight: within 4% of the input volume, 2% of the diagonal
    assert info["layers"][0]["volume_ratio"] < 1.04
    assert info["layers"][0]["hausdorff_relative"] < 0.02
    json.dumps(info)  # JSON-serialisable


def test_layer_gap_is_the_distance_to_the_previous_layer(neck, neck_layers):
    """``min_gap_absolute`` (taken from the clearance step's measurement at unit diagonal, scaled) is the
    distance to the previous layer in the caller's units, and the internal record does not leak."""
    V, F = neck
    layers, info = neck_layers
    prev = (V, F)
    for (Vk, Fk), li in zip(layers, info["layers"]):
        d = min_distance(Vk, Fk, *prev)
        assert li["min_gap_absolute"] == pytest.approx(d, rel=1e-9)
        assert "clearance_distance" not in li
        prev = (Vk, Fk)


def test_layer_gap_after_an_intermediate_layer_is_measured_again(neck, monkeypatch, failing_flow):
    """After a recovery the clearance was measured against the intermediate layer: not reused."""
    V, F = neck
    real = nested_backend_module.flow_inside

    def flaky(Vf, Ff, Vc, Fc, **kw):  # every target of 600 faces around the input fails
        if len(Fc) <= 620 and len(Ff) >= len(F):
            return failing_flow(Vf, Ff, Vc, Fc, **kw)
        return real(Vf, Ff, Vc, Fc, **kw)

    monkeypatch.setattr(nested_backend_module, "flow_inside", flaky)
    layers, info = nested_backend(V, F, [600])
    li = info["layers"][0]
    assert "intermediate" in li
    assert li["min_gap_absolute"] == pytest.approx(min_distance(*layers[0], V, F), rel=1e-9)


def test_genus2_three_cages_certified(genus2):
    V, F = genus2
    layers, info = nested_backend(V, F, [700, 180, 100])
    rep = verify_nesting([(V, F)] + layers)
    assert rep.ok, str(rep)
    assert len(layers) == 3
    # the handles survive: every cage keeps genus 2 (χ = 2 - 2g = -2)
    for Vk, Fk in layers:
        E = igl.edges(Fk)
        assert len(Vk) - len(E) + len(Fk) == -2
    assert info["layers"][0]["volume_ratio"] < 1.1


def test_build_cages_integration(neck):
    V, F = neck
    layers, info = build_cages(V, F, levels=3, method="nested", return_info=True)
    assert info["certified"] and info["nested"]
    assert len(layers) == 3 and layers[0][0].shape == V.shape


def test_min_gap_is_kept(neck):
    V, F = neck
    diag = np.linalg.norm(np.ptp(V, axis=0))
    layers, info = nested_backend(V, F, [600], min_gap=4e-3)
    gap = min_distance(layers[0][0], layers[0][1], V, F)
    assert gap >= 4e-3 * diag
    assert info["layers"][0]["min_gap_relative"] >= 4e-3
    assert verify_nesting([(V, F)] + layers, min_gap=4e-3).ok


def test_offset_surface_clears_face_planes(neck):
    V, F = neck
    W = offset_surface(V, F, 0.01)
    FN = igl.per_face_normals(V, F, np.array([0.0, 0.0, 1.0]))
    # every offset vertex is at least 0.01 in front of the planes of its incident faces
    for k in range(3):
        h = np.einsum("ij,ij->i", W[F[:, k]] - V[F[:, k]], FN)
        assert h.min() >= 0.01 - 1e-12


def test_offset_surface_moves_a_needle_tip_by_the_fold_factor():
    """A needle (square pyramid 20x taller than wide): its tip's normal is ~87 degrees from every face's,
    past the 3x clamp; ``fold_factor`` sets its offset (1: the gap itself, the re-inflation's target)
    and leaves every other vertex where the clamped rule puts it."""
    a, h, g = 0.05, 1.0, 0.01
    V = np.array([[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0], [0, 0, h]], dtype=float)
    F = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    W3, W1 = offset_surface(V, F, g), offset_surface(V, F, g, fold_factor=1.0)
    assert np.allclose(W3[4] - V[4], [0, 0, 3 * g]) and np.allclose(W1[4] - V[4], [0, 0, g])
    assert np.array_equal(W3[:4], W1[:4])


def test_push_out_separates_a_cage_edge_crossing_a_sharp_edge(monkeypatch):
    """A cage edge passing 0.4 gap over a cube's edge, every vertex of either surface at least 10 gap
    from the other: the closest pair is edge-edge (:func:`cagegen.collision.close_edge_pairs` finds it,
    with the direction from the cube's edge to the cage's), and one pass of ``push_out`` clears it. Moved
    by the point distances alone nothing moves and the passes run out (the repaired box_parts.stl's
    envelope cage stopped at 0.00185 of 0.0025 so, where a cage edge crossed a part's edge)."""
    import trimesh

    from cagegen.collision import close_edge_pairs

    box = trimesh.creation.box(extents=(2, 2, 2))
    Vf, Ff = np.asarray(box.vertices, float), np.asarray(box.faces)
    gap = 0.05
    e, t = 0.4 * gap / np.sqrt(2), 0.5
    pts = np.array([(1 + e + t, 1 + e - t, 0), (1 + e - t, 1 + e + t, 0), (3, 3, 0.3), (3, 3, -0.3)])
    hull = trimesh.convex.convex_hull(pts)
    Vc, Fc = np.asarray(hull.vertices, float), np.asarray(hull.faces)
    assert min_distance(Vc, Fc, Vf, Ff) == pytest.approx(0.4 * gap, rel=1e-9)
    assert np.sqrt(igl.point_mesh_squared_distance(Vc, Vf, Ff)[0]).min() > 10 * gap
    assert np.sqrt(igl.point_mesh_squared_distance(Vf, Vc, Fc)[0]).min() > 10 * gap
    E, d, D = close_edge_pairs(Vc, Fc, Vf, Ff, 1.05 * gap)
    assert len(E) == 1 and np.allclose(np.sort(pts[:2], 0), np.sort(Vc[E[0]], 0))
    assert d[0] == pytest.approx(0.4 * gap, rel=1e-9) and np.allclose(D[0], [2 ** -0.5, 2 ** -0.5, 0])
    C2, info = nested_backend_module.push_out(Vc, Fc, Vf, Ff, gap)
    assert C2 is not None and info["passes"] == 1 and min_distance(C2, Fc, Vf, Ff) >= gap
    # the restricted target of a blocked pass moves the violating edge's ends only
    adj = igl.adjacency_matrix(Fc).tocsr()
    near = nested_backend_module._near_parts(Vc, Fc, Vf, Ff, 1.05 * gap)
    T = nested_backend_module._push_target(Vc, Fc, gap, adj, near, gap, soften=False)
    moved = np.flatnonzero(np.abs(T - Vc).max(axis=1) > 0)
    assert np.array_equal(np.sort(moved), np.sort(E[0]))
    assert np.allclose(T[moved] - Vc[moved], (1.07 - 0.4) * gap * D[0])
    # complete_clearance: one distance before the push, one after its pass (none measured twice)
    calls = []
    real = nested_backend_module.min_distance
    monkeypatch.setattr(nested_backend_module, "min_distance", lambda *a, **k: calls.append(1) or real(*a, **k))
    C4, d4, rec = nested_backend_module.complete_clearance(Vc, Fc, Vf, Ff, gap)
    assert len(calls) == 2 and rec["passes"] == 1 and np.array_equal(C4, C2)
    assert d4 == real(C4, Fc, Vf, Ff) >= gap
    empty = (np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, 3)))
    monkeypatch.setattr(nested_backend_module, "close_edge_pairs", lambda *a: empty)
    C3, info = nested_backend_module.push_out(Vc, Fc, Vf, Ff, gap)
    assert C3 is None and info["distance"] == pytest.approx(0.4 * gap, rel=1e-6)


def test_recovery_after_flow_failure(neck, monkeypatch, failing_flow):
    """A failing flow (the paper's 'Ĉ too far from F') is recovered and recorded in info."""
    V, F = neck
    real = nested_backend_module.flow_inside
    calls = {"n": 0}

    def flaky(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 1:
            return failing_flow(*args, **kw)
        return real(*args, **kw)

    monkeypatch.setattr(nested_backend_module, "flow_inside", flaky)
    layers, info = nested_backend(V, F, [600])
    assert calls["n"] >= 2
    assert info["recovery"] and info["recovery"][0]["stage"] == "flow"
    assert verify_nesting([(V, F)] + layers).ok


def test_only_the_last_target_gets_the_full_flow_cap(neck, monkeypatch, failing_flow):
    """Every target Ĉ but the last one tried gets a flow cap of QUICK_FLOW_WORK / fine faces iterations
    (at least QUICK_FLOW_MIN_ITER), so a plateaued flow cannot spend minutes before the next target;
    the last target keeps the full ``flow_max_iter``."""
    V, F = neck
    caps: list = []

    def record(*args, **kw):
        caps.append((len(args[1]), kw["max_iter"]))
        return failing_flow(*args, **kw)

    monkeypatch.setattr(nested_backend_module, "flow_inside", record)
    monkeypatch.setattr(nested_backend_module, "QUICK_FLOW_WORK", 40 * len(F))
    with pytest.raises(Exception):
        nested_backend(V, F, [600], max_recovery_depth=0, fallback=None)
    assert len(caps) == 3  # layer decimated by qslim, its envelope, the layer by the other decimator
    (n0, c0), (n1, c1), (n2, c2) = caps
    assert c0 == max(nested_backend_module.QUICK_FLOW_MIN_ITER, 40 * len(F) // n0) < 1000
    assert c1 == max(nested_backend_module.QUICK_FLOW_MIN_ITER, 40 * len(F) // n1) < 1000
    assert c2 == 1000


def test_unrecoverable_layer_raises_cage_error(neck, monkeypatch, failing_flow):
    V, F = neck
    monkeypatch.setattr(nested_backend_module, "flow_inside",
                        failing_flow)
    from cagegen.errors import CageError

    with pytest.raises(CageError) as exc:
        nested_backend(V, F, [600], max_recovery_depth=0, fallback=None)
    assert exc.value.layer == 1



def test_default_fallback_is_a_certified_sdf_layer(neck, monkeypatch, failing_flow):
    """A layer whose flow fails (forced) and whose intermediate layers are not allowed falls back by
    default to an sdf cage (MIT) of exactly the requested size, certified."""
    V, F = neck
    monkeypatch.setattr(nested_backend_module, "flow_inside",
                        failing_flow)
    layers, info = nested_backend(V, F, [600], max_recovery_depth=0)
    li = info["layers"][0]
    assert li["fallback"] == "sdf" and len(layers[0][1]) == 600
    assert li["verification"]["ok"] is True
    assert verify_nesting([(V, F)] + layers).ok
    assert any(r["stage"] == "fallback" for r in info["recovery"])
    # (that nothing copyleft is loaded is checked in a fresh process: test_nestmg_usermesh's licence probe)

def test_decimate_from_input_nests_previous_layer(neck):
    """Targets decimated from the input (not the previous cage) still nest the previous layer."""
    V, F = neck
    layers, info = nested_backend(V, F, [600, 150], decimate_from="input")
    assert verify_nesting([(V, F)] + layers).ok
    assert info["decimate_from"] == "input"
    assert info["layers"][1]["volume_ratio_to_input"] > info["layers"][0]["volume_ratio_to_input"] > 1.0


def test_reinflation_step_gives_up_when_it_stops_converging():
    """A reverse step stops once its best |F - target| has not halved in STALL_NEWTON iterations (the
    |F - target| of cheburashka.obj's stuck clearance step, in units of 1e-5 of the diagonal)."""
    import importlib

    rf = importlib.import_module("cagegen.nested.reinflate")
    seq = [328, 297, 281, 256, 218, 187, 157, 130, 130, 131, 133, 134, 135] + [134, 133] * 30
    best, stop = [330.0], None
    for i, g in enumerate(seq):
        best.append(min(best[-1], g))
        if rf._stalled(best):
            stop = i + 1
            break
    # iteration 24: the best 130 is more than half of 256, the best 20 iterations before (the real run
    # stopped there too, instead of running on to max_newton = 60)
    assert rf.STALL_NEWTON == 20
    assert stop == 24
    halving = [330.0 * 0.7 ** i for i in range(60)]  # steady progress: never stalls
    assert not any(rf._stalled(halving[: k + 1]) for k in range(60))


def _dented_box_pair(depth: float):
    """F: the cube [-1, 1]^3 (12 triangles); Ĉ: the cube [-1.05, 1.05]^3 with a vertex at the centre of
    its top face pushed down by ``depth`` (0.1: the dent's apex at z = 0.95 crosses F's top face while
    every quadrature point of F, 1/6 of a triangle from its edges, stays inside Ĉ)."""
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    Vf, Ff = np.asarray(box.vertices, float), np.asarray(box.faces, np.int64)
    cage = trimesh.creation.box(extents=(2.1, 2.1, 2.1)).subdivide()
    Vc, Fc = np.array(cage.vertices, float), np.asarray(cage.faces, np.int64)
    top = np.flatnonzero(np.isclose(Vc[:, 2], 1.05) & np.isclose(np.abs(Vc[:, :2]).sum(1), 0.0))
    assert len(top) == 1
    Vc[top, 2] -= depth
    return Vf, Ff, Vc, Fc


def test_flow_expands_the_target_where_it_crosses_a_surface_already_inside():
    """All quadrature points inside but Ĉ crossing F̄: Ĉ is expanded after ``expand_after`` such
    iterations (it used to wait for 37, then every 25: 100 iterations on featuretype.stl's envelope)."""
    from cagegen.nested import flow as flow_module

    Vf, Ff, Vc, Fc = _dented_box_pair(0.1)
    fl = flow_module._Flow(Vf, Ff, Vc, Fc, 2, None)
    assert fl.S.max() < 0.0  # every quadrature point inside Ĉ
    assert fl.pair.intersects(fl.pair.stack(fl.Vc, fl.V))
    actions = [flow_module._when_inside(fl, 150, 5, 20) for _ in range(5)]
    assert actions == ["", "", "", "", "again"]
    assert fl.n_expand == 1
    assert fl.Vc[:, 2].max() > 1.05  # the dent's faces moved out
    res = flow_module.flow_inside(Vf, Ff, Vc, Fc, expand_after=5)
    assert res.success and res.iterations <= 10


def _two_boxes(top_rotation_deg: float, lift: float):
    """F: the cube [-1, 1]^2 x [-2, 0] and, above it, a cube of side 2 rotated about the y axis and lifted
    so that its lowest point is ``lift`` above z = 0 (two components, closed)."""
    import trimesh

    a = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    a.apply_translation((0.0, 0.0, -1.0))
    b = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    b.apply_transform(trimesh.transformations.rotation_matrix(np.radians(top_rotation_deg), (0, 1, 0)))
    b.apply_translation((0.0, 0.0, lift - b.vertices[:, 2].min()))
    V = np.vstack([a.vertices, b.vertices])
    F = np.vstack([a.faces, b.faces + len(a.vertices)]).astype(np.int64)
    return V, F


def test_crossings_plateau_rule():
    """The flow's inside phase stops when the fewest crossing pairs of the last window are no fewer than
    those of the window before (featuretype.stl's second layer: 8 early, then 22-24 for 60 iterations)."""
    from cagegen.nested.flow import _crossings_plateaued

    counts = [10, 8, 24, 24, 22, 24, 24, 24]
    assert _crossings_plateaued(counts, 20, 5)
    assert not _crossings_plateaued(counts[:-1], 20, 5)  # fewer than two windows of counts
    assert not _crossings_plateaued(counts, None, 5)
    assert not _crossings_plateaued([60, 32, 66, 44, 102, 60, 35, 7], 20, 5)  # still clearing


def test_flow_inside_phase_stops_when_crossings_do_not_fall():
    """Every point inside, Ĉ crossing F̄ and nothing clearing it (no expansion left): with a plateau
    window the flow gives up after two windows of counts, without one only at ``stall_iter``."""
    from cagegen.nested import flow as flow_module

    Vf, Ff, Vc, Fc = _dented_box_pair(0.1)
    fl = flow_module._Flow(Vf, Ff, Vc, Fc, 2, None)
    actions = [flow_module._when_inside(fl, 150, 5, 0, 20) for _ in range(40)]
    assert actions[:36] == [""] * 36 and actions[36] == "again"  # the denser quadrature at 150 // 4
    assert actions[37:] == ["", "", "plateaued"]
    assert len(fl.crossings) == 8 and len(set(fl.crossings)) == 1 and fl.crossings[0] > 0
    fl = flow_module._Flow(Vf, Ff, Vc, Fc, 2, None)
    actions = [flow_module._when_inside(fl, 150, 5, 0, None) for _ in range(150)]
    assert "plateaued" not in actions and actions[-1] == "stalled"


def test_narrow_slot_vertices_finds_points_between_facing_walls_only():
    """A point between two parallel walls 0.02 apart is in a slot narrower than 0.03, not than 0.015; a
    point above the top face, or under a wall tilted by 45 degrees (a crease, not a slot), is not."""
    slot = nested_backend_module.narrow_slot_vertices
    V, F = _two_boxes(0.0, 0.02)
    U = np.array([[0.1, 0.2, 0.01], [0.1, 0.2, 2.1], [0.1, 0.2, -0.01]])  # slot, above, inside F
    assert slot(U, V, F, 0.03).tolist() == [0]
    assert slot(U, V, F, 0.015).tolist() == []
    V, F = _two_boxes(45.0, 0.02)  # the ray from (0.1, 0.2, 0) up meets the tilted face at z = 0.12
    assert slot(np.array([[0.1, 0.2, 0.01]]), V, F, 0.5).tolist() == []


def test_a_quick_flow_stops_when_it_makes_no_progress():
    """The plateau rule: no lower largest signed distance in the last window than in the one before."""
    from cagegen.nested import flow as flow_module

    rising = list(np.linspace(0.002, 0.013, 60))
    stops = [k for k in range(1, 61) if flow_module._plateaued(rising[:k], k, 20, 0.0, 1.0)]
    assert stops[0] == 40  # the first check after twice the window
    slow = list(0.01 * 0.99 ** np.arange(300))  # lucy-like slow but steady progress: never stops
    assert not any(flow_module._plateaued(slow[:k], k, 20, 0.0, 1.0) for k in range(1, 301))
    assert not flow_module._plateaued(rising, 60, None, 0.0, 1.0)  # off by default


def test_a_layer_target_in_a_slot_narrower_than_the_clearance_goes_behind_the_envelopes():
    """_build_layer's order: a decimated layer with a vertex in a slot narrower than twice the clearance
    is tried after the envelope targets, once; without an envelope after it, or without a clearance,
    it keeps its place (no probe)."""
    probe = nested_backend_module._slot_probe
    V, F = _two_boxes(0.0, 0.02)
    U, G = np.array([[0.1, 0.2, 0.01]]), np.zeros((0, 3), dtype=np.int64)
    sources = [("layer", "qslim", None), ("envelope", "qslim", 0.05), ("layer", "shortest_edge", None)]
    with pytest.raises(nested_backend_module._Slotted, match="1 vertex"):
        probe(V, F, 0.015, sources, 0, set())(U, G)
    assert probe(V, F, 0.005, sources, 0, set())(U, G) is None  # the slot is wider than 2 x 0.005
    assert probe(V, F, 0.015, sources, 0, {sources[0]}) is None  # moved once only
    assert probe(V, F, 0.0, sources, 0, set()) is None  # no clearance asked
    assert probe(V, F, 0.015, sources[:1] + sources[2:3], 0, set()) is None  # no envelope follows
    assert probe(V, F, 0.015, sources, 1, set()) is None  # an envelope target is never deferred


def test_decimation_stops_at_the_first_attempt_its_inspection_rejects():
    """decimate_surface(inspect=): called on every attempt before the attempt's checks; its exception ends
    the decimation (the slot test above needs no self-intersection-free attempt)."""
    from cagegen.decimate import decimate_surface

    V, F = shapes.sphere(res=24)
    seen = []

    def reject(U, G):
        seen.append(len(G))
        raise KeyError("slotted")

    with pytest.raises(KeyError, match="slotted"):
        decimate_surface(V, F, 200, inspect=reject)
    assert seen == [200]
    U, G, info = decimate_surface(V, F, 200, inspect=lambda U, G: seen.append(len(G)))
    assert len(G) == 200 and seen == [200, 200] and len(info["attempts"]) == 1


def test_the_flow_queries_again_only_the_points_that_may_have_come_near_the_target(monkeypatch):
    """_Flow.evaluate: a point deeper than DEEP_POINT_DEPTH that cannot have come closer keeps its closest
    point (its value bounds the exact one from below, within its motion); every other point is exact."""
    import trimesh

    from cagegen.nested import flow as flow_module

    big = trimesh.creation.icosphere(subdivisions=3)
    small = trimesh.creation.icosphere(subdivisions=2)
    Vc, Fc = np.asarray(big.vertices), np.asarray(big.faces, dtype=np.int64)
    Vf, Ff = 0.5 * np.asarray(small.vertices), np.asarray(small.faces, dtype=np.int64)
    fl = flow_module._Flow(Vf, Ff, Vc, Fc, 2, None)
    queried = []
    exact = flow_module._signed_distance
    monkeypatch.setattr(flow_module, "_signed_distance",
                        lambda P, V, F: queried.append(len(P)) or exact(P, V, F))
    fl.evaluate(fl.V)
    assert queried == [len(fl.S)] and len(fl.S) < flow_module.DEEP_POINT_MIN_POINTS  # small: always exact
    assert fl._exact is None  # ... and keeps no cache
    monkeypatch.setattr(flow_module, "DEEP_POINT_MIN_POINTS", 0)
    fl.evaluate_here()  # the cache, at the flow's positions

    def check(V):
        queried.clear()
        P, S, Q, N, W = fl.evaluate(V)
        S_true = exact(P, Vc, Fc)[0]
        moved = np.linalg.norm(P - fl.B @ fl.V, axis=1)
        assert np.all(S <= S_true + 1e-12) and np.all(S_true - S <= 2 * moved + 1e-12)
        near = S_true > -flow_module.DEEP_POINT_DEPTH * fl.diag
        np.testing.assert_allclose(S[near], S_true[near], atol=1e-12)
        assert np.count_nonzero(near) <= sum(queried) <= np.count_nonzero(moved > 0)
        return S, S_true, near

    S, S_true, near = check(fl.V * 1.02)  # every point ~0.49 deep, moved 0.01: none queried again
    assert sum(queried) == 0 and not near.any()
    assert np.abs(S - S_true).max() > 0  # ... and their values are bounds, not the exact ones
    one_side = fl.V.copy()
    one_side[Vf[:, 0] > 0] *= 2.1  # these move out of Ĉ (radius 1.05): queried again, exact
    S, S_true, near = check(one_side)
    assert near.sum() > 0.3 * len(S) and sum(queried) < len(S)
    fl.evaluate_here()  # Ĉ changed (expansion) or a new quadrature: every point again
    assert queried[-1] == len(S)


def test_newton_systems_large_by_cg_small_by_lu_with_lu_when_cg_fails(monkeypatch):
    """_solve_spd: Jacobi-CG from NEWTON_CG_MIN_SIZE unknowns, sparse LU below it and when CG does not
    converge, to round-off; above NEWTON_LU_MAX_SIZE an unconverged CG's iterate (truncated Newton)."""
    import importlib

    import scipy.sparse as sp

    rm = importlib.import_module("cagegen.nested.reinflate")
    calls = []
    cg = rm.spla.cg
    monkeypatch.setattr(rm.spla, "cg", lambda *a, **k: calls.append(1) or cg(*a, **k))
    rng = np.random.default_rng(3)

    def spd(n):  # a grid Laplacian (a mesh-like sparsity: LU stays cheap) plus a positive diagonal
        k = int(np.ceil(n ** (1 / 3)))
        T = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
        I = sp.identity(k)
        K = sp.kron(sp.kron(T, I), I) + sp.kron(sp.kron(I, T), I) + sp.kron(sp.kron(I, I), T)
        return (K + sp.diags(0.1 + rng.random(k ** 3))).tocsc(), rng.standard_normal(k ** 3)

    def rel_residual(H, x, g):
        return np.linalg.norm(H @ x - g) / np.linalg.norm(g)

    H, g = spd(rm.NEWTON_CG_MIN_SIZE + 10)
    assert rel_residual(H, rm._solve_spd(H, g), g) < 1e-9 and len(calls) == 1
    Hs, gs = spd(500)
    assert rel_residual(Hs, rm._solve_spd(Hs, gs), gs) < 1e-12 and len(calls) == 1  # small: LU only
    monkeypatch.setattr(rm, "NEWTON_CG_MAXITER", 1)
    assert rel_residual(H, rm._solve_spd(H, g), g) < 1e-12 and len(calls) == 2  # CG gave up: LU
    # above NEWTON_LU_MAX_SIZE: no LU, CG's iterate is the direction, a descent direction of the
    # quadratic model q(x) = x.Hx/2 - g.x, not the solution
    monkeypatch.setattr(rm, "NEWTON_CG_MAXITER", 5)
    monkeypatch.setattr(rm, "NEWTON_LU_MAX_SIZE", H.shape[0] - 1)
    monkeypatch.setattr(rm.spla, "splu", lambda *a, **k: pytest.fail("SuperLU above NEWTON_LU_MAX_SIZE"))
    x = rm._solve_spd(H, g)
    assert len(calls) == 3 and rel_residual(H, x, g) > 1e-3
    assert g @ x > 0 and 0.5 * x @ (H @ x) - g @ x < 0


def test_the_envelope_target_grid_is_refined_when_the_envelope_would_be_coarser_than_the_target(monkeypatch):
    """_envelope_spacing: h = offset with no probe when the area bound says the envelope is fine enough;
    halved (at most twice) while the un-amplified envelope has too few faces for the target."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3)
    V, F = _unit(np.asarray(sphere.vertices)), np.asarray(sphere.faces, dtype=np.int64)
    probes = []
    real = nested_backend_module.build_envelope

    def probe(*a, **k):
        probes.append(k["h"])
        return real(*a, **k)

    monkeypatch.setattr(nested_backend_module, "build_envelope", probe)
    spacing = nested_backend_module._envelope_spacing
    assert spacing(V, F, 500, 0.01) == 0.01 and probes == []  # far coarser target: no probe
    faces_at = {h: len(real(V, F, c=0.01, h=h, band=0.04, amplify=False).F) for h in (0.01, 0.005)}
    n = int(faces_at[0.01] / nested_backend_module.ENVELOPE_FACE_MARGIN) + 1  # just too many for h = 0.01
    assert faces_at[0.005] > nested_backend_module.ENVELOPE_FACE_MARGIN * n
    assert spacing(V, F, n, 0.01) == 0.005 and probes == [0.01]  # at 0.005 the area bound suffices
    probes.clear()
    assert spacing(V, F, 10 ** 7, 0.01) == 0.0025 and probes == [0.01, 0.005]  # a quarter at most


def test_target_dilation_tests_only_moved_faces_and_finds_what_the_full_test_finds(monkeypatch):
    """_dilate_target's rounds after the first test self-intersections of the faces that moved only;
    the dilation must be the one the whole-mesh test gives (a torus whose hole closes when dilated:
    8 rounds, pairs found in the later ones, vertices held)."""
    import trimesh

    from cagegen import intersect

    t = trimesh.creation.torus(1.0, 0.99, 48, 24)
    V, F = np.asarray(t.vertices), np.asarray(t.faces, dtype=np.int64)
    full = intersect.self_pairs
    calls = []

    def recorded(V, F, only=None):
        pairs = full(V, F, only)
        calls.append((None if only is None else len(only), len(pairs)))
        return pairs

    monkeypatch.setattr(intersect, "self_pairs", recorded)
    W, info = nested_backend_module._dilate_target(V, F, 2.0)
    monkeypatch.setattr(intersect, "self_pairs", lambda V, F, only=None: full(V, F))
    W_full, info_full = nested_backend_module._dilate_target(V, F, 2.0)
    assert np.array_equal(W, W_full) and info == info_full
    assert info["rounds"] >= 3 and info["held"] > 0
    assert calls[0][0] is None  # the first round tests the whole mesh
    # later rounds test a part of the mesh, and find pairs there
    assert all(n is not None for n, _ in calls[1:])
    assert any(n < len(F) and found for n, found in calls[1:])


def test_backend_runs_with_one_blas_thread(neck, monkeypatch):
    """The nested backend's BLAS work (Newton-CG dot products) runs on one thread, and the caller's
    thread count is back afterwards (OpenBLAS threads spinning beside ipctk's pool slowed it down)."""
    inside = record_blas_threads(monkeypatch, nested_backend_module, "reinflate")
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        V, F = neck
        nested_backend(V, F, [600])
        after = blas_threads()
    assert inside and set(inside) == {1}
    assert after == before


def test_cage_threads_one_gives_the_same_cages_every_run(neck, monkeypatch):
    """``cage_threads=1``: ipctk runs on one thread while the cages are built (its parallel sums differ run
    to run), the caller's thread count is back afterwards, and two runs give the same bytes."""
    import ipctk

    seen = []
    real = nested_backend_module.nest_pair

    def recorded(*a, **k):
        seen.append(ipctk.get_num_threads())
        return real(*a, **k)

    monkeypatch.setattr(nested_backend_module, "nest_pair", recorded)
    V, F = neck
    before = ipctk.get_num_threads()
    runs = [build_cages(V, F, 3, "nested", cage_threads=1) for _ in range(2)]
    assert seen and set(seen) == {1} and ipctk.get_num_threads() == before
    assert len(runs[0]) == 3
    for (Va, Fa), (Vb, Fb) in zip(runs[0], runs[1]):
        assert np.array_equal(Va, Vb) and np.array_equal(Fa, Fb)
    seen.clear()
    build_cages(V, F, 2, "nested")
    assert set(seen) == {before}  # the default leaves ipctk's own


def test_nested_refuses_before_any_work_when_its_estimate_exceeds_the_budget(neck):
    """``cage_time_budget``: an estimate above it raises at once, naming the option (reason "time budget"),
    the caller's arrays untouched; the default budget admits a 100k-face scan's cages and refuses a
    192k-face input's (estimate_seconds' calibration: lucy 81 s, homer subdivided 979 s measured)."""
    import time

    from cagegen import CageError
    from cagegen.nested.backend import DEFAULT_TIME_BUDGET, estimate_seconds

    V, F = neck
    V0, F0 = V.copy(), F.copy()
    t = time.perf_counter()
    with pytest.raises(CageError, match=r"cage_time_budget=1 s; pass a larger cage_time_budget") as e:
        build_cages(V, F, 3, "nested", cage_time_budget=1.0)
    assert e.value.reason == "time budget" and e.value.layer == 1
    assert time.perf_counter() - t < 5.0  # the audit only
    assert np.array_equal(V, V0) and np.array_equal(F, F0)
    assert estimate_seconds(99_970, [24_992, 6_248]) < 0.5 * DEFAULT_TIME_BUDGET
    assert estimate_seconds(192_000, [48_000, 12_000]) > DEFAULT_TIME_BUDGET
    assert estimate_seconds(len(F), [len(F) // 4]) < 10.0


@pytest.mark.parametrize("method", ["nested", "sdf"])
def test_budget_refuses_before_the_input_audit(method, monkeypatch):
    """build_cages asks the backend's registry ``budget`` check on the face count as given, before the
    audit (whose exact self-intersection test took 26 s on a 342k-face input before the refusal): the
    audit is never called for a run the budget refuses; an input it admits is audited, and a malformed
    one still gets the audit's own error."""
    from cagegen import build
    from cagegen import CageError, MeshInputError
    from cagegen.registry import get_budget

    V, F = shapes.sphere(8)
    big = np.tile(F, (600, 1))  # 321,600 faces: no need for a valid surface, the audit must not run

    def no_audit(*a, **k):
        raise AssertionError("audited before the budget check")

    monkeypatch.setattr(build, "check_mesh", no_audit)
    with pytest.raises(CageError, match=r"exceeds cage_time_budget=900 s") as e:
        build_cages(V, big, 3, method)
    assert e.value.reason == "time budget"
    # the estimate is the backend's own, on the given face count and the default counts
    est = get_budget(method)(len(big), [len(big) // 4, len(big) // 16], cage_time_budget=None)
    assert est > 900.0
    with pytest.raises(AssertionError, match="audited before"):  # admitted: the audit runs next
        build_cages(V, F, 3, method)
    monkeypatch.undo()
    with pytest.raises(MeshInputError):
        build_cages(V, big[:, :2], 3, method)
