"""Tests of solvers.fem: P1 stiffness/mass on tets, boundary nodes, Dirichlet elimination, Neumann helpers."""

import igl
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solvers import fem
from solvers.errors import IncompatibleRHSError, SolverInputError
from solvers.gallery import kuhn_cube_mesh


@pytest.fixture(scope="module")
def jittered_cube():
    """Kuhn cube, n=4, interior nodes moved randomly (an unstructured, still valid tet mesh)."""
    rng = np.random.default_rng(7)
    V, T = kuhn_cube_mesh(4)
    interior = np.setdiff1d(np.arange(len(V)), fem.boundary_nodes(T))
    V = V.copy()
    V[interior] += rng.uniform(-0.06, 0.06, size=(interior.size, 3))
    return V, T


def _reference_stiffness(V, T):
    """Element-by-element K_ij = vol ∇φ_i·∇φ_j, written independently of libigl (tests only)."""
    n = len(V)
    K = np.zeros((n, n))
    for t in T:
        X = V[t]
        D = np.column_stack([X[1] - X[0], X[2] - X[0], X[3] - X[0]])  # x = X0 + D λ
        vol = abs(np.linalg.det(D)) / 6
        Ginv = np.linalg.inv(D)  # rows: gradients of λ1..λ3
        G = np.vstack([-Ginv.sum(axis=0), Ginv])
        K[np.ix_(t, t)] += vol * G @ G.T
    return K


def test_stiffness_matches_reference_and_is_psd(jittered_cube):
    V, T = jittered_cube
    K = fem.stiffness_matrix(V, T)
    Kd = K.toarray()
    np.testing.assert_allclose(Kd, _reference_stiffness(V, T), atol=1e-12)
    assert abs(K - K.T).max() < 1e-14
    assert np.abs(K @ np.ones(len(V))).max() < 1e-12  # rows sum to 0
    ev = np.linalg.eigvalsh(Kd)
    assert ev[0] > -1e-12 and ev[1] > 1e-3  # PSD, one-dimensional null space (connected mesh)



def test_stiffness_equals_libigl_cotmatrix_with_unused_nodes(jittered_cube):
    """The own COO assembly of libigl's cotangent weights gives libigl's matrix; unused nodes keep
    empty rows; the CSR arrays are canonical (sorted, no duplicates)."""
    V, T = jittered_cube
    V2 = np.vstack([V, [[5.0, 5.0, 5.0]]])  # one node in no tet
    K = fem.stiffness_matrix(V2, T)
    ref = -igl.cotmatrix(V2, T)
    assert abs(K - ref).max() < 1e-13
    assert K.getrow(len(V)).nnz == 0
    assert K.has_canonical_format and np.all(np.diff(K.indptr) >= 0)
    for r in range(0, K.shape[0], 7):
        cols = K.indices[K.indptr[r]:K.indptr[r + 1]]
        assert np.all(np.diff(cols) > 0)
    _, _, vol = fem.check_tet_mesh(V, T, return_volumes=True)
    assert vol.sum() == pytest.approx(1.0, rel=1e-12) and np.all(vol > 0)

def test_stiffness_energy_of_linear_functions(jittered_cube):
    V, T = jittered_cube
    K = fem.stiffness_matrix(V, T)
    a = np.array([0.3, -1.7, 2.2])
    u = V @ a + 5.0
    # ∫|∇u|² = |a|² · volume (unit cube)
    assert u @ K @ u == pytest.approx(a @ a, rel=1e-12)


@pytest.mark.parametrize("kind", ["barycentric", "voronoi", "full"])
def test_mass_sums_to_volume(jittered_cube, kind):
    V, T = jittered_cube
    M = fem.mass_matrix(V, T, kind)
    assert M.sum() == pytest.approx(1.0, rel=1e-12)
    assert abs(M - M.T).max() < 1e-15
    if kind != "full":
        assert M.nnz == len(V) and np.all(M.diagonal() > 0)


def test_full_mass_is_exact_for_p1(jittered_cube):
    V, T = jittered_cube
    M = fem.mass_matrix(V, T, "full")
    x = V[:, 0]
    assert x @ M @ x == pytest.approx(1.0 / 3.0, rel=1e-12)  # ∫ x² over the unit cube
    ev = np.linalg.eigvalsh(M.toarray())
    assert ev[0] > 0


def test_boundary_nodes_of_cube():
    n = 5
    V, T = kuhn_cube_mesh(n)
    b = fem.boundary_nodes(T)
    assert b.size == (n + 1) ** 3 - (n - 1) ** 3
    on_face = np.any((V < 1e-12) | (V > 1 - 1e-12), axis=1)
    np.testing.assert_array_equal(b, np.flatnonzero(on_face))



def _cube_with_cavity_and_pinch():
    """4x4x4 Kuhn cube minus its 2x2x2 centre (an inner boundary surface), plus one extra cube of 6 tets
    touching the big cube at a single corner node (a pinched vertex), plus an unused node."""
    V, T = kuhn_cube_mesh(4)
    c = V[T].mean(axis=1)
    T = T[~np.all((c > 0.25) & (c < 0.75), axis=1)]
    V2, T2 = kuhn_cube_mesh(1)
    V2 = V2 * 0.25 + 1.0  # corner (1, 1, 1) coincides with the big cube's node (1, 1, 1)
    shared = int(np.flatnonzero(np.all(np.abs(V - 1.0) < 1e-12, axis=1))[0])
    own = np.all(np.abs(V2 - 1.0) < 1e-12, axis=1)
    idx = np.where(own, shared, len(V) + np.cumsum(~own) - 1)
    V = np.vstack([V, V2[~own], [[9.0, 9.0, 9.0]]])
    return V, np.vstack([T, idx[T2]])


def test_boundary_nodes_from_stiffness_link_topology(jittered_cube):
    """The O(n) link-Euler classification equals the face count on a convex mesh, one with a cavity
    and a pinched vertex; the cavity's nodes and the pinched node are boundary, the unused node not."""
    V, T = _cube_with_cavity_and_pinch()
    K = fem.stiffness_matrix(V, T)
    b_faces = fem.boundary_nodes(T)
    b_link = fem.boundary_nodes(T, stiffness=K)
    np.testing.assert_array_equal(b_link, b_faces)
    on_cavity = np.all((V >= 0.25 - 1e-12) & (V <= 0.75 + 1e-12), axis=1)
    on_cavity &= np.abs(V - 0.5).max(axis=1) > 1e-12  # the removed block's centre node is unused
    assert np.all(np.isin(np.flatnonzero(on_cavity), b_link))
    assert np.count_nonzero(on_cavity) == 26  # 3x3x3 nodes of the removed block minus its centre
    assert len(V) - 1 not in b_link
    Vj, Tj = jittered_cube
    np.testing.assert_array_equal(fem.boundary_nodes(Tj, stiffness=fem.stiffness_matrix(Vj, Tj)),
                                  fem.boundary_nodes(Tj))
    with pytest.raises(SolverInputError, match="square CSR"):
        fem.boundary_nodes(T, stiffness=K[:5])

def test_dirichlet_linear_solution_is_exact(jittered_cube):
    V, T = jittered_cube
    K = fem.stiffness_matrix(V, T)
    g = V @ np.array([1.0, 2.0, -0.5]) + 0.25
    bnd = fem.boundary_nodes(T)
    ds = fem.eliminate_dirichlet(K, np.zeros(len(V)), bnd, g[bnd])
    u = ds.expand(spla.spsolve(ds.A.tocsc(), ds.b))
    assert np.abs(u - g).max() < 1e-12
    assert ds.A.shape == (len(V) - bnd.size,) * 2


def test_dirichlet_on_part_of_boundary():
    V, T = kuhn_cube_mesh(6)
    K = fem.stiffness_matrix(V, T)
    left = np.flatnonzero(V[:, 0] < 1e-12)
    right = np.flatnonzero(V[:, 0] > 1 - 1e-12)
    fixed = np.concatenate([left, right])
    vals = np.concatenate([np.zeros(left.size), np.ones(right.size)])
    ds = fem.eliminate_dirichlet(K, np.zeros(len(V)), fixed, vals)
    u = ds.expand(spla.spsolve(ds.A.tocsc(), ds.b))
    assert np.abs(u - V[:, 0]).max() < 1e-12  # other faces natural (Neumann): u = x exactly
    mask = np.zeros(len(V), bool)
    mask[fixed] = True
    ds2 = fem.eliminate_dirichlet(K, np.zeros(len(V)), mask, vals[np.argsort(fixed)])
    np.testing.assert_array_equal(ds2.free, ds.free)
    np.testing.assert_allclose(ds2.b, ds.b)


def test_poisson_converges_second_order():
    errs = []
    for n in (4, 8, 16):
        V, T = kuhn_cube_mesh(n)
        u_ex = np.prod(np.sin(np.pi * V), axis=1)
        f = 3 * np.pi**2 * u_ex
        K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
        ds = fem.eliminate_dirichlet(K, fem.load_vector(M, f), fem.boundary_nodes(T))
        u = ds.expand(spla.spsolve(ds.A.tocsc(), ds.b))
        errs.append(np.abs(u - u_ex).max())
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert rates[-1] > 1.8, (errs, rates)
    assert errs[-1] < 0.02


def test_neumann_helpers():
    V, T = kuhn_cube_mesh(3)
    M = fem.mass_matrix(V, T)
    b = fem.load_vector(M, V[:, 0] - 0.5)  # ∫ (x - 1/2) = 0 -> compatible
    fem.check_compatible(b)
    with pytest.raises(IncompatibleRHSError, match="sum"):
        fem.check_compatible(fem.load_vector(M, 1.0))
    p = fem.project_rhs(fem.load_vector(M, 1.0) + b)
    assert abs(p.sum()) < 1e-14
    u = V[:, 1] + 3.0
    assert abs(fem.remove_mean(u).mean()) < 1e-14
    um = fem.remove_mean(u, M)
    assert abs(np.ones(len(V)) @ M @ um) < 1e-14
    np.testing.assert_allclose(um, V[:, 1] - 0.5, atol=1e-14)
    # a function whose nodal mean differs from its integral: lumped-mass weights matter
    w = V[:, 1] ** 2 + V[:, 0] * V[:, 2]
    wm = fem.remove_mean(w, M)
    assert abs(np.ones(len(V)) @ M @ wm) < 1e-14
    assert abs(wm.mean()) > 1e-3  # not the plain mean
    np.testing.assert_allclose(wm - w, -(M.diagonal() @ w) / M.diagonal().sum())


def test_diffusion_matrix_is_spd():
    V, T = kuhn_cube_mesh(3)
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    A = fem.diffusion_matrix(K, M, 0.1)
    assert np.linalg.eigvalsh(A.toarray())[0] > 0
    with pytest.raises(SolverInputError):
        fem.diffusion_matrix(K, M, -1.0)
    with pytest.raises(SolverInputError):
        fem.diffusion_matrix(K, M, np.nan)


def test_bad_meshes_raise_clear_errors():
    V, T = kuhn_cube_mesh(2)
    with pytest.raises(SolverInputError, match="NaN"):
        Vn = V.copy()
        Vn[3, 1] = np.nan
        fem.stiffness_matrix(Vn, T)
    with pytest.raises(SolverInputError, match="range"):
        Tb = T.copy()
        Tb[0, 0] = len(V)
        fem.stiffness_matrix(V, Tb)
    with pytest.raises(SolverInputError, match="shape"):
        fem.mass_matrix(V[:, :2], T)
    with pytest.raises(SolverInputError, match="zero volume"):
        Vf = V.copy()
        Vf[:, 2] = 0.0  # flatten: every tet degenerate
        fem.stiffness_matrix(Vf, T)
    with pytest.raises(SolverInputError, match="repeat"):
        Tr = T.copy()
        Tr[1, 1] = Tr[1, 0]
        fem.stiffness_matrix(V, Tr)
    with pytest.raises(SolverInputError, match="kind"):
        fem.mass_matrix(V, T, "lumped")


def test_inputs_not_modified():
    V, T = kuhn_cube_mesh(3)
    V0, T0 = V.copy(), T.copy()
    K = fem.stiffness_matrix(V, T)
    b = np.ones(len(V))
    ds = fem.eliminate_dirichlet(K, b, fem.boundary_nodes(T), 2.0)
    ds.expand(np.zeros(ds.free.size))
    np.testing.assert_array_equal(V, V0)
    np.testing.assert_array_equal(T, T0)
    np.testing.assert_array_equal(b, 1.0)


def test_eliminate_dirichlet_errors():
    A = sp.identity(4, format="csr")
    with pytest.raises(SolverInputError, match="every node"):
        fem.eliminate_dirichlet(A, np.zeros(4), [0, 1, 2, 3])
    with pytest.raises(SolverInputError, match="different"):
        fem.eliminate_dirichlet(A, np.zeros(4), [0, 0], [1.0, 2.0])
    with pytest.raises(SolverInputError, match=r"must be in \[0, 4\)"):
        fem.eliminate_dirichlet(A, np.zeros(4), [4])
    with pytest.raises(SolverInputError, match="shape"):
        fem.eliminate_dirichlet(A, np.zeros(3), [0])


def test_docstring_examples():
    import doctest

    failures, tests = doctest.testmod(fem)
    assert tests >= 3 and failures == 0


def test_boundary_faces_match_libigl():
    import igl

    from solvers.fem import boundary_faces
    from solvers.gallery import kuhn_cube_mesh

    V, T = kuhn_cube_mesh(6)
    vol = np.einsum("ij,ij->i", np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), V[T[:, 3]] - V[T[:, 0]])
    T = T.copy()
    T[vol < 0, 2], T[vol < 0, 3] = T[vol < 0, 3].copy(), T[vol < 0, 2].copy()
    F, J = boundary_faces(T)
    F2 = igl.boundary_facets(T)[0]
    assert len(F) == len(F2) == 6 * 2 * 36
    assert {tuple(sorted(f)) for f in F} == {tuple(sorted(f)) for f in F2}
    assert all(set(f) <= set(T[j]) for f, j in zip(F, J))
    # outward orientation: the divergence theorem gives the cube's volume
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    assert abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 - 1.0) < 1e-12


def _reference_weighted_stiffness(V, T, w):
    n = len(V)
    K = np.zeros((n, n))
    for t, wt in zip(T, w):
        K += wt * _reference_stiffness(V, t[None])
    return K


def test_weighted_stiffness_and_mass(jittered_cube):
    """Per-tet weights: K = Σ_e w_e K_e and M = Σ_e w_e M_e (volume-fraction weighted coarse operators)."""
    V, T = jittered_cube
    w = np.random.default_rng(3).uniform(0.0, 1.0, len(T))
    Kw = fem.stiffness_matrix(V, T, w)
    np.testing.assert_allclose(Kw.toarray(), _reference_weighted_stiffness(V, T, w), atol=1e-12)
    assert np.abs(Kw @ np.ones(len(V))).max() < 1e-12
    assert abs(fem.stiffness_matrix(V, T, np.ones(len(T))) - fem.stiffness_matrix(V, T)).max() < 1e-13
    vol = np.abs(np.linalg.det(V[T[:, 1:]] - V[T[:, :1]])) / 6
    Mw = fem.mass_matrix(V, T, weights=w)
    assert Mw.sum() == pytest.approx(vol @ w, rel=1e-12)
    assert abs(fem.mass_matrix(V, T, weights=np.ones(len(T))) - fem.mass_matrix(V, T)).max() < 1e-15
    with pytest.raises(SolverInputError, match="weights"):
        fem.stiffness_matrix(V, T, -w)
    with pytest.raises(SolverInputError, match="weights"):
        fem.mass_matrix(V, T, weights=w[:-1])
    with pytest.raises(SolverInputError, match="barycentric"):
        fem.mass_matrix(V, T, kind="full", weights=w)
