"""Curved P2 tets: nodes, certified Jacobians, the fitting energy, P2 FEM and its convergence on curved domains."""

from __future__ import annotations

import numpy as np
import pytest

from nestmg import NestmgInputError, setup_problem, shapes
from nestmg.curved import (
    certify_tets,
    curve_mesh,
    jacobian_bernstein,
    linear_scaled_jacobians,
    p2_nodes,
    scaled_jacobians,
    sphere_projector,
    surface_projector,
    torus_projector,
)
from nestmg.refine import refine_tets
from solvers.fem_p2 import p2_basis, p2_l2_error, p2_load, p2_stiffness_matrix


@pytest.fixture(scope="module")
def ball():
    return shapes.ball_tets(4)  # 82k, 10k, 1.3k, 160, 20 tets


@pytest.fixture(scope="module")
def torus():
    return shapes.torus_tets(3, segments=12)  # 111k, 14k, 1.7k, 216 tets


def test_p2_nodes_are_the_red_refinement_nodes(ball):
    V, T = ball[0][2]
    X, T10, E = p2_nodes(V, T)
    V2, _, _ = refine_tets(V, T)
    np.testing.assert_array_equal(X, V2)
    np.testing.assert_allclose(X[T10[:, 4]], 0.5 * (V[T[:, 0]] + V[T[:, 1]]))  # m01
    np.testing.assert_allclose(X[T10[:, 5]], 0.5 * (V[T[:, 1]] + V[T[:, 2]]))  # m12 (tetra10 order)


def test_bernstein_coefficients_reproduce_det_j():
    rng = np.random.default_rng(3)
    X, T10, _ = p2_nodes(np.eye(4, 3, k=-1), np.array([[0, 1, 2, 3]]))
    X[4:] += 0.15 * rng.standard_normal((6, 3))
    coef, _ = jacobian_bernstein(X, T10)
    lam = rng.dirichlet(np.ones(4), 50)
    from math import factorial

    from nestmg.curved import _lattice

    A = _lattice(3)
    mult = np.array([factorial(3) / np.prod([factorial(a) for a in al]) for al in A])
    bern = mult * np.prod(lam[:, None, :] ** A[None], axis=2)  # (50, 20)
    _, dN = p2_basis(lam[:, 1:])
    direct = np.linalg.det(np.einsum("ad,qak->qdk", X[T10[0]], dN))
    np.testing.assert_allclose(bern @ coef[0], direct, rtol=1e-12, atol=1e-12)
    assert coef.min() <= direct.min() + 1e-14 and coef.max() >= direct.max() - 1e-14


def test_certification_subdivides_undecided_tets():
    # a valid curved tet whose degree-3 Bernstein coefficients are not all positive: proved by splitting
    rng = np.random.default_rng(1)
    X0, T10, _ = p2_nodes(np.eye(4, 3, k=-1), np.array([[0, 1, 2, 3]]))
    rng.standard_normal((6, 3))  # the second draw of this seed is the case
    X = X0.copy()
    X[4:] += 0.25 * rng.standard_normal((6, 3))
    assert jacobian_bernstein(X, T10)[0].min() < 0 < scaled_jacobians(X, T10, order=12)[0]
    assert certify_tets(X, T10, depth=0).tolist() == [0]
    assert certify_tets(X, T10, depth=2).tolist() == [1]


def _dent_projector(center, target, normal, radius):
    """The unit sphere, except near ``center`` where the surface is the plane through ``target``."""
    sphere = sphere_projector()

    def project(P):
        C, N = sphere(P)
        near = np.linalg.norm(P - center, axis=1) < radius
        d = (P[near] - target) @ normal
        C[near] = P[near] - d[:, None] * normal
        N[near] = normal
        return C, N

    return project


def test_negative_control_mid_node_through_opposite_face_is_invalid_then_repaired(ball):
    V, T = ball[0][3]  # 160 tets, boundary vertices on the sphere
    cm0 = curve_mesh(V, T, sphere_projector())
    F6 = cm0.boundary_facets()
    node = F6[0, 3]  # a boundary edge node
    t = np.flatnonzero((cm0.T10 == node).any(axis=1))[0]
    a, b = cm0.E[node - cm0.n_vertices]
    opp = [v for v in cm0.T[t] if v not in (a, b)]
    far = V[opp].mean(axis=0)  # beyond the face opposite the edge: pushed through the tet
    mid = 0.5 * (V[a] + V[b])
    target = mid + 1.6 * (far - mid)
    normal = (mid - far) / np.linalg.norm(mid - far)
    proj = _dent_projector(mid, target, normal, 0.4 * np.linalg.norm(V[a] - V[b]))
    bad = curve_mesh(V, T, proj, fit=False)
    assert bad.report["invalid_after_projection"] >= 1
    assert bad.report["straightened"] >= 1 and bad.report["certified"]  # fallback: straight, counted
    fitted = curve_mesh(V, T, proj, fit=True)  # the repair alone (no quality pass: it would undo the dent)
    assert fitted.report["invalid_after_projection"] >= 1
    assert fitted.report["fit"]["iterations"] > 0
    assert fitted.report["straightened"] == 0 and fitted.report["certified"]
    assert (certify_tets(fitted.X, fitted.T10) == 1).all()
    # the energy moved the node towards the dent (as far as validity allows), not back to straight
    moved = (fitted.X[node] - mid) @ (-normal)
    assert moved > 0.1 * np.linalg.norm(far - mid)


def test_quality_pass_raises_the_scaled_jacobian_at_a_fit_cost_set_by_lambda(ball):
    V, T = ball[0][3]  # 160 tets of the unit ball: coarse, so curving costs quality
    before = curve_mesh(V, T, sphere_projector(), quality=None)
    cm = curve_mesh(V, T, sphere_projector(), quality=0.95, quality_lam=0.05)
    sj0, sj = scaled_jacobians(before.X, before.T10), scaled_jacobians(cm.X, cm.T10)
    assert sj0.min() < 0.7 and sj.min() > sj0.min() + 0.1 and sj.mean() > sj0.mean() + 0.03
    assert cm.report["scaled_jacobian"]["min"] == pytest.approx(sj[sj < 1].min())
    assert cm.report["scaled_jacobian"]["before_quality"]["min"] == pytest.approx(sj0.min())
    assert cm.report["certified"] and (certify_tets(cm.X, cm.T10) == 1).all()
    # the certified lower bound is a lower bound, and the pass kept its record
    assert 0 < cm.report["scaled_jacobian"]["bound_min"] <= cm.report["scaled_jacobian"]["min"]
    assert cm.report["quality"]["passes"][0]["kept"]
    # λ trades fit for quality: at 0.05 the facets still take > 85 % of the way to the sphere
    d = cm.report["surface_distance"]
    assert before.report["surface_distance"]["curved_max"] < d["curved_max"] < 0.15 * d["straight_max"]
    loose = curve_mesh(V, T, sphere_projector(), quality=0.95, quality_lam=1.0)
    assert loose.report["scaled_jacobian"]["min"] > max(0.9, sj.min())
    assert loose.report["surface_distance"]["curved_max"] > 2 * d["curved_max"]
    # straight tets' own (linear) scaled Jacobian: 1 for the regular tet, reported for the curved mesh
    lin = linear_scaled_jacobians(cm.V, cm.T)
    assert cm.report["linear_scaled_jacobian"]["min"] == pytest.approx(lin.min()) and 0 < lin.max() <= 1.5


@pytest.mark.parametrize("shape", ["ball", "torus"])
def test_sj_floor_lifts_every_tet_to_the_floor_by_partial_curving(ball, torus, shape):
    (tets, _), proj = (ball, sphere_projector()) if shape == "ball" else (torus, torus_projector())
    V, T = tets[2]  # 1280 / 1728 tets: their curved tets go down to 0.80 / 0.63
    free = curve_mesh(V, T, proj)
    assert free.report["scaled_jacobian"]["min"] < 0.9 and "sj_floor" not in free.report
    cm = curve_mesh(V, T, proj, sj_floor=0.955)
    sj, lb = scaled_jacobians(cm.X, cm.T10, order=12), scaled_jacobians(cm.X, cm.T10, bound=True)
    assert lb.min() >= 0.955 and sj.min() >= lb.min() - 1e-12  # certified: the Bernstein bound meets it
    assert cm.report["scaled_jacobian"]["bound_min"] >= 0.955 and cm.report["certified"]
    assert (certify_tets(cm.X, cm.T10) == 1).all()
    fl = cm.report["sj_floor"]
    assert fl["tets_below_before"] == int((scaled_jacobians(free.X, free.T10, bound=True) < 0.955).sum()) > 0
    assert 0 < fl["backed_off"] <= fl["curved_edge_nodes"] and fl["rounds"] >= 1
    # only backed off, never pushed further: every node between its straight and its curved position
    Xs = free.straight().X
    D, Dc = cm.X - Xs, free.X - Xs
    t = np.einsum("ij,ij->i", D, Dc) / np.maximum(np.einsum("ij,ij->i", Dc, Dc), 1e-300)
    np.testing.assert_allclose(D, t[:, None] * Dc, atol=1e-14)
    assert t.min() >= 0 and t.max() <= 1 and (t[np.any(Dc != 0, axis=1)] < 1).sum() == fl["backed_off"]
    # the cost: the facets lie between straight and curved (some edges of the torus are straightened)
    d, d0 = cm.report["surface_distance"], free.report["surface_distance"]
    assert d0["curved_max"] < d["curved_max"] <= d["straight_max"]
    assert d0["curved_mean"] < d["curved_mean"] < d["straight_mean"]
    # a floor the mesh already meets changes nothing
    low = curve_mesh(V, T, proj, sj_floor=0.5)
    np.testing.assert_array_equal(low.X, free.X)
    assert low.report["sj_floor"]["backed_off"] == 0
    with pytest.raises(NestmgInputError, match="sj_floor"):
        curve_mesh(V, T, proj, sj_floor=1.0)


def test_spread_energy_gradient_matches_finite_differences():
    from nestmg.curved_fit import jacobian_spread_energy, reference_inverse

    rng = np.random.default_rng(5)
    V, T = np.eye(4, 3, k=-1), np.array([[0, 1, 2, 3]])
    X, T10, _ = p2_nodes(V, T)
    X[4:] += 0.05 * rng.standard_normal((6, 3))
    Ai = reference_inverse(V, T)
    E, G = jacobian_spread_energy(X, T10, Ai, beta=0.5)
    num = np.zeros_like(X)
    for i, k in np.ndindex(10, 3):
        dX = np.zeros_like(X)
        dX[i, k] = 1e-6
        num[i, k] = (jacobian_spread_energy(X + dX, T10, Ai, beta=0.5)[0]
                     - jacobian_spread_energy(X - dX, T10, Ai, beta=0.5)[0]) / 2e-6
    np.testing.assert_allclose(G, num, atol=1e-7 * abs(G).max())
    assert E > 0 and jacobian_spread_energy(p2_nodes(V, T)[0], T10, Ai)[0] == pytest.approx(0, abs=1e-20)


@pytest.mark.parametrize("shape", ["ball", "torus"])
def test_relax_lifts_the_scaled_jacobian_without_moving_the_boundary(ball, torus, shape):
    (tets, _), proj = (ball, sphere_projector()) if shape == "ball" else (torus, torus_projector())
    V, T = tets[2]  # 1280 / 1728 tets: curved tets down to 0.80 / 0.63
    free = curve_mesh(V, T, proj)
    cm = curve_mesh(V, T, proj, relax=0.97)
    sj0, sj = scaled_jacobians(free.X, free.T10), scaled_jacobians(cm.X, cm.T10)
    bnd = np.unique(cm.boundary_facets())
    np.testing.assert_array_equal(cm.X[bnd], free.X[bnd])  # the fit is untouched
    assert cm.report["surface_distance"] == free.report["surface_distance"]
    assert cm.report["certified"] and (certify_tets(cm.X, cm.T10) == 1).all()
    assert cm.report["scaled_jacobian"]["bound_min"] > 0
    # measured 0.795 -> 0.946 / 0.626 -> 0.890; tets below 0.955: 560 -> 38 / 960 -> 624
    assert sj.min() > sj0.min() + 0.14 and (sj < 0.955).sum() < 0.7 * (sj0 < 0.955).sum()
    assert sj[sj < 1].mean() > sj0[sj0 < 1].mean() + 0.03
    assert cm.report["relax"]["passes"][0]["kept"] and cm.report["relax"]["iterations"] > 0
    with pytest.raises(NestmgInputError, match="relax"):
        curve_mesh(V, T, proj, relax=1.5)


@pytest.mark.slow
def test_relax_beats_the_papers_minimum_on_the_ball_with_the_full_fit(ball):
    V, T = ball[0][1]  # 10240 tets: projected, the curved tets go down to 0.889
    cm = curve_mesh(V, T, sphere_projector(), relax=0.97, sj_floor=0.96)
    assert cm.report["scaled_jacobian"]["bound_min"] > 0.96 and cm.report["certified"]  # measured 0.967
    assert cm.report["sj_floor"]["backed_off"] == 0  # the floor had nothing to do
    assert cm.report["surface_distance"]["curved_max"] < 1e-5  # third-order fit kept (6.9e-6)
    floor = curve_mesh(V, T, sphere_projector(), sj_floor=0.96).report  # the floor alone un-curves
    assert floor["sj_floor"]["boundary_backed_off"] == floor["sj_floor"]["boundary_edge_nodes"]
    assert floor["surface_distance"]["curved_max"] > 100 * cm.report["surface_distance"]["curved_max"]


def test_smooth_normals_follow_the_surface_and_keep_sharp_creases():
    Vs, Fs = shapes.sphere(16)
    Vs = Vs / np.linalg.norm(Vs, axis=1, keepdims=True)
    rng = np.random.default_rng(0)
    P = rng.standard_normal((400, 3))
    P *= (1.0 + 0.01 * rng.standard_normal((400, 1))) / np.linalg.norm(P, axis=1, keepdims=True)
    errs = {}
    for kind in ("face", "smooth"):
        C, n = surface_projector(Vs, Fs, normals=kind)(P)
        true = C / np.linalg.norm(C, axis=1, keepdims=True)
        errs[kind] = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, true), -1, 1))).max()
    assert errs["smooth"] < 0.25 * errs["face"]
    # a cube: every edge is a 90° crease, the normal is the face's own up to the edges
    Vc = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    Fc = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                   [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    Q = np.array([[0.5, 0.5, 1.2], [1.3, 0.2, 0.7], [0.01, 0.5, 0.5]])
    _, n = surface_projector(Vc, Fc, normals="smooth")(Q)
    np.testing.assert_allclose(np.abs(n), [[0, 0, 1], [1, 0, 0], [1, 0, 0]], atol=1e-12)
    with pytest.raises(NestmgInputError, match="normals"):
        surface_projector(Vc, Fc, normals="vertex")


def test_p2_stiffness_matches_scikit_fem_on_curved_tets(ball):
    skfem = pytest.importorskip("skfem")
    from skfem.models.poisson import laplace, mass

    from solvers.fem_p2 import p2_mass_matrix

    V, T = ball[0][2]
    cm = curve_mesh(V, T, sphere_projector())
    m = skfem.MeshTet(np.ascontiguousarray(cm.V.T), np.ascontiguousarray(cm.T.T))
    n = cm.n_vertices
    key = {tuple(e): i for i, e in enumerate(np.sort(m.edges.T, axis=1))}
    perm = np.r_[np.arange(n), n + np.array([key[tuple(e)] for e in cm.E])]
    doflocs = np.zeros((3, len(cm.X)))
    doflocs[:, perm] = cm.X.T
    basis = skfem.Basis(skfem.MeshTet2(doflocs, np.ascontiguousarray(cm.T.T)), skfem.ElementTetP2(), intorder=7)
    K = skfem.asm(laplace, basis)[perm][:, perm]
    M = skfem.asm(mass, basis)[perm][:, perm]
    assert abs(K - p2_stiffness_matrix(cm.X, cm.T10)).max() < 1e-5 * abs(K).max()
    assert abs(M - p2_mass_matrix(cm.X, cm.T10)).max() < 1e-7 * abs(M).max()


# ----------------------------------------------------------------------------- convergence

def _grad_un(x):
    return np.c_[np.exp(x[:, 0]) * np.cos(x[:, 1]), -np.exp(x[:, 0]) * np.sin(x[:, 1]), np.zeros(len(x))]


def _un(x):  # harmonic
    return np.exp(x[:, 0]) * np.cos(x[:, 1])


def _solve_p2(tets, P, name, proj, curved, f, u):
    """L2 error, unknowns and MG-PCG iterations of a P2 problem with data given on the true surface."""
    if name == "poisson-dirichlet":
        kw = {"boundary_values": lambda x: u(proj(x)[0])}
    else:
        kw = {"flux": lambda x, n: np.einsum("ij,ij->i", _grad_un(proj(x)[0]), proj(x)[1])}
    cm = curve_mesh(*tets[0], proj) if curved else None
    pr = setup_problem(tets, P, name, element="P2", curved=cm, f=f, **kw)
    x, info = pr.multigrid().solve(pr.b, tol=1e-10, accel="cg", return_info=True)
    err = p2_l2_error(pr.mesh.X, pr.mesh.T10, pr.expand(x), u, remove_mean=name == "poisson-neumann")
    return err, pr.n_fine, info["iterations"]


def _p1_error(tets, P, proj, f, u, dirichlet):
    """L2 error of P1 on a mesh whose boundary vertices lie on the surface (loads by P2 quadrature: exact)."""
    from nestmg.tetmesh import orient_tets
    from solvers import stiffness_matrix
    from solvers.fem_p2 import p2_boundary_facets, p2_neumann_load

    from nestmg.curved import p2_prolongation
    from solvers import MultigridSolver, restrict_prolongations

    V, T = tets[0]
    T = orient_tets(V, T)
    X, T10, E = p2_nodes(V, T)
    Pp = p2_prolongation(len(V), E)
    K = stiffness_matrix(V, T)
    b = Pp.T @ p2_load(X, T10, f)
    n = len(V)
    F6 = p2_boundary_facets(T10)[0]
    bnd = np.unique(F6[:, :3])
    uh = np.zeros(n)
    if dirichlet:
        free = np.setdiff1d(np.arange(n), bnd)
        uh[bnd] = u(V[bnd])
        A, rhs = K[free][:, free], b[free] - K[free][:, bnd] @ uh[bnd]
    else:
        b = b + Pp.T @ p2_neumann_load(X, F6, lambda x, nn: np.einsum("ij,ij->i", _grad_un(proj(x)[0]), proj(x)[1]))
        free = np.arange(1, n)
        A, rhs = K[1:, 1:], (b - b.mean())[1:]
    ml = MultigridSolver(A.tocsr(), restrict_prolongations(P, free)[0])  # the refinement hierarchy
    uh[free] = ml.solve(rhs, tol=1e-11, accel="cg")
    return p2_l2_error(X, T10, Pp @ uh, u, remove_mean=not dirichlet)


def _ball_dirichlet(x):
    return (1 - (x**2).sum(1)) * np.exp(x[:, 0])


def _ball_source(x):
    return np.exp(x[:, 0]) * (6 + 4 * x[:, 0] - (1 - (x**2).sum(1)))


def _zero(x):
    return np.zeros(len(x))


def _convergence(tets, P, name, proj, f, u, coarse_end):
    """Errors of curved and straight P2 on tets[2] and tets[1] (hierarchy down to ``coarse_end``), P1 on tets[0]."""
    e_c, e_s, its = [], [], []
    for j in (2, 1):
        ec, n, it = _solve_p2(tets[j:coarse_end], P[j:coarse_end - 1], name, proj, True, f, u)
        es, _, _ = _solve_p2(tets[j:coarse_end], P[j:coarse_end - 1], name, proj, False, f, u)
        e_c.append(ec), e_s.append(es), its.append(it)
    # equal unknowns: curved P2 on tets[1] vs P1 on its red refinement tets[0] (the same node count)
    e_p1 = _p1_error(tets[:coarse_end], P[:coarse_end - 1], proj, f, u, name == "poisson-dirichlet")
    return e_c, e_s, its, e_p1


def _check_rates(e_c, e_s, its, e_p1):
    rate_c, rate_s = np.log2(e_c[0] / e_c[1]), np.log2(e_s[0] / e_s[1])
    assert rate_c >= 2.7, (e_c, rate_c)
    assert rate_s <= 2.2, (e_s, rate_s)
    assert e_c[1] < 0.1 * e_s[1]
    assert max(its) <= 12 and its[1] <= its[0] + 2  # p-multigrid on the P1 levels: flat iteration counts
    assert e_c[1] * 10 <= e_p1, (e_c[1], e_p1)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["poisson-dirichlet", "poisson-neumann"])
def test_ball_curved_p2_converges_at_third_order(ball, name):
    tets, P = ball
    f, u = (_ball_source, _ball_dirichlet) if name == "poisson-dirichlet" else (_zero, _un)
    # curved P2 on 1280 and 10240 tets (the 160-tet mesh is the coarse level), P1 on 82k tets
    _check_rates(*_convergence(tets, P, name, sphere_projector(), f, u, coarse_end=4))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["poisson-dirichlet", "poisson-neumann"])
def test_torus_curved_p2_converges_at_third_order(torus, name):
    tets, P = torus
    _check_rates(*_convergence(tets, P, name, torus_projector(), _zero, _un, coarse_end=len(tets)))


@pytest.mark.parametrize("shape", ["ball", "torus"])
def test_surface_fit_converges_at_third_order(ball, torus, shape):
    (tets, _), proj = (ball, sphere_projector()) if shape == "ball" else (torus, torus_projector())
    reps = [curve_mesh(*tets[j], proj).report for j in (2, 1)]
    d = [r["surface_distance"] for r in reps]
    assert np.log2(d[0]["curved_max"] / d[1]["curved_max"]) >= 2.7, d
    assert np.log2(d[0]["straight_max"] / d[1]["straight_max"]) <= 2.2, d
    rep = reps[1]
    assert rep["certified"] and rep["straightened"] == 0
    assert 0.5 < rep["scaled_jacobian"]["min"] <= 1.0


def test_bad_input_is_one_clear_error(ball):
    V, T = ball[0][3]
    with pytest.raises(NestmgInputError, match="element"):
        setup_problem(ball[0][3:], ball[1][3:], element="P3")
    with pytest.raises(NestmgInputError, match="need element='P2'"):
        setup_problem(ball[0][3:], ball[1][3:], flux=lambda x, n: x[:, 0])
    with pytest.raises(NestmgInputError, match="curve tets"):
        setup_problem(ball[0][2:], ball[1][2:], element="P2", curved=curve_mesh(V, T, sphere_projector()))
    with pytest.raises(NestmgInputError, match="curve_mesh needs"):
        curve_mesh(V[:, :2], T, sphere_projector())


def test_cli_solve_element_p2_writes_tetra10(tmp_path):
    import json

    import meshio

    from nestmg.cli import main

    out = tmp_path / "r.json"
    rc = main(["solve", "shape:sphere", "--method", "decimate", "--levels", "2", "--mesher", "tetgen",
               "--max-tets", "8000", "--element", "P2", "--accel", "cg", "--json", str(out), "--out",
               str(tmp_path / "vtu"), "--quiet"])
    assert rc == 0
    r = json.loads(out.read_text())["solve"]
    assert r["element"] == "P2" and r["converged"] and r["iterations"] <= 20
    assert r["curved"]["certified"] and r["curved"]["level"] == 0
    m = meshio.read(tmp_path / "vtu" / "p2.vtu")
    assert m.cells[0].type == "tetra10" and len(m.cells[0].data) == r["curved"]["tets"]
    assert np.isfinite(m.point_data["u"]).all() and np.abs(m.point_data["u"]).max() > 0
    assert "sj_floor" not in r["curved"]  # off by default; --sj-floor reaches curve_mesh:
    rc = main(["solve", "shape:sphere", "--method", "decimate", "--levels", "2", "--mesher", "tetgen",
               "--max-tets", "8000", "--element", "P2", "--sj-floor", "0.955", "--json", str(out), "--quiet"])
    r = json.loads(out.read_text())["solve"]
    assert rc == 0 and r["converged"] and r["curved"]["certified"]
    assert r["curved"]["sj_floor"]["floor"] == 0.955 and r["curved"]["scaled_jacobian"]["bound_min"] >= 0.955
    assert main(["solve", "shape:sphere", "--element", "P2", "--problem", "elasticity-free", "--levels", "2",
                 "--mesher", "tetgen", "--max-tets", "8000", "--quiet"]) == 2
