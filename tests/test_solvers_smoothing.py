"""Tests of solvers.smoothing: the smoother registry over pyamg's kernels."""

import numpy as np
import pytest

from solvers import fem
from solvers.errors import SolverInputError
from solvers.gallery import kuhn_cube_mesh
from solvers.smoothing import SMOOTHERS, make_smoother, spectral_radius


@pytest.fixture(scope="module")
def poisson():
    V, T = kuhn_cube_mesh(8)
    K = fem.stiffness_matrix(V, T)
    ds = fem.eliminate_dirichlet(K, np.zeros(len(V)), fem.boundary_nodes(T))
    return ds.A


def _error_reduction(A, spec, sweeps=10, seed=0):
    """||e_after||_A / ||e_before||_A for A x = 0 from a random start (the error is x itself)."""
    x = np.random.default_rng(seed).standard_normal(A.shape[0])
    e0 = np.sqrt(x @ A @ x)
    sm = make_smoother(A, spec)
    b = np.zeros_like(x)
    for _ in range(sweeps):
        sm(A, x, b)
    return np.sqrt(x @ A @ x) / e0, sm


def test_registry_names():
    assert {"gauss_seidel", "symmetric_gauss_seidel", "jacobi", "chebyshev", "none"} <= set(SMOOTHERS)


@pytest.mark.parametrize(
    "spec, bound",
    [
        # measured: 0.0040, 0.00043, 0.022, 0.037, 0.0038, 0.0041 (10 sweeps, random start, n=8 cube)
        ("gauss_seidel", 0.01),
        ("symmetric_gauss_seidel", 0.001),
        ("jacobi", 0.045),
        (("jacobi", {"omega": 0.5}), 0.075),
        ("chebyshev", 0.008),
        (("chebyshev", {"degree": 2, "iterations": 2}), 0.008),
    ],
)
def test_smoothers_reduce_energy_error(poisson, spec, bound):
    red, sm = _error_reduction(poisson, spec)
    assert red < bound, (spec, red)
    assert sm.work > 0


@pytest.mark.parametrize(
    "spec, high_max",
    # measured on the n=16 cube, one application: smooth mode keeps 0.96 / 0.93 / 0.99 / 0.88 of its
    # energy norm, the highest grid mode 0.33 / 0.11 / 0.34 / 0.13
    [("gauss_seidel", 0.4), ("symmetric_gauss_seidel", 0.15), ("jacobi", 0.4), ("chebyshev", 0.2)],
)
def test_smoother_damps_high_frequencies_not_smooth_ones(spec, high_max):
    n = 16
    V, T = kuhn_cube_mesh(n)
    A = fem.eliminate_dirichlet(fem.stiffness_matrix(V, T), np.zeros(len(V)), fem.boundary_nodes(T)).A
    i = np.arange(1, n)
    out = []
    for freq in (1, n - 1):  # lowest and highest discrete sine mode in each direction
        g = np.sin(np.pi * freq * i / n)
        x = np.einsum("i,j,k->kji", g, g, g).ravel()
        e0 = np.sqrt(x @ A @ x)
        make_smoother(A, spec)(A, x, np.zeros_like(x))
        out.append(np.sqrt(x @ A @ x) / e0)
    assert out[0] > 0.85 and out[1] < high_max, (spec, out)


def test_none_does_nothing(poisson):
    red, sm = _error_reduction(poisson, "none")
    assert red == 1.0 and sm.work == 0


def test_jacobi_default_weight_and_spectral_radius(poisson):
    A = poisson.toarray()
    d = np.diag(A)
    rho = np.linalg.eigvalsh(A / np.sqrt(np.outer(d, d))).max()
    assert spectral_radius(poisson, jacobi=True) == pytest.approx(rho, rel=0.05)
    sm = make_smoother(poisson, "jacobi")
    assert sm.params["omega"] == pytest.approx(4 / (3 * rho), rel=0.05)
    ch = make_smoother(poisson, ("chebyshev", {"degree": 4}))
    assert ch.params["upper"] >= rho and ch.work == 4


def test_symmetric_gs_is_a_symmetric_operator(poisson):
    """x <- S(b) from x=0 is linear in b; symmetric GS gives a symmetric matrix, forward GS does not."""
    n = poisson.shape[0]
    rng = np.random.default_rng(1)
    u, v = rng.standard_normal((2, n))

    def apply(spec, b):
        x = np.zeros(n)
        make_smoother(poisson, spec)(poisson, x, b)
        return x

    s = apply("symmetric_gauss_seidel", u) @ v - u @ apply("symmetric_gauss_seidel", v)
    f = apply("gauss_seidel", u) @ v - u @ apply("gauss_seidel", v)
    assert abs(s) < 1e-12 * abs(u @ v + 1) and abs(f) > 1e-3


def test_bad_specs(poisson):
    with pytest.raises(SolverInputError, match="unknown smoother"):
        make_smoother(poisson, "ilu")
    with pytest.raises(SolverInputError, match="bad options"):
        make_smoother(poisson, ("jacobi", {"weight": 0.5}))
    with pytest.raises(SolverInputError, match="sweep"):
        make_smoother(poisson, ("gauss_seidel", {"sweep": "sideways"}))
    with pytest.raises(SolverInputError, match="iterations"):
        make_smoother(poisson, ("jacobi", {"iterations": -1}))
    with pytest.raises(SolverInputError, match="lower_bound"):
        make_smoother(poisson, ("chebyshev", {"lower_bound": 2.0}))
    with pytest.raises(SolverInputError):
        make_smoother(poisson, 3)


def test_triangular_split_reassembles_the_matrix(poisson):
    import scipy.sparse as sp

    from solvers.smoothing import triangular_split

    A = sp.csr_matrix(poisson)
    A.sort_indices()
    L, U = triangular_split(A)
    assert abs(L - sp.tril(A)).max() == 0 and abs(U - sp.triu(A, 1)).max() == 0
    assert L.nnz + U.nnz == A.nnz and np.array_equal(L.diagonal(), A.diagonal())


@pytest.mark.parametrize("iterations", [1, 2, 3])
@pytest.mark.parametrize("zero", [True, False])
@pytest.mark.parametrize("given_lower", [False, True])
def test_gauss_seidel_residual_fast_path(poisson, iterations, zero, given_lower):
    """The forward sweeps' cheap residual U (x_old - x_new) (and the half sweep from zero) give the
    same iterate and residual as the sweeps followed by b - A x, to round-off; with ``lower = (D + L, d)``
    given (rows shuffled, as any order within rows is allowed) ``U`` is read off it."""
    import scipy.sparse as sp

    A = poisson
    lower = None
    if given_lower:
        DL = sp.csr_matrix(sp.tril(A))
        rng = np.random.default_rng(7)
        for i in range(DL.shape[0]):  # shuffle every row's entries
            s = slice(DL.indptr[i], DL.indptr[i + 1])
            p = rng.permutation(s.stop - s.start)
            DL.indices[s], DL.data[s] = DL.indices[s][p], DL.data[s][p]
        DL.has_sorted_indices = False
        lower = (DL, A.diagonal())
    sm = make_smoother(A, ("gauss_seidel", {"sweep": "forward", "iterations": iterations}), lower=lower)
    assert sm.smooth_residual is not None
    rng = np.random.default_rng(iterations)
    b = rng.standard_normal(A.shape[0])
    x0 = np.zeros(A.shape[0]) if zero else rng.standard_normal(A.shape[0])
    x_ref = x0.copy()
    sm(A, x_ref, b)
    r_ref = b - A @ x_ref
    x = x0.copy()
    r = sm.residual(A, x, b, zero=zero)
    assert np.abs(x - x_ref).max() <= 1e-13 * np.abs(x_ref).max()
    assert np.abs(r - r_ref).max() <= 1e-12 * np.abs(b).max()
    assert np.abs(r_ref).max() > 1e-3 * np.abs(b).max()  # a residual that is not trivially zero
    # another operator than the smoother's own: the plain path
    A2 = 2.0 * A
    assert sm.smooth_residual(A2, x0.copy(), b, zero) is None


def test_symmetric_sor_uses_its_weight(poisson):
    """``symmetric_gauss_seidel`` with ``omega`` is SSOR: a forward then a backward SOR sweep (pyamg's own
    symmetric sweep runs ``omega = 1`` whatever it is given)."""
    from pyamg.relaxation.relaxation import sor

    rng = np.random.default_rng(2)
    x0, b = rng.standard_normal((2, poisson.shape[0]))
    for omega in (0.8, 1.0, 1.5):
        x = x0.copy()
        make_smoother(poisson, ("symmetric_gauss_seidel", {"omega": omega, "iterations": 2}))(poisson, x, b)
        y = x0.copy()
        for _ in range(2):
            sor(poisson, y, b, omega, sweep="forward")
            sor(poisson, y, b, omega, sweep="backward")
        assert np.allclose(x, y, rtol=0, atol=1e-14 * np.abs(y).max()), omega
    z = x0.copy()
    make_smoother(poisson, ("symmetric_gauss_seidel", {"omega": 1.5}))(poisson, z, b)
    w = x0.copy()
    make_smoother(poisson, "symmetric_gauss_seidel")(poisson, w, b)
    assert np.abs(z - w).max() > 1e-3 * np.abs(w).max()  # the weight changes the sweep


def test_reversed_order_is_the_reversal_permutation(poisson):
    import scipy.sparse as sp

    from solvers.smoothing import reversed_order

    A = sp.csr_matrix(poisson)
    A.sort_indices()
    A.data = A.data * (1.0 + np.arange(A.nnz) / A.nnz)  # distinct entries, not symmetric: order matters
    J = np.arange(A.shape[0])[::-1]
    R = reversed_order(A)
    ref = sp.csr_matrix(A[J][:, J])
    ref.sort_indices()
    assert R.has_canonical_format and np.array_equal(R.indptr, ref.indptr)
    assert np.array_equal(R.indices, ref.indices) and np.array_equal(R.data, ref.data)


@pytest.mark.parametrize("sweep,iterations,omega", [("backward", 1, 1.0), ("backward", 2, 1.0),
                                                    ("backward", 2, 1.4), ("symmetric", 2, 1.0),
                                                    ("symmetric", 1, 0.8)])
def test_backward_sweeps_on_the_reversed_matrix_equal_pyamgs(poisson, sweep, iterations, omega, monkeypatch):
    """A backward sweep runs forwards on J A J (rows of >= REVERSED_SWEEP_MIN_ROW entries: here every
    matrix); the iterate equals pyamg's backward sweep to round-off (each row's sum in the other order).
    Another operator takes pyamg's path."""
    from pyamg.relaxation.relaxation import sor

    import solvers.smoothing as smoothing

    monkeypatch.setattr(smoothing, "REVERSED_SWEEP_MIN_ROW", 0)
    A = poisson
    rng = np.random.default_rng(7)
    x0, b = rng.standard_normal((2, A.shape[0]))
    sm = make_smoother(A, ("gauss_seidel", {"sweep": sweep, "iterations": iterations, "omega": omega}))
    x = x0.copy()
    sm(A, x, b)
    y = x0.copy()
    for _ in range(iterations):
        if sweep == "symmetric":
            sor(A, y, b, omega, sweep="forward")
        sor(A, y, b, omega, sweep="backward")
    assert np.abs(x - y).max() <= 1e-13 * np.abs(y).max()
    assert np.abs(x - x0).max() > 1e-2 * np.abs(x0).max()  # the sweeps did move x
    A2 = 2.0 * A  # not the smoother's operator: pyamg on A2 itself
    z, w = x0.copy(), x0.copy()
    sm(A2, z, b)
    for _ in range(iterations):
        if sweep == "symmetric":
            sor(A2, w, b, omega, sweep="forward")
        sor(A2, w, b, omega, sweep="backward")
    assert np.array_equal(z, w)


def test_short_rows_keep_pyamgs_backward_sweep(poisson):
    """Rows shorter than REVERSED_SWEEP_MIN_ROW (a P1 Laplacian's ~14) keep pyamg's backward sweep: the
    same bits, no reversed copy."""
    from pyamg.relaxation.relaxation import gauss_seidel

    from solvers.smoothing import REVERSED_SWEEP_MIN_ROW

    assert poisson.nnz < REVERSED_SWEEP_MIN_ROW * poisson.shape[0]
    rng = np.random.default_rng(3)
    x0, b = rng.standard_normal((2, poisson.shape[0]))
    x, y = x0.copy(), x0.copy()
    make_smoother(poisson, ("gauss_seidel", {"sweep": "backward", "iterations": 2}))(poisson, x, b)
    gauss_seidel(poisson, y, b, iterations=2, sweep="backward")
    assert np.array_equal(x, y)
