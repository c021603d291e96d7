"""Tests of the numpy Gauss-Newton barrier Hessian (cagegen.nested.contact_hessian) against ipctk.

The contact arrays and the barrier derivatives are checked through the gradient they imply, which must
equal ipctk's barrier gradient (where no edge-edge mollifier is active); the Hessian through a single
point-triangle contact, where along the normal it equals the exact second derivative, and through PSD-ness
and the reduced (``dofs``) form on a real cage/fine configuration.
"""

from __future__ import annotations

import importlib

import ipctk
import numpy as np
import pytest

from cagegen import verify_nesting
from cagegen.collision import PairMesh
from cagegen.decimate import decimate_surface
from cagegen.nested import flow_inside, reinflate
from cagegen.nested.contact_hessian import (
    ContactArrays,
    barrier_derivatives,
    collision_lists,
    contact_arrays,
    contact_gradients,
    gauss_newton_hessian,
    subset,
)
from nestmg import shapes

rf = importlib.import_module("cagegen.nested.reinflate")


@pytest.fixture(scope="module")
def contact_state():
    """A cage and the flowed fine surface inside it (the first re-inflation state), with its contacts."""
    V, F = shapes.neck_blobs(res=28)
    lo, hi = V.min(0), V.max(0)
    V = (V - 0.5 * (lo + hi)) / np.linalg.norm(hi - lo)
    U, G, _ = decimate_surface(V, F, len(F) // 4)
    fl = flow_inside(V, F, U, G)
    assert fl.success
    pair = PairMesh(U, G, fl.history[-1], F)
    X = pair.stack(U, fl.history[-1])
    dhat = 0.02
    col = pair.collisions(X, dhat)
    return V, F, U, G, fl, pair, X, dhat, col


def test_contact_arrays_reproduce_the_ipctk_barrier_gradient(contact_state):
    *_, pair, X, dhat, col = contact_state
    kappa = 1e3
    ca = contact_arrays(col, pair.mesh)
    counts = np.bincount(ca.kind, minlength=4)
    assert len(ca) == len(col) and np.all(counts[:3] > 0), counts  # face-vertex, edge-edge, edge-vertex
    rest = np.asarray(pair.mesh.rest_positions)
    d, g, w = contact_gradients(X, ca, rest)
    # distances: ipctk's squared distances of the same stencils
    E, Fm = pair.mesh.edges, pair.mesh.faces
    d_ref = np.sqrt([c.compute_distance(X, E, Fm) for c in col.fv_collisions])
    np.testing.assert_allclose(d[ca.kind == ContactArrays.FV], d_ref, rtol=1e-10)
    h1, _ = barrier_derivatives(d, dhat, kappa)
    G = np.zeros_like(X)
    np.add.at(G, np.maximum(ca.ids, 0), (w * h1)[:, None, None] * g * (ca.ids >= 0)[:, :, None])
    ref = ipctk.BarrierPotential(dhat, kappa).gradient(col, pair.mesh, X).reshape(-1, 3)
    # the mollifier's own gradient (nearly parallel edge-edge pairs) is not in the Gauss-Newton model
    ee = ca.ids[(ca.kind == ContactArrays.EE) & (w < ca.weight)]
    free = np.ones(len(X), dtype=bool)
    free[ee.ravel()] = False
    assert np.linalg.norm(ref[free]) > 0.5 * np.linalg.norm(ref)
    np.testing.assert_allclose(G[free], ref[free], atol=1e-9 * np.abs(ref).max())


def test_barrier_derivatives_match_finite_differences():
    dhat, kappa = 0.1, 7.0
    d = np.array([1e-3, 0.01, 0.05, 0.09])
    h = lambda x: kappa * -(x * x - dhat**2) ** 2 * np.log(x * x / dhat**2)  # noqa: E731
    eps = 1e-5 * d
    h1, h2 = barrier_derivatives(d, dhat, kappa)
    np.testing.assert_allclose(h1, (h(d + eps) - h(d - eps)) / (2 * eps), rtol=1e-7)
    up, lo = barrier_derivatives(d + eps, dhat, kappa)[0], barrier_derivatives(d - eps, dhat, kappa)[0]
    np.testing.assert_allclose(h2, (up - lo) / (2 * eps), rtol=1e-7)
    z1, z2 = barrier_derivatives(np.array([dhat, 2 * dhat]), dhat, kappa)
    assert np.all(z1 == 0) and np.all(z2 == 0)


def test_single_point_triangle_contact_has_the_exact_normal_curvature():
    # a point 0.01 above the triangle's interior: d is linear in the point's normal motion, so the
    # exact Hessian and the Gauss-Newton one agree along it (h''(d)), and GN has rank one
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.3, 0.01]])
    Fm = np.array([[0, 1, 2]], dtype=np.int32)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(Fm), Fm)
    dhat, kappa = 0.05, 3.0
    col = ipctk.NormalCollisions()
    col.build(mesh, V, dhat)
    ca = contact_arrays(col, mesh)
    assert list(ca.kind) == [ContactArrays.FV] and list(ca.ids[0]) == [3, 0, 1, 2]
    H = gauss_newton_hessian(V, ca, V, dhat, kappa).toarray()
    barrier = ipctk.BarrierPotential(dhat, kappa)
    H_exact = barrier.hessian(col, mesh, V, ipctk.PSDProjectionMethod.NONE).toarray()
    v = np.zeros(12)
    v[11] = 1.0  # the point's z
    _, h2 = barrier_derivatives(np.array([0.01]), dhat, kappa)
    assert v @ H @ v == pytest.approx(h2[0], rel=1e-12)
    assert v @ H_exact @ v == pytest.approx(h2[0], rel=1e-8)
    ev = np.linalg.eigvalsh(H)
    assert np.sum(ev > 1e-9 * ev.max()) == 1 and ev.min() > -1e-9 * ev.max()


def test_gauss_newton_hessian_is_psd_and_its_dofs_form_is_the_submatrix(contact_state):
    *_, pair, X, dhat, col = contact_state
    ca = contact_arrays(col, pair.mesh)
    rest = np.asarray(pair.mesh.rest_positions)
    H = gauss_newton_hessian(X, ca, rest, dhat, 1e3)
    assert abs(H - H.T).max() <= 1e-12 * abs(H).max()
    rng = np.random.default_rng(3)
    V = rng.standard_normal((X.size, 20))
    assert np.all(np.einsum("ij,ij->j", V, H @ V) >= -1e-10 * abs(H).max())
    dofs = np.sort(rng.choice(X.size, X.size // 3, replace=False))
    Hs = gauss_newton_hessian(X, ca, rest, dhat, 1e3, dofs=dofs)
    assert abs(Hs - H[dofs][:, dofs]).max() <= 1e-12 * abs(H).max()


def test_gauss_newton_hessian_is_the_sum_of_the_contacts_outer_products(contact_state):
    """The sparse assembly against a dense sum over the contacts of ``w m max(h'', 0) grad d grad d^T``."""
    *_, pair, X, dhat, col = contact_state
    kappa = 1e3
    ca = contact_arrays(col, pair.mesh)
    rest = np.asarray(pair.mesh.rest_positions)
    d, g, w = contact_gradients(X, ca, rest)
    _, h2 = barrier_derivatives(d, dhat, kappa)
    used = np.unique(ca.ids[ca.ids >= 0])
    dofs = (3 * used[:, None] + np.arange(3)).ravel()  # every DOF of some contact, in vertex order
    where = np.full(X.size, -1)
    where[dofs] = np.arange(len(dofs))
    dense = np.zeros((len(dofs), len(dofs)))
    for k in range(len(ca)):
        ok = ca.ids[k] >= 0
        rows = where[(3 * ca.ids[k][ok][:, None] + np.arange(3)).ravel()]
        gk = g[k][ok].ravel()
        dense[np.ix_(rows, rows)] += w[k] * max(h2[k], 0.0) * np.outer(gk, gk)
    H = gauss_newton_hessian(X, ca, rest, dhat, kappa, dofs=dofs).toarray()
    assert np.abs(dense).max() > 0
    np.testing.assert_allclose(H, dense, rtol=0, atol=1e-12 * np.abs(dense).max())


@pytest.mark.parametrize("reverse", ["gauss_newton", "ipctk"])
@pytest.mark.parametrize("final", ["gauss_newton", "ipctk"])
def test_both_barrier_hessians_reinflate_to_a_certified_cage(contact_state, monkeypatch, reverse, final):
    V, F, U, G, fl, *_ = contact_state
    monkeypatch.setattr(rf, "REVERSE_HESSIAN", reverse)
    monkeypatch.setattr(rf, "BARRIER_HESSIAN", final)
    rr = reinflate(fl.history, F, U, G, energy="volume")
    assert rr.success, rr.reason
    assert np.array_equal(rr.fine, V)
    assert verify_nesting([(V, F), (rr.cage, G)]).ok
    assert rr.stats["volume_after_final"] < rr.stats["volume_before_final"]


@pytest.mark.parametrize("knob, value", [("GN_BLOCKED_ALPHA", 1.01), ("GN_PATIENCE", 0)])
def test_a_blocked_or_slow_gauss_newton_step_switches_the_reinflation_to_ipctk(contact_state, monkeypatch,
                                                                                knob, value):
    monkeypatch.setattr(rf, knob, value)  # every step counts as blocked / too slow: switch at the first
    monkeypatch.setattr(rf, "REVERSE_HESSIAN", "gauss_newton")
    monkeypatch.setattr(rf, "BARRIER_HESSIAN", "gauss_newton")
    re, fin, rr = _hessian_kinds(contact_state, monkeypatch)
    assert rr.stats["hessian_switched_at"] == [1, 1]
    assert re[0] == "gauss_newton" and set(re[1:]) == {"ipctk"} and len(re) > 1
    assert set(fin) == {"gauss_newton"}  # the final phase starts over with the Gauss-Newton matrix


def _hessian_kinds(contact_state, monkeypatch) -> tuple[list, list, object]:
    """The Newton matrices a certified re-inflation used: (reverse steps, final phase), one entry per Newton
    step, and its result."""
    V, F, U, G, fl, *_ = contact_state
    kinds = []
    newton_step = rf._Problem.newton_step

    def spy(self, X, target):
        kinds.append((self.hessian_kind, target is None))
        return newton_step(self, X, target)

    monkeypatch.setattr(rf._Problem, "newton_step", spy)
    rr = reinflate(fl.history, F, U, G, energy="volume")
    assert rr.success, rr.reason
    assert verify_nesting([(V, F), (rr.cage, G)]).ok
    return [k for k, final in kinds if not final], [k for k, final in kinds if final], rr


def test_gauss_newton_reverse_steps_and_the_final_phase_ipctk(contact_state, monkeypatch):
    # the defaults are ipctk's Hessian in both phases (REVERSE_HESSIAN's comment says why); with Gauss-Newton
    # reverse steps the final energy's minimiser (the cage) is still reached with ipctk's projected Hessian
    assert (rf.REVERSE_HESSIAN, rf.BARRIER_HESSIAN) == ("ipctk", "ipctk")
    monkeypatch.setattr(rf, "REVERSE_HESSIAN", "gauss_newton")
    monkeypatch.setattr(rf, "GN_BLOCKED_ALPHA", -1.0)  # no switch: every reverse step stays Gauss-Newton
    monkeypatch.setattr(rf, "GN_PATIENCE", 10**6)
    re, fin, _ = _hessian_kinds(contact_state, monkeypatch)
    assert re and set(re) == {"gauss_newton"}
    assert fin and set(fin) == {"ipctk"}


def test_reverse_hessian_ipctk_keeps_ipctk_throughout(contact_state, monkeypatch):
    monkeypatch.setattr(rf, "REVERSE_HESSIAN", "ipctk")
    re, fin, _ = _hessian_kinds(contact_state, monkeypatch)
    assert set(re) == {"ipctk"} and set(fin) == {"ipctk"}


def _between(d: np.ndarray) -> float:
    """A distance half-way between two consecutive contact distances near the median (no contact sits on
    the split, where ``d < split`` and ipctk's own build could round differently)."""
    u = np.unique(d)
    k = len(u) // 2
    return 0.5 * float(u[k] + u[k + 1])


def test_hybrid_hessian_is_ipctk_near_and_gauss_newton_far(contact_state, monkeypatch):
    """``HYBRID_NEAR`` above every contact: ipctk's projected Hessian; at 0: the Gauss-Newton matrix; in
    between: the sum of the two over the split, on the same DOFs."""
    *_, pair, X, dhat, col = contact_state
    prob = rf._Problem(pair, None, dhat, 1e3, 1e3)
    rest = np.asarray(pair.mesh.rest_positions)
    ca = contact_arrays(col, pair.mesh)
    d = contact_gradients(X, ca, rest)[0]
    full = prob.barrier.hessian(col, pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP).tocsr()
    monkeypatch.setattr(rf, "HYBRID_NEAR", 1.01)
    H, idx = prob._hybrid_hessian(col, X, True)
    assert len(idx) > 3 * pair.nc and abs(H - full[idx][:, idx]).max() <= 1e-12 * abs(full).max()
    monkeypatch.setattr(rf, "HYBRID_NEAR", 0.0)
    H0, idx0 = prob._hybrid_hessian(col, X, True)
    assert np.array_equal(idx0, idx)
    gn = gauss_newton_hessian(X, ca, rest, dhat, 1e3, dofs=idx)
    assert abs(H0 - gn).max() <= 1e-12 * abs(gn).max()
    split = _between(d) / dhat
    monkeypatch.setattr(rf, "HYBRID_NEAR", split)
    Hs, _ = prob._hybrid_hessian(col, X, True)
    near = pair.collisions(X, split * dhat)
    assert 0 < len(near) < len(col)
    ref = (gauss_newton_hessian(X, ca, rest, dhat, 1e3, dofs=idx, mask=d >= split * dhat)
           + prob.barrier.hessian(near, pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP).tocsr()[idx][:, idx])
    assert abs(Hs - ref).max() <= 1e-12 * abs(full).max()
    assert abs(Hs - full[idx][:, idx]).max() > 1e-6 * abs(full).max()  # the far part is not ipctk's


def test_large_contact_sets_take_the_hybrid_matrix_and_still_certify(contact_state, monkeypatch):
    V, F, U, G, fl, *_ = contact_state
    calls = []
    hybrid = rf._Problem._hybrid_hessian

    def spy(self, col, X, fine_moves):
        calls.append(len(col))
        return hybrid(self, col, X, fine_moves)

    monkeypatch.setattr(rf._Problem, "_hybrid_hessian", spy)
    monkeypatch.setattr(rf, "HYBRID_MIN_CONTACTS", 1)  # every set counts as large
    rr = reinflate(fl.history, F, U, G, energy="volume")
    assert rr.success, rr.reason
    assert calls
    assert verify_nesting([(V, F), (rr.cage, G)]).ok
    assert rr.stats["volume_after_final"] < rr.stats["volume_before_final"]
    calls.clear()
    monkeypatch.setattr(rf, "HYBRID_MIN_CONTACTS", 10**9)
    assert reinflate(fl.history, F, U, G, energy="volume").success and not calls


def test_subset_of_the_collision_objects_is_the_collision_set_built_closer(contact_state):
    """The hybrid's near set, picked from the objects already read, is the set ipctk builds at the smaller
    distance: the same contacts, the same projected Hessian."""
    *_, pair, X, dhat, col = contact_state
    lists = collision_lists(col)
    ca = contact_arrays(col, pair.mesh, lists)
    d = contact_gradients(X, ca, np.asarray(pair.mesh.rest_positions))[0]
    split = _between(d)
    near = subset(lists, d < split)
    fresh = pair.collisions(X, split)
    assert 0 < len(near) == len(fresh) < len(col)
    barrier = ipctk.BarrierPotential(dhat, 1e3)
    H = barrier.hessian(near, pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP)
    ref = barrier.hessian(fresh, pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP)
    assert abs(H - ref).max() <= 1e-12 * abs(ref).max()
    assert len(subset(lists, np.zeros(len(col), dtype=bool))) == 0
