"""nestmg.memory: a tet layer that would not fit is refused before meshing, with a clear MemoryError."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh

from cagegen.errors import NestmgError
from nestmg.memory import TetMeshMemoryError, check_tet_memory, estimate_tet_bytes, estimate_tets


@pytest.fixture(scope="module")
def ball():
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices) / np.sqrt(12.0), np.asarray(m.faces)  # radius 0.289, diagonal 1


def test_estimate_bounds_tetgen_count(ball):
    pytest.importorskip("tetgen")
    from nestmg.tetmesh import tetrahedralize

    V, F = ball
    for h in (0.06, 0.04):
        n_est = estimate_tets(V, F, h)
        _, T = tetrahedralize(V, F, mesher="tetgen", edge_length_abs=h)
        assert len(T) <= n_est <= 3 * len(T), (h, len(T), n_est)
    # the count scales like h^-3
    assert estimate_tets(V, F, 0.01) == pytest.approx(8 * estimate_tets(V, F, 0.02), rel=0.01)
    assert estimate_tet_bytes(10**6, "tetwild") > estimate_tet_bytes(10**6, "tetgen") > 6e8
    with pytest.raises(ValueError, match="unknown mesher"):
        estimate_tet_bytes(10, "gmsh")


def test_refused_before_meshing(ball, monkeypatch):
    V, F = ball
    monkeypatch.delenv("NESTMG_MEMORY_LIMIT", raising=False)
    assert check_tet_memory(V, F, 0.05, "tetwild") == estimate_tets(V, F, 0.05)  # fits on this machine
    t0 = time.perf_counter()
    with pytest.raises(TetMeshMemoryError) as ei:
        check_tet_memory(V, F, 1e-5, "tetgen", layer=2)  # ~1e14 tets: no machine has that memory
    assert time.perf_counter() - t0 < 1.0
    e = ei.value
    assert isinstance(e, MemoryError) and isinstance(e, NestmgError)
    assert e.n_tets > 1e13 and e.needed > e.available
    assert "tetgen tet mesh of layer 2" in str(e) and "larger edge length" in str(e)


def test_pipeline_and_cli_refuse_with_artificial_limit(monkeypatch, capsys, tmp_path):
    from nestmg import SizingOptions, build_hierarchy, shapes
    from nestmg.cli import main

    V, F = shapes.sphere(res=16)
    monkeypatch.setenv("NESTMG_MEMORY_LIMIT", "2M")
    t0 = time.perf_counter()
    with pytest.raises(TetMeshMemoryError, match=r"only 2\.0 MB are available \(limit: \$NESTMG_MEMORY_LIMIT\)"):
        build_hierarchy(V, F, 2, "decimate", sizing=SizingOptions(face_counts=[100]), cache=False,
                        progress=False)
    assert time.perf_counter() - t0 < 5.0  # refused up front, TetWild never ran
    rc = main(["solve", "shape:sphere", "--method", "decimate", "--levels", "2", "--no-cache", "--quiet",
               "--json", str(tmp_path / "r.json")])
    assert rc == 2 and "tet mesh" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()
