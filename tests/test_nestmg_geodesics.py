"""Heat-method geodesics (nestmg.geodesics): gradient operator, accuracy on a ball, multigrid = direct."""

import numpy as np
import pytest

from nestmg.geodesics import (
    GeodesicInputError,
    divergence_rhs,
    gradient_operator,
    heat_geodesic,
    heat_precompute,
    multigrid_solve,
)
from solvers import SolverInputError
from solvers.gallery import kuhn_cube_mesh


@pytest.fixture(scope="module")
def ball():
    """Solid unit ball, TetGen, ~20k tets (convex: geodesic distance = straight-line distance)."""
    pytest.importorskip("tetgen")
    from nestmg import shapes
    from nestmg.tetmesh import tetrahedralize

    V, F = shapes.sphere(20)
    return tetrahedralize(V, F, mesher="tetgen", edge_length_abs=0.14)


def test_gradient_operator_exact_on_linear_functions(ball):
    V, T = ball
    G, vol = gradient_operator(V, T)
    a = np.array([0.3, -1.2, 2.0])
    g = (G @ (V @ a + 0.7)).reshape(-1, 3)
    assert np.abs(g - a).max() < 1e-9
    assert G.shape == (3 * len(T), len(V))
    # volume of the polyhedral ball: a bit below 4/3 π
    assert 0.95 * 4 / 3 * np.pi < vol.sum() < 4 / 3 * np.pi
    assert np.all(vol > 0)


def test_divergence_rhs_is_compatible(ball):
    V, T = ball
    pre = heat_precompute(V, T)
    u = np.exp(-np.linalg.norm(V - [0, 0, 1.0], axis=1))
    b = divergence_rhs(pre, u)
    assert abs(b.sum()) < 1e-12 * np.abs(b).sum()
    # X = -∇u/|∇u| points away from (0,0,1); ∫ X·∇φ_i is non-trivial
    assert np.abs(b).max() > 1e-3


@pytest.mark.parametrize("point, mean_tol, max_tol", [((0.0, 0.0, 0.0), 0.03, 0.08), ((0.0, 0.0, -1.0), 0.06, 0.16)])
def test_distance_in_ball_matches_straight_line(ball, point, mean_tol, max_tol):
    """Inside a convex solid the geodesic distance is |x - s| (the solid analogue of the great-circle test).

    Measured at this resolution (h ≈ 0.14, t = h²): centre source mean |error| 0.011, max 0.04;
    boundary source mean 0.033, max 0.11 (the heat method smooths near the source and at the far side).
    """
    V, T = ball
    s = int(np.argmin(np.linalg.norm(V - np.asarray(point), axis=1)))
    V0, T0 = V.copy(), T.copy()
    r = heat_geodesic(V, T, s)
    ref = np.linalg.norm(V - V[s], axis=1)
    err = np.abs(r.distance - ref)
    assert r.distance[s] == 0.0 and r.distance.min() > -0.05
    assert err.mean() < mean_tol, err.mean()
    assert err.max() < max_tol, err.max()
    # the distance is monotone along a radius from the source on average: strong correlation with ref
    assert np.corrcoef(r.distance, ref)[0, 1] > 0.995
    np.testing.assert_array_equal(V, V0)
    np.testing.assert_array_equal(T, T0)


def test_multigrid_solve_matches_direct(torus_iso_tets):
    _, tets, P, _ = torus_iso_tets
    Vf, Tf = tets[0]
    pre = heat_precompute(Vf, Tf)
    src = [0, int(np.argmax(Vf[:, 0]))]
    ref = heat_geodesic(Vf, Tf, src, pre=pre)
    for coarse in ("galerkin", "rediscretized"):
        solve = multigrid_solve(tets, P, t=pre.t, coarse=coarse, nu=2, accel="cg", tol=1e-11)
        r = heat_geodesic(Vf, Tf, src, pre=pre, solve=solve)
        assert r.info["heat"]["converged"] and r.info["poisson"]["converged"]
        assert r.info["poisson"]["iterations"] <= 25, (coarse, r.info["poisson"]["iterations"])  # measured 12 / 20
        assert np.abs(r.distance - ref.distance).max() < 1e-6 * ref.distance.max()
        assert np.abs(r.heat - ref.heat).max() < 1e-8 * ref.heat.max()
        assert min(r.distance[s] for s in src) == 0.0


def test_stationary_cycles_converge_on_nested_hierarchy(torus_iso_tets):
    """Plain V(1,1) cycles (no CG) solve both steps on the procedurally nested torus hierarchy."""
    _, tets, P, _ = torus_iso_tets
    Vf, Tf = tets[0]
    pre = heat_precompute(Vf, Tf)
    solve = multigrid_solve(tets, P, t=pre.t, coarse="galerkin", nu=1, accel=None, tol=1e-8, maxiter=80)
    r = heat_geodesic(Vf, Tf, 0, pre=pre, solve=solve)
    assert r.info["heat"]["converged"] and r.info["poisson"]["converged"]
    # measured: heat 0.47, Poisson 0.52 (26 cycles)
    assert r.info["heat"]["factor"] < 0.6 and r.info["poisson"]["factor"] < 0.7


def test_cube_corner_distance():
    V, T = kuhn_cube_mesh(8)
    d = heat_geodesic(V, T, 0).distance
    ref = np.linalg.norm(V, axis=1)
    assert np.abs(d - ref).mean() < 0.05
    assert abs(d.max() - np.sqrt(3)) < 0.15


def test_bad_inputs():
    V, T = kuhn_cube_mesh(3)
    with pytest.raises(GeodesicInputError, match="in \\[0, 64\\)"):
        heat_geodesic(V, T, 64)
    with pytest.raises(GeodesicInputError, match="non-empty"):
        heat_geodesic(V, T, np.array([], dtype=int))
    with pytest.raises(GeodesicInputError, match="integer"):
        heat_geodesic(V, T, np.array([0.5]))
    with pytest.raises(GeodesicInputError, match="positive"):
        heat_geodesic(V, T, 0, t=-1.0)
    with pytest.raises(GeodesicInputError, match="positive"):
        heat_geodesic(V, T, 0, t=float("nan"))
    Vbad = V.copy()
    Vbad[3, 1] = np.nan
    with pytest.raises(SolverInputError, match="NaN"):
        heat_geodesic(Vbad, T, 0)
    with pytest.raises(GeodesicInputError, match="coarse"):
        multigrid_solve([(V, T)], [], t=1.0, coarse="rap")
    assert isinstance(GeodesicInputError("x"), ValueError)


def test_hierarchy_of_another_mesh_is_rejected(torus_iso_tets):
    _, tets, P, _ = torus_iso_tets
    V, T = kuhn_cube_mesh(4)
    solve = multigrid_solve(tets, P, t=0.01)
    with pytest.raises(GeodesicInputError, match="not the mesh"):
        heat_geodesic(V, T, 0, solve=solve)


def test_docstring_examples():
    import doctest

    import nestmg.geodesics as mod

    assert doctest.testmod(mod).failed == 0


def test_multigrid_solve_sets_up_once_per_operator(torus_iso_tets, monkeypatch):
    """Many sources reuse one multigrid setup per operator (heat, Poisson); a new operator sets up again."""
    import nestmg.problems

    _, tets, P, _ = torus_iso_tets
    Vf, Tf = tets[0]
    pre = heat_precompute(Vf, Tf)
    calls = []
    real = nestmg.problems.setup_problem
    monkeypatch.setattr(nestmg.problems, "setup_problem", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    solve = multigrid_solve(tets, P, t=pre.t, accel="cg", tol=1e-11)
    ref = [heat_geodesic(Vf, Tf, s, pre=pre) for s in (0, 5, 9)]
    for s, r0 in zip((0, 5, 9), ref):
        r = heat_geodesic(Vf, Tf, s, pre=pre, solve=solve)
        assert np.abs(r.distance - r0.distance).max() < 1e-4 * r0.distance.max()
    assert calls == ["diffusion-neumann", "poisson-neumann"]
    solve(pre.K.copy(), np.zeros(pre.K.shape[0]), "poisson")  # another matrix object: set up again
    assert calls[-1] == "poisson-neumann" and len(calls) == 3
