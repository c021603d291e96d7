"""Trust across the pipeline: cache reuse is bitwise, solver failures are named, bad data is refused.

(Fuzzing of the inputs is in ``test_fuzz.py``; memory limits in ``test_*_memory.py``.)
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from nestmg import MeshingOptions, SizingOptions, SolverOptions
from solvers import DivergenceError, IncompatibleRHSError, MultigridSolver
from solvers.fem import stiffness_matrix


@pytest.fixture(scope="module")
def ball_hierarchy():
    """A 3-level procedurally nested sphere hierarchy (TetGen), ~5k / 3k / 3k tets."""
    pytest.importorskip("tetgen")
    from nestmg import MeshingOptions, SizingOptions, shapes
    from nestmg.hierarchy import tet_hierarchy

    S = shapes.nested_isosurfaces("sphere", [0.0, 0.15, 0.4], [14, 10, 8])
    tets, P, reps, _ = tet_hierarchy(S, sizing=SizingOptions(edge_length=0.08, coarsening=None),
                                     meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    assert [r.n_outside for r in reps] == [0, 0]
    return tets, P


def _same_arrays(h1, h2) -> None:
    for (V1, F1), (V2, F2) in zip(h1.surfaces, h2.surfaces, strict=True):
        assert V1.tobytes() == V2.tobytes() and F1.tobytes() == F2.tobytes()
    for (V1, T1), (V2, T2) in zip(h1.tets, h2.tets, strict=True):
        assert V1.tobytes() == V2.tobytes() and T1.tobytes() == T2.tobytes()
    for P1, P2 in zip(h1.P, h2.P, strict=True):
        assert P1.shape == P2.shape
        for a in ("data", "indices", "indptr"):
            assert getattr(P1, a).tobytes() == getattr(P2, a).tobytes()


def test_rerun_hits_the_cache_and_is_bitwise_identical(tmp_path, monkeypatch):
    pytest.importorskip("tetgen")
    import cagegen
    import nestmg.hierarchy as hier
    from nestmg import build_hierarchy, shapes

    monkeypatch.setenv("NESTMG_CACHE", str(tmp_path / "cache"))
    V, F = shapes.sphere(res=16)
    V0, F0 = V.copy(), F.copy()
    kw = {"levels": 3, "method": "decimate", "sizing": SizingOptions(face_counts=[200, 60]),
          "meshing": MeshingOptions(mesher="tetgen"), "progress": False}
    h1 = build_hierarchy(V, F, **kw)
    entries = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert len(entries) == 2 * 4  # cages + 3 tet layers, .npz + .json each
    assert not any(n.endswith(".tmp") for n in entries)  # atomic writes leave no temp file

    # second run: neither the cage backend nor the mesher may run again
    def forbidden(*a, **k):
        raise AssertionError("cache miss: recomputed")

    monkeypatch.setattr(cagegen, "build_cages", forbidden)
    monkeypatch.setattr(hier, "tetrahedralize", forbidden)
    h2 = build_hierarchy(V, F, **kw)
    assert h2.cage_info.get("cached") is True and "cached" not in h1.cage_info
    _same_arrays(h1, h2)
    assert h2.n_outside == h1.n_outside
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == entries
    np.testing.assert_array_equal(V, V0)
    np.testing.assert_array_equal(F, F0)


def test_rerun_without_cache_is_deterministic(monkeypatch, tmp_path):
    pytest.importorskip("tetgen")
    from nestmg import build_hierarchy, shapes

    V, F = shapes.sphere(res=16)
    kw = {"levels": 3, "method": "decimate", "sizing": SizingOptions(face_counts=[200, 60]),
          "meshing": MeshingOptions(mesher="tetgen"), "progress": False, "cache": False}
    _same_arrays(build_hierarchy(V, F, **kw), build_hierarchy(V, F, **kw))


def test_divergence_is_reported_with_cycle_through_nestmg(ball_hierarchy):
    """Coarse tets shrunk 1000x make the re-discretised coarse correction 1000x too large: divergence."""
    from nestmg.run import solve_on_hierarchy

    tets, P = ball_hierarchy
    red = SolverOptions(coarse="rediscretized")
    ok = solve_on_hierarchy(tets, P, "poisson-dirichlet", red, cost=False)
    assert ok["converged"] and not ok["diverged"]
    bad = [tets[0], tets[1], (tets[2][0] * 1e-3, tets[2][1])]
    # the energy-optimal scaling of re-discretised corrections (issue 15, default "auto") would absorb
    # the 1000x; without it the divergence must be detected and reported
    r = solve_on_hierarchy(bad, P, "poisson-dirichlet", SolverOptions(coarse="rediscretized",
                                                                      coarse_scaling=None),
                           cost=False)
    assert r["diverged"] and not r["converged"]
    assert 1 <= r["iterations"] <= 5
    assert f"V-cycle {r['iterations']} diverges" in r["message"]
    assert r["residuals"][-1] > 1e5 * r["residuals"][0]
    # ... and with the default energy scaling the same wrongly scaled coarse level is harmless
    r2 = solve_on_hierarchy(bad, P, "poisson-dirichlet", red, cost=False)
    assert r2["converged"] and not r2["diverged"]


def test_nan_is_located_by_level_and_cycle_through_nestmg(ball_hierarchy):
    from nestmg.problems import setup_problem

    tets, P = ball_hierarchy
    prob = setup_problem(tets, P, "poisson-neumann", coarse="rediscretized")
    ops = list(prob.coarse)
    ops[-1] = ops[-1] * 1e-160  # a coarsest operator 1e160x too weak: with data ~1e150 its solve overflows
    ml = MultigridSolver(prob.A, prob.P, coarse=ops, nullspace=prob.nullspace)
    with pytest.raises(DivergenceError) as ei, np.errstate(all="ignore"):
        ml.solve(prob.b * 1e150, divtol=np.inf)
    e = ei.value
    assert (e.cycle, e.level) == (1, 2)
    assert "V-cycle 1 produced NaN/inf; first non-finite value on level 2 during coarsest direct solve" in str(e)


def test_overflowing_residual_is_divergence_not_an_unlocated_nan(ball_hierarchy):
    """Regression: a finite iterate whose residual norm overflowed was reported as a NaN on level None
    "(not reproducible)"; it is divergence, and now says so."""
    from nestmg.problems import setup_problem

    tets, P = ball_hierarchy
    bad = [tets[0], tets[1], (tets[2][0] * 1e-30, tets[2][1])]
    prob = setup_problem(bad, P, "poisson-neumann", coarse="rediscretized")
    ml = MultigridSolver(prob.A, prob.P, coarse=prob.coarse, nullspace=prob.nullspace)
    with pytest.raises(DivergenceError, match=r"V-cycle \d+ diverges: the residual norm overflowed") as ei, \
            np.errstate(all="ignore"):
        ml.solve(prob.b, divtol=np.inf, maxiter=60)
    assert ei.value.level is None and ei.value.cycle >= 2


def test_stiffness_is_scale_safe(ball_hierarchy):
    """Regression: libigl's cotangent formula returned NaN/inf for tets of edge ~1e-30 (K scales like
    length in 3D, so it is now assembled on a unit-sized copy)."""
    V, T = ball_hierarchy[0][2]
    K = stiffness_matrix(V, T)
    for s in (1e-30, 1e-8, 1e8, 1e30):
        Ks = stiffness_matrix(V * s + 1e3 * s, T)
        assert np.all(np.isfinite(Ks.data))
        assert abs(Ks / s - K).max() <= 1e-10 * abs(K).max()


def test_incompatible_neumann_data_is_rejected_through_nestmg(ball_hierarchy):
    from nestmg.problems import setup_problem

    tets, P = ball_hierarchy
    n0 = len(tets[0][0])
    f = np.ones(n0) * 3.0 + np.linspace(0, 1, n0)  # mean far from zero
    prob = setup_problem(tets, P, "poisson-neumann", f=f)
    assert abs(prob.b.sum()) <= 1e-12 * np.abs(prob.b).sum()  # setup_problem makes the data compatible
    ml = MultigridSolver(prob.A, prob.P, nullspace=prob.nullspace)
    x = ml.solve(prob.b, tol=1e-8)
    assert np.linalg.norm(prob.b - prob.A @ x) <= 1e-8 * np.linalg.norm(prob.b)
    b_bad = prob.b + 1e-3 * np.abs(prob.b).max()  # net flux: no solution exists
    with pytest.raises(IncompatibleRHSError):
        ml.solve(b_bad)
    x2 = ml.solve(b_bad, project=True, tol=1e-8)  # explicit opt-in projects instead
    assert np.linalg.norm(x2 - x) > 0 and abs(x2.mean()) < 1e-12
    assert sp.issparse(prob.A)


def test_altered_or_truncated_cache_entries_are_rebuilt(tmp_path, monkeypatch):
    """A cache entry is returned only if its arrays hash to what was stored (and verified) when saved."""
    from nestmg.cache import load_entry, save_entry

    monkeypatch.setenv("NESTMG_CACHE", str(tmp_path))
    arrays = {"V0": np.arange(12.0).reshape(4, 3), "F0": np.array([[0, 1, 2], [0, 2, 3]])}
    save_entry("k", arrays, {"certified": True})
    hit = load_entry("k")
    assert hit is not None and hit[1] == {"certified": True}
    for name, a in arrays.items():
        assert hit[0][name].tobytes() == a.tobytes()
    # someone edits the arrays (a valid npz, different content): not returned
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, V0=arrays["V0"] + 1e-9, F0=arrays["F0"])
    (tmp_path / "k.npz").write_bytes(buf.getvalue())
    assert load_entry("k") is None
    # truncated file, garbage JSON: misses, never exceptions
    save_entry("k", arrays, {"certified": True})
    data = (tmp_path / "k.npz").read_bytes()
    (tmp_path / "k.npz").write_bytes(data[: len(data) // 2])
    assert load_entry("k") is None
    save_entry("k", arrays, {"certified": True})
    (tmp_path / "k.json").write_text("[1, 2")
    assert load_entry("k") is None
    (tmp_path / "k.json").write_text("[1, 2]")
    assert load_entry("k") is None


def test_pipeline_rebuilds_an_altered_cage_entry(tmp_path, monkeypatch):
    pytest.importorskip("tetgen")
    import nestmg.hierarchy as hier
    from nestmg import build_hierarchy, shapes

    monkeypatch.setenv("NESTMG_CACHE", str(tmp_path))
    V, F = shapes.sphere(res=16)
    kw = {"levels": 2, "method": "decimate", "sizing": SizingOptions(face_counts=[60]),
          "meshing": MeshingOptions(mesher="tetgen"), "progress": False}
    h1 = build_hierarchy(V, F, **kw)
    # the cage entry (keyed on the normalised input since issue 14): found by its metadata
    keys = [p.stem for p in tmp_path.glob("*.json") if '"audit"' in p.read_text()]  # cages carry the audit
    assert len(keys) == 1
    key = keys[0]
    assert (tmp_path / f"{key}.npz").exists()
    with np.load(tmp_path / f"{key}.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["V1"] = arrays["V1"] * 0.5  # shrink the cage: it would no longer contain the input
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    (tmp_path / f"{key}.npz").write_bytes(buf.getvalue())
    h2 = build_hierarchy(V, F, **kw)
    assert "cached" not in h2.cage_info  # rebuilt, not loaded
    _same_arrays(h1, h2)
    assert hier.load_entry(key) is not None  # and stored again, intact
