"""``PetscMultigrid.from_distributed`` (issue 33): the fine level distributed, each rank's own rows of P₀.

One-rank tests run PETSc in the pytest process against the in-process ``MultigridSolver`` on the same
hierarchy; ``tests/mpi_petsc_distributed_check.py`` runs on 2 ranks with an uneven row split; the driver
``docs/examples/petsc_distributed.py`` (DMPlex partition, parallel refinement, per-rank assembly) runs on
2 ranks. Skipped with a reason without petsc4py or mpirun.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

pytest.importorskip("petsc4py", reason="petsc4py not installed: run scripts/install-petsc.sh")

from solvers.errors import OutsideCoarseMeshError, SolverInputError
from solvers.multilevel import MultigridSolver
from solvers.petsc import PetscMultigrid, broadcast_arrays
from solvers.transfer import restrict_prolongations

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
N, LEVELS = 12, 3


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_check = _load("mpi_petsc_distributed_check", HERE / "mpi_petsc_distributed_check.py")


@pytest.fixture(scope="module")
def prob():
    return _check.problem(N, LEVELS)


def _petsc_mat(A):
    from petsc4py import PETSc

    A = sp.csr_matrix(A)
    A.sort_indices()
    it = PETSc.IntType
    M = PETSc.Mat().createAIJ(size=A.shape, csr=(A.indptr.astype(it), A.indices.astype(it), A.data),
                              comm=PETSc.COMM_WORLD)
    M.assemble()
    return M


def _inprocess_ps(prob) -> list:
    """The same hierarchy on one process: P0 located globally, restricted to the supported coarse nodes."""
    from solvers.locate import clean_weights, locate_in_tets

    V1, T1 = prob["coarse_mesh"]
    loc = locate_in_tets(prob["xyz"], V1, T1)
    W = clean_weights(loc.weights)
    n0 = len(prob["xyz"])
    P0 = sp.csr_matrix((W.ravel(), (np.repeat(np.arange(n0), 4), loc.cols.ravel())), shape=(n0, len(V1)))
    return restrict_prolongations([P0] + list(prob["coarse_Ps"]), np.arange(n0))[0]


def _sgs():
    return ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})


def test_one_rank_is_the_inprocess_solver(prob):
    """Same hierarchy, same cycle: the residual histories agree cycle by cycle, the solutions to 1e-10."""
    A = _petsc_mat(prob["A"])
    with PetscMultigrid.from_distributed(A, prob["xyz"], prob["coarse_mesh"], prob["coarse_Ps"],
                                         krylov="richardson") as mg:
        x, info = mg.solve(prob["b"], tol=1e-8, maxiter=100)
        location, sizes = mg.location, [L["n"] for L in mg.levels]
    A.destroy()
    Ps = _inprocess_ps(prob)
    n0 = len(prob["xyz"])
    ml = MultigridSolver(prob["A"], Ps, presmoother=_sgs(), postsmoother=_sgs())
    xr, ref = ml.solve(prob["b"], tol=1e-8, maxiter=100, return_info=True)
    assert location["n_outside"] == 0 and location["coarse_sizes"] == [P.shape[1] for P in Ps]
    assert sizes == [n0] + [P.shape[1] for P in Ps]
    assert info["iterations"] == ref["iterations"] <= 12
    np.testing.assert_allclose(info["residuals"], ref["residuals"], rtol=1e-6, atol=1e-14)
    assert np.linalg.norm(x - xr) <= 1e-10 * np.linalg.norm(xr)
    # and the solve is a solve
    assert np.linalg.norm(prob["A"] @ x - prob["b"]) <= 1e-8 * np.linalg.norm(prob["b"])


def test_file_is_the_arrays(prob, tmp_path):
    """Coarse levels streamed from a save_coarse_levels file: the same solver as from the arrays."""
    from solvers.petsc import CoarseLevels, save_coarse_levels

    path = tmp_path / "coarse.npz"
    save_coarse_levels(path, *prob["coarse_mesh"], prob["coarse_Ps"])
    A = _petsc_mat(prob["A"])
    out = []
    for coarse, Ps in ((prob["coarse_mesh"], prob["coarse_Ps"]), (path, ()),
                       (CoarseLevels.from_file(path), ())):
        with PetscMultigrid.from_distributed(A, prob["xyz"], coarse, Ps, krylov="richardson") as mg:
            x, info = mg.solve(prob["b"], tol=1e-8, maxiter=100)
            out.append((x, info["residuals"], dict(mg.location)))
    with pytest.raises(SolverInputError, match="coarse_Ps must be empty"):
        PetscMultigrid.from_distributed(A, prob["xyz"], path, prob["coarse_Ps"])
    A.destroy()
    for x, res, loc in out[1:]:
        assert res == out[0][1] and np.array_equal(x, out[0][0])
        assert loc["crop_tets"] == len(prob["coarse_mesh"][1])  # one rank: the whole mesh
        assert loc["coarse_sizes"] == out[0][2]["coarse_sizes"]


def test_outside_node_is_refused(prob):
    A = _petsc_mat(prob["A"])
    pts = prob["xyz"].copy()
    pts[5] = [1.5, 0.5, 0.5]  # 0.5 outside the unit cube
    try:
        with pytest.raises(OutsideCoarseMeshError, match="1 fine nodes lie outside") as err:
            PetscMultigrid.from_distributed(A, pts, prob["coarse_mesh"], prob["coarse_Ps"])
        assert err.value.n_outside == 1 and abs(err.value.max_distance - 0.5) < 1e-12
    finally:
        A.destroy()


@pytest.mark.parametrize("case,match", [
    ("count", "one finite"), ("nan", "one finite"), ("mesh", "pair"), ("Ps", "coarse_Ps"),
    ("partition", "partition"),
])
def test_bad_input(prob, case, match):
    A = _petsc_mat(prob["A"])
    args = [prob["xyz"], prob["coarse_mesh"], prob["coarse_Ps"]]
    kw = {}
    if case == "count":
        args[0] = prob["xyz"][:-1]
    elif case == "nan":
        args[0] = prob["xyz"].copy()
        args[0][0, 0] = np.nan
    elif case == "mesh":
        args[1] = prob["coarse_mesh"][0]
    elif case == "Ps":
        args[2] = [prob["coarse_Ps"][0].T]
    else:
        kw["partition"] = "natural"
    try:
        with pytest.raises(SolverInputError, match=match):
            PetscMultigrid.from_distributed(A, *args, **kw)
    finally:
        A.destroy()
    with pytest.raises(SolverInputError, match="PETSc.Mat"):
        PetscMultigrid.from_distributed(prob["A"], *args)


def test_solve_checks_the_local_vector(prob):
    A = _petsc_mat(prob["A"])
    with PetscMultigrid.from_distributed(A, prob["xyz"], prob["coarse_mesh"], prob["coarse_Ps"]) as mg:
        with pytest.raises(SolverInputError, match="shape"):
            mg.solve(prob["b"][:-1])
        assert np.array_equal(mg.local_rows(), np.arange(len(prob["b"])))
        assert "caller's" in repr(mg)
    A.destroy()


def test_broadcast_arrays_keeps_dtypes_and_shapes():
    from petsc4py import PETSc

    src = {"V": np.arange(12.0).reshape(4, 3), "T": np.arange(8, dtype=np.int32).reshape(2, 4),
           "flag": np.array(True), "empty": np.zeros((0, 3))}
    out = broadcast_arrays(PETSc.COMM_WORLD, src)
    for k, v in src.items():
        assert out[k].dtype == v.dtype and out[k].shape == v.shape and np.array_equal(out[k], v)


# --------------------------------------------------------------------------------------------- mpirun
def _mpirun() -> str | None:
    return shutil.which("mpirun") or shutil.which("mpiexec")


def _env() -> dict:
    return dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                OMPI_MCA_rmaps_base_oversubscribe="1", OMP_NUM_THREADS="1",
                PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


@pytest.mark.mpi
@pytest.mark.skipif(_mpirun() is None, reason="no mpirun/mpiexec on PATH (apt-get install openmpi-bin)")
def test_two_ranks_uneven_rows(tmp_path, prob):
    """2 ranks, 1/3 and 2/3 of the rows: each builds its own rows of P0; same answer as in-process."""
    cmd = [_mpirun(), "-n", "2", sys.executable, str(HERE / "mpi_petsc_distributed_check.py"),
           "--n", str(N), "--levels", str(LEVELS), "--out", str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=600)
    assert proc.returncode == 0, f"mpirun failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    recs = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    x = np.concatenate([np.load(tmp_path / f"rank{r}.npy") for r in range(2)])
    n = prob["A"].shape[0]
    assert recs[0]["rows_per_rank"] == [int(round(n / 3)), n - int(round(n / 3))]
    ml = MultigridSolver(prob["A"], _inprocess_ps(prob), presmoother=_sgs(), postsmoother=_sgs())
    xr, ref = ml.solve(prob["b"], tol=1e-8, accel="cg", return_info=True)
    for rec in recs:
        assert rec["converged"] and rec["location"]["n_outside"] == 0
        # processor-local SOR (block Jacobi across ranks): equal or one more CG iteration
        assert ref["iterations"] <= rec["iterations"] <= ref["iterations"] + 1
        # the certification failure of rank 1's one point is raised on both ranks
        err = rec["error"]
        assert err is not None and err["n_outside"] == 1 and "rank 1: 1" in err["message"]
    assert np.linalg.norm(x - xr) <= 1e-6 * np.linalg.norm(xr)
    assert np.linalg.norm(prob["A"] @ x - prob["b"]) <= 1e-8 * np.linalg.norm(prob["b"])
    # coarse levels streamed from a file: each rank a strict crop of the 1296 coarse tets, the same answer
    xf = np.concatenate([np.load(tmp_path / f"rank{r}_file.npy") for r in range(2)])
    t1 = len(prob["coarse_mesh"][1])
    for rec in recs:
        loc, ref_loc = rec["file_location"], rec["location"]
        assert rec["file_iterations"] == rec["iterations"] and loc["coarse_sizes"] == ref_loc["coarse_sizes"]
        assert 0 < loc["crop_tets"] < t1 and loc["crop_tets"] == ref_loc["crop_tets"]
    assert sum(r["file_location"]["crop_tets"] for r in recs) < 1.4 * t1  # 2 * t1 without cropping
    assert sum(r["file_location"]["coarse_rows"][0] for r in recs) == ref_loc["coarse_sizes"][0]
    assert np.linalg.norm(xf - x) <= 1e-12 * np.linalg.norm(x)


@pytest.mark.mpi
@pytest.mark.slow
@pytest.mark.skipif(_mpirun() is None, reason="no mpirun/mpiexec on PATH (apt-get install openmpi-bin)")
def test_driver_two_ranks(tmp_path):
    """docs/examples/petsc_distributed.py under mpirun -n 2: DMPlex partition, refinement, assembly, solve."""
    cmd = [_mpirun(), "-n", "2", sys.executable, str(ROOT / "docs" / "examples" / "petsc_distributed.py"),
           "--refine", "1", "--out", str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, f"mpirun failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-4000:]}"
    m = re.search(r"(\d+) fine tets on 2 ranks: (\d+) CG iterations, "
                  r"relative residual (\S+), n_outside (\d+)", proc.stdout)
    assert m, proc.stdout[-3000:]
    tets, its, res, outside = int(m[1]), int(m[2]), float(m[3]), int(m[4])
    assert tets > 10000 and outside == 0 and res <= 1e-8 and its <= 12
    parts = [np.load(tmp_path / f"rank{r}.npz") for r in range(2)]
    assert all(len(p["x"]) > 0.2 * sum(len(q["x"]) for q in parts) for p in parts)  # both ranks hold a share
    assert all(np.all(p["x"] > 0) for p in parts)  # -Δu = f > 0, u = 0 on the boundary: u > 0 inside


def test_neumann_nullspace_one_rank():
    """Pure Neumann: constant null space, zero-mean answer, the in-process histories; bad b refused."""
    from solvers.errors import IncompatibleRHSError
    from solvers.gallery import kuhn_cube_hierarchy

    neu = _check._load_base().neumann_problem(N, LEVELS)
    meshes, Ps = kuhn_cube_hierarchy(N, LEVELS)
    prob = {"xyz": meshes[0][0], "coarse_mesh": meshes[1], "coarse_Ps": Ps[1:]}
    A = _petsc_mat(neu["A"])
    with PetscMultigrid.from_distributed(A, prob["xyz"], prob["coarse_mesh"], prob["coarse_Ps"],
                                         nullspace="constant", krylov="richardson") as mg:
        x, info = mg.solve(neu["b"], tol=1e-8, maxiter=100)
        with pytest.raises(IncompatibleRHSError, match="over all ranks"):
            mg.solve(neu["b"] + 1.0)
        xp, _ = mg.solve(neu["b"] + 1.0, project=True)
    A.destroy()
    ml = MultigridSolver(neu["A"], _inprocess_ps(prob), presmoother=_sgs(), postsmoother=_sgs(),
                         nullspace="constant")
    xr, ref = ml.solve(neu["b"], tol=1e-8, maxiter=100, return_info=True)
    assert info["iterations"] == ref["iterations"] <= 30
    np.testing.assert_allclose(info["residuals"], ref["residuals"], rtol=1e-6, atol=1e-14)
    assert abs(x.mean()) < 1e-12 and np.linalg.norm(x - xr) <= 1e-9 * np.linalg.norm(xr)
    assert np.linalg.norm(xp - x) <= 1e-6 * np.linalg.norm(x)  # b + 1 projected is b
