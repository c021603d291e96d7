"""Shared fixtures: procedural shapes and hierarchies (no files from outside the repository)."""

from __future__ import annotations

import numpy as np
import pytest


def energy_factor(ml, cycles: int = 25) -> float:
    """Asymptotic energy-norm factor of ``ml``'s V-cycle error propagation on ``A x = 0`` from a random
    start (kept at zero mean: valid for Neumann and Dirichlet operators alike), over its last 5 cycles."""
    A = ml.levels[0].A
    e = np.random.default_rng(1).standard_normal(A.shape[0])
    norms = []
    for _ in range(cycles):
        e -= e.mean()
        ml._cycle(0, e, np.zeros_like(e), "V")
        e -= e.mean()
        norms.append(np.sqrt(e @ (A @ e)))
    return (norms[-1] / norms[-6]) ** 0.2


def blas_threads() -> list[int]:
    """Thread limits of the loaded BLAS libraries (threadpoolctl); the test skips when none is reported."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    counts = [p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"]
    if not counts:
        pytest.skip("no BLAS library reported by threadpoolctl")
    return counts


def record_blas_threads(monkeypatch, owner, name: str) -> list[int]:
    """Wrap ``owner.name`` so that every call appends the BLAS thread limits it runs with to the returned
    list (skips, as :func:`blas_threads`, without a reported BLAS library)."""
    blas_threads()
    seen: list[int] = []
    real = getattr(owner, name)

    def spy(*args, **kwargs):
        seen.extend(blas_threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, spy)
    return seen


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """Every test session writes its cache entries into a temporary folder."""
    monkeypatch.setenv("NESTMG_CACHE", str(tmp_path_factory.getbasetemp() / "nestmg-cache"))


@pytest.fixture
def rng():
    """A fresh generator per test: a shared one would make each test's draws depend on which tests ran
    before it in the same (xdist) worker."""
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def torus_iso_tets():
    """A procedurally nested 4-level torus hierarchy (iso-surfaces at growing offsets), meshed by TetGen."""
    pytest.importorskip("tetgen")
    from nestmg import MeshingOptions, SizingOptions, shapes
    from nestmg.hierarchy import tet_hierarchy

    # default sizing (fine edge = the input's mean edge, doubling per level): 77k / 14k / 3k / 1.8k tets
    S = shapes.nested_isosurfaces("torus", [0.0, 0.06, 0.15, 0.35], [32, 20, 12, 8])
    tets, P, reps, _ = tet_hierarchy(S, sizing=SizingOptions(coarsening=None),
                                     meshing=MeshingOptions(mesher="tetgen"),
                                     cache=False, progress=False)
    return S, tets, P, reps


@pytest.fixture
def one_ipctk_thread():
    """ipctk on one thread: its parallel reductions (barrier gradients, potentials) sum in a different
    order run to run, and the re-inflation's Newton iterations amplify those last bits (1e-10 on a
    skeleton cage), or a small CAD plate's second layer then sometimes needs the fallback (minutes)."""
    from cagegen.collision import ipctk_threads

    with ipctk_threads(1):
        yield


@pytest.fixture
def failing_flow():
    """A stand-in for ``cagegen.nested.flow.flow_inside`` that always fails: forces the recovery and
    fallback paths (a flow capped at 0 iterations succeeds when Ĉ, decimated from the envelope,
    already contains the fine surface)."""
    from cagegen.nested.flow import FlowResult

    def fail(Vf, *args, **kwargs):
        return FlowResult([np.array(Vf, dtype=float)], False, 0, "forced failure (test)", 1.0)

    return fail
