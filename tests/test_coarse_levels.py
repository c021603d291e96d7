"""``solvers.coarse_levels``: the first coarse mesh cropped to a box, rows of coarse prolongations, streamed.

Pure numpy (no PETSc): the pieces a rank of ``PetscMultigrid.from_distributed`` reads must equal the
global objects' pieces, read from arrays or streamed from a file in many small chunks.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import solvers.coarse_levels as cl
from solvers.coarse_levels import CoarseLevels, save_coarse_levels
from solvers.errors import SolverInputError
from solvers.gallery import kuhn_cube_hierarchy
from solvers.locate import locate_in_tets


@pytest.fixture(scope="module")
def levels():
    meshes, Ps = kuhn_cube_hierarchy(12, 3)
    return meshes, Ps


@pytest.fixture()
def small_chunks(monkeypatch):
    monkeypatch.setattr(cl, "CHUNK_ROWS", 37)  # many chunks, rows split across chunk borders


def _sources(tmp_path, meshes, Ps):
    V1, T1 = meshes[1]
    save_coarse_levels(tmp_path / "coarse.npz", V1, T1, Ps[1:])
    return [CoarseLevels.from_arrays(V1, T1, Ps[1:]), CoarseLevels.from_file(tmp_path / "coarse.npz")]


def test_crop_is_exactly_the_tets_whose_box_meets(tmp_path, levels, small_chunks):
    meshes, Ps = levels
    V1, T1 = meshes[1]
    box = (np.array([0.1, 0.0, 0.3]), np.array([0.45, 1.0, 0.62]))
    lo, hi = V1[T1].min(axis=1), V1[T1].max(axis=1)
    want = np.flatnonzero(np.all((lo <= box[1]) & (hi >= box[0]), axis=1))
    assert 0 < len(want) < len(T1) // 2
    for src in _sources(tmp_path, meshes, Ps):
        assert (src.n_nodes, src.n_tets, src.shapes) == (len(V1), len(T1), [P.shape for P in Ps[1:]])
        V, T, gid = src.crop(box)
        assert np.all(np.diff(gid) > 0) and np.array_equal(V, V1[gid])
        assert np.array_equal(_sorted_rows(gid[T]), _sorted_rows(T1[want]))


def _sorted_rows(T):
    T = np.sort(T, axis=1)
    return T[np.lexsort(T.T[::-1])]


def test_location_in_the_crop_equals_location_in_the_whole_mesh(levels):
    """Fine nodes of a slab (incl. ones on coarse faces and on the boundary) get the same weights."""
    meshes, Ps = levels
    V0 = meshes[0][0]
    V1, T1 = meshes[1]
    pts = V0[(V0[:, 2] > 0.24) & (V0[:, 2] < 0.6)]
    whole = locate_in_tets(pts, V1, T1)
    margin = 1e-6 * np.sqrt(3)
    V, T, gid = CoarseLevels.from_arrays(V1, T1).crop((pts.min(axis=0) - margin, pts.max(axis=0) + margin))
    assert len(T) < len(T1)
    part = locate_in_tets(pts, V, T, diag=np.sqrt(3))
    A = sp.csr_matrix((whole.weights.ravel(), (np.repeat(np.arange(len(pts)), 4), whole.cols.ravel())))
    B = sp.csr_matrix((part.weights.ravel(), (np.repeat(np.arange(len(pts)), 4), gid[part.cols].ravel())),
                      shape=A.shape)
    assert len(part.outside) == len(whole.outside) == 0
    assert abs(A - B).max() < 1e-12


def test_rows_equal_the_global_rows(tmp_path, levels, small_chunks):
    meshes, Ps = levels
    rng = np.random.default_rng(3)
    for src in _sources(tmp_path, meshes, Ps):
        for k, P in enumerate(Ps[1:], start=1):
            rows = np.sort(rng.choice(P.shape[0], size=P.shape[0] // 3, replace=False))
            rows[-1] = P.shape[0] - 1  # the last row (its end is the last indptr entry)
            got = src.rows(k, rows)
            assert got.shape == (len(rows), P.shape[1])
            assert abs(got - sp.csr_matrix(P)[rows]).max() == 0 and got.nnz == sp.csr_matrix(P)[rows].nnz
        assert src.rows(1, np.zeros(0, dtype=np.int64)).shape == (0, Ps[1].shape[1])


def test_bad_inputs(tmp_path, levels):
    meshes, Ps = levels
    V1, T1 = meshes[1]
    with pytest.raises(SolverInputError, match="does not exist"):
        CoarseLevels.from_file(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(SolverInputError, match="not an .npz"):
        CoarseLevels.from_file(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", V=V1)
    with pytest.raises(SolverInputError, match="lacks"):
        CoarseLevels.from_file(tmp_path / "other.npz")
    with pytest.raises(SolverInputError, match=r"coarse_Ps\[0\] has shape"):
        CoarseLevels.from_arrays(V1, T1, [Ps[1].T])
    with pytest.raises(SolverInputError, match="index nodes outside"):
        CoarseLevels.from_arrays(V1, T1 + len(V1))
    with pytest.raises(SolverInputError, match="finite"):
        CoarseLevels.from_arrays(np.full_like(V1, np.nan), T1)
