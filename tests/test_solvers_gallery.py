"""Tests of solvers.gallery: the exactly nested Kuhn cube hierarchy."""

import igl
import numpy as np
import pytest

from solvers import fem
from solvers.errors import SolverInputError
from solvers.gallery import kuhn_cube_hierarchy, kuhn_cube_mesh


def test_kuhn_mesh_is_a_valid_conforming_tet_mesh():
    n = 4
    V, T = kuhn_cube_mesh(n)
    assert V.shape == ((n + 1) ** 3, 3) and T.shape == (6 * n**3, 4)
    assert V.dtype == np.float64 and T.dtype == np.int64
    vol = igl.volume(V, T).ravel()
    np.testing.assert_allclose(vol, 1.0 / (6 * n**3), rtol=1e-12)  # all positively oriented
    F = igl.boundary_facets(T)[0]
    assert F.shape[0] == 12 * n**2  # conforming: only the cube's faces are unmatched


def test_prolongation_is_exact_barycentric_interpolation():
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    for (Vf, _), (Vc, Tc), P in zip(meshes, meshes[1:], Ps):
        assert P.shape == (len(Vf), len(Vc))
        np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0, atol=1e-15)
        a = np.array([0.7, -1.1, 0.4])
        np.testing.assert_allclose(P @ (Vc @ a + 2), Vf @ a + 2, atol=1e-14)
        # independent check: locate fine nodes in coarse tets with libigl and interpolate
        tree = igl.AABB()
        tree.init(Vc, Tc)
        q = Vf * (1 - 1e-9) + 0.5e-9  # nudge nodes off the faces so in_element is unambiguous
        I = igl.in_element(Vc, Tc, q, tree)
        assert np.all(I >= 0)
        tc = Tc[I]
        B = igl.barycentric_coordinates(q, *[np.ascontiguousarray(Vc[tc[:, k]]) for k in range(4)])
        Pd = P.toarray()
        np.testing.assert_allclose(Pd[np.arange(len(Vf))[:, None], tc], B, atol=1e-8)
        assert np.allclose(Pd.sum(axis=1), B.sum(axis=1))


def test_nestedness_galerkin_equals_rediscretisation():
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    Ks = [fem.stiffness_matrix(V, T) for V, T in meshes]
    for Kf, Kc, P in zip(Ks, Ks[1:], Ps):
        assert abs(P.T @ Kf @ P - Kc).max() < 1e-12


def test_hierarchy_sizes_and_errors():
    meshes, Ps = kuhn_cube_hierarchy(16, 4)
    assert [len(V) for V, _ in meshes] == [17**3, 9**3, 5**3, 3**3]
    assert len(Ps) == 3
    with pytest.raises(SolverInputError, match="multiple"):
        kuhn_cube_hierarchy(12, 4)
    with pytest.raises(SolverInputError):
        kuhn_cube_hierarchy(4, 0)
    with pytest.raises(SolverInputError):
        kuhn_cube_mesh(0)


def test_docstring_examples():
    import doctest

    import solvers.gallery

    failures, tests = doctest.testmod(solvers.gallery)
    assert tests >= 3 and failures == 0


def test_kuhn_interpolation_at_random_points_matches_libigl():
    from solvers.gallery import kuhn_interpolation

    n = 3
    Vc, Tc = kuhn_cube_mesh(n)
    Q = np.random.default_rng(5).uniform(0, 1, (400, 3))
    P = kuhn_interpolation(Q, n)
    assert P.shape == (400, len(Vc)) and np.all(P.data >= 0) and P.getnnz(axis=1).max() <= 4
    np.testing.assert_allclose(P @ Vc, Q, atol=1e-14)  # reproduces the coordinates
    tree = igl.AABB()
    tree.init(Vc, Tc)
    I = igl.in_element(Vc, Tc, Q, tree)
    tc = Tc[I]
    B = igl.barycentric_coordinates(Q, *[np.ascontiguousarray(Vc[tc[:, k]]) for k in range(4)])
    np.testing.assert_allclose(P.toarray()[np.arange(len(Q))[:, None], tc], B, atol=1e-12)
    with pytest.raises(SolverInputError, match="outside"):
        kuhn_interpolation([[0.5, 0.5, 1.01]], n)
