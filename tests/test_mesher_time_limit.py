"""The external tet meshers run under a time limit (issue 27, item 0).

TetGen's mesh improvement looped forever on one input of the fuzz suite, which hung CI. Both meshers now
run in a worker process that is killed when a call runs past its limit; the error names the limit and
how to raise it, and the next call starts a fresh worker.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from nestmg import shapes
from nestmg.tetmesh import TIME_LIMIT_ENV, TetMeshError, TetMeshTimeoutError, mesh_time_limit, tetrahedralize


@pytest.mark.parametrize("mesher", ["tetgen", "tetwild"])
def test_a_mesher_past_its_limit_is_stopped_with_a_clear_error(mesher):
    if mesher == "tetgen":
        pytest.importorskip("tetgen")
    V, F = shapes.torus(24)
    # far more tets than 0.2 s allows (TetGen: ~1M tets, seconds; TetWild: tens of seconds)
    h = 0.006 if mesher == "tetgen" else 0.01
    t = time.perf_counter()
    with pytest.raises(TetMeshTimeoutError) as exc:
        tetrahedralize(V, F, mesher=mesher, edge_length=h, time_limit=0.2)
    elapsed = time.perf_counter() - t
    assert elapsed < 10.0, elapsed  # killed, not waited for
    msg = str(exc.value)
    assert mesher in msg and TIME_LIMIT_ENV in msg and "time_limit" in msg
    assert isinstance(exc.value, TetMeshError)
    # the killed worker is replaced: the next call meshes normally
    Vt, T = tetrahedralize(V, F, mesher=mesher, edge_length=0.08, time_limit=120)
    assert len(T) > 100 and np.isfinite(Vt).all()


def test_in_process_and_worker_give_the_same_tetgen_mesh():
    pytest.importorskip("tetgen")
    V, F = shapes.sphere(12)
    a = tetrahedralize(V, F, mesher="tetgen", edge_length=0.1, time_limit=None)
    b = tetrahedralize(V, F, mesher="tetgen", edge_length=0.1, time_limit=60)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[0], b[0])


def test_time_limit_from_the_environment(monkeypatch):
    V, F = shapes.sphere(8)
    monkeypatch.setenv(TIME_LIMIT_ENV, "none")
    assert mesh_time_limit(V, F, 0.05) is None
    monkeypatch.setenv(TIME_LIMIT_ENV, "42")
    assert mesh_time_limit(V, F, 0.05) == 42.0
    monkeypatch.setenv(TIME_LIMIT_ENV, "-3")
    with pytest.raises(ValueError, match=TIME_LIMIT_ENV):
        mesh_time_limit(V, F, 0.05)
    monkeypatch.delenv(TIME_LIMIT_ENV)
    assert mesh_time_limit(V, F, 0.05, "tetgen") >= 60.0  # the floors of the automatic limit
    assert mesh_time_limit(V, F, 0.05, "tetwild") >= 900.0


def test_a_cpu_budget_stops_the_worker_and_ignores_idle_seconds():
    """TetGen's modes are switched on CPU seconds, not wall seconds (a wall-clock share made the mesh
    depend on the machine's load): a busy job past its budget is stopped with the budget in the message,
    and the worker's idle wall time counts for nothing."""
    pytest.importorskip("tetgen")
    import os
    import signal

    from nestmg import tetmesh

    V, F = shapes.torus(24)
    d = float(np.linalg.norm(np.ptp(V, axis=0)))

    def opts(h):  # TetGen's options for edge length h x the diagonal
        return {"quality": True, "minratio": 1.5, "fixedvolume": True, "maxvolume": (h * d) ** 3 / (6 * np.sqrt(2)),
                "steinerleft": -1}

    t = time.perf_counter()
    with pytest.raises(TetMeshTimeoutError, match="CPU budget 0.3 s"):
        tetmesh._mesher_call("tetgen", V, F, opts(0.006), time.monotonic() + 120, cpu_budget=0.3)
    assert time.perf_counter() - t < 10.0
    # a small job while the worker is stopped for 1.5 s: 1.5 wall seconds, no CPU: within a 1 s budget
    small = opts(0.1)
    tetmesh._mesher_call("tetgen", V, F, small, time.monotonic() + 120)  # a fresh worker, warmed up
    pid = tetmesh._worker.proc.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        timer = __import__("threading").Timer(1.5, os.kill, (pid, signal.SIGCONT))
        timer.start()
        t = time.perf_counter()
        Vt, T = tetmesh._mesher_call("tetgen", V, F, small, time.monotonic() + 120, cpu_budget=1.0)
        assert time.perf_counter() - t >= 1.4 and len(T) > 100
    finally:
        timer.join()
        os.kill(pid, signal.SIGCONT)
    assert tetmesh._cpu_seconds(os.getpid()) > 0.0
