import numpy as np
import pytest

from nestmg.errors import NestmgError, NestmgInputError
from nestmg.prolongation import EXTRAPOLATIONS, prolongation
from solvers.errors import SolverInputError


def _cube_tets(n=4, scale=1.0):
    from solvers.gallery import kuhn_cube_mesh

    V, T = kuhn_cube_mesh(n)
    return (V - 0.5) * scale, T


def test_inside_nodes_reproduce_linear_functions(rng):
    Vc, Tc = _cube_tets(4)
    Q = rng.uniform(-0.5, 0.5, (5000, 3))
    P, rep = prolongation(Q, Vc, Tc)
    assert rep.n_outside == 0 and rep.max_distance == 0.0
    a = np.array([0.3, -1.2, 2.0])
    assert np.abs(P @ (Vc @ a + 0.7) - (Q @ a + 0.7)).max() < 1e-12
    assert np.abs(np.asarray(P.sum(axis=1)).ravel() - 1).max() < 1e-12
    assert P.shape == (5000, len(Vc)) and (P.getnnz(axis=1) <= 4).all()
    assert P.min() >= 0


@pytest.mark.parametrize("rule", EXTRAPOLATIONS)
def test_outside_nodes_counted_and_extrapolated(rule, rng):
    Vc, Tc = _cube_tets(3)
    inside = rng.uniform(-0.45, 0.45, (300, 3))
    outside = np.array([[0.6, 0.0, 0.0], [0.0, -0.55, 0.1], [0.52, 0.52, 0.0]])
    P, rep = prolongation(np.vstack([inside, outside]), Vc, Tc, extrapolation=rule)
    assert rep.n_outside == 3
    assert abs(rep.max_distance - 0.1) < 1e-12  # farthest of the three: (0.6, 0, 0) is 0.1 away
    rows = np.asarray(P.sum(axis=1)).ravel()
    assert np.abs(rows - 1).max() < 1e-12
    a = np.array([1.0, 2.0, 3.0])
    f = Vc @ a
    err = np.abs(P @ f - np.vstack([inside, outside]) @ a)
    assert err[:300].max() < 1e-12  # inside rows exact whatever the rule
    if rule == "linear":
        assert err[300:].max() < 1e-12  # linear extrapolation also reproduces linears outside
    elif rule == "clamped":
        assert P.min() >= 0 and err[300:].max() > 1e-3  # clamped weights cannot reach outside points
    elif rule == "closest_point":
        # value of the closest boundary point: (0.5, 0, 0) for (0.6, 0, 0)
        assert abs((P @ f)[300] - np.array([0.5, 0, 0]) @ a) < 1e-12


def test_bad_input_is_rejected():
    """The extrapolation is prolongation's own check; the arrays are checked once, by locate_in_tets."""
    Vc, Tc = _cube_tets(2)
    with pytest.raises(NestmgInputError, match="^unknown extrapolation 'magic'; choose from"):
        prolongation(np.zeros((1, 3)), Vc, Tc, extrapolation="magic")
    n, m = len(Vc), Tc.max() + 1000
    bad = [((np.array([[np.nan, 0, 0]]), Vc, Tc), "^node coordinates contain NaN or inf$"),
           ((np.zeros((1, 3)), Vc, Tc + 1000),
            rf"^the coarse tets index nodes outside the {n} coarse nodes \(indices 1000 to {m}\)$"),
           ((np.zeros((4, 2)), Vc, Tc), r"must be \(n,3\) arrays, got shapes \(4, 2\) and"),
           ((np.zeros((1, 3)), Vc, Tc[:, :3]),
            r"^the coarse tets must be a non-empty \(t,4\) array, got shape"),
           ((np.zeros((1, 3)), Vc, Tc[:0]), r"non-empty \(t,4\) array, got shape \(0, 4\)$")]
    for args, message in bad:
        with pytest.raises(SolverInputError, match=message) as exc:
            prolongation(*args)
        assert isinstance(exc.value, NestmgError) and isinstance(exc.value, ValueError)
        assert "\n" not in str(exc.value)


def test_million_nodes_in_seconds(rng):
    import time

    Vc, Tc = _cube_tets(20)  # 48k tets
    Q = rng.uniform(-0.5, 0.5, (1_000_000, 3))
    t0 = time.perf_counter()
    P, rep = prolongation(Q, Vc, Tc)
    dt = time.perf_counter() - t0
    assert rep.n_outside == 0 and P.shape[0] == 1_000_000
    assert dt < 15.0, f"1M nodes took {dt:.1f} s"


def test_nodes_on_the_coarse_boundary_up_to_roundoff_are_not_extrapolated():
    Vc, Tc = _cube_tets(2)
    Q = np.array([[0.5 + 1e-15, 0.1, -0.2], [0.5 + 1e-3, 0.1, -0.2], [0.0, 0.0, 0.0]])  # on, outside, inside
    P, rep = prolongation(Q, Vc, Tc, extrapolation="linear")
    assert rep.n_outside == 1 and rep.n_on_boundary == 1
    assert abs(rep.max_distance - 1e-3) < 1e-12
    a = np.array([1.0, -2.0, 0.5])
    assert abs(P[0] @ (Vc @ a) - np.array([0.5, 0.1, -0.2]) @ a) < 1e-12  # exact at the boundary point
    _, rep2 = prolongation(Q, Vc, Tc, on_boundary_tol=0.0)
    assert rep2.n_on_boundary == 0 and rep2.n_outside in (1, 2)  # point location may or may not catch it
