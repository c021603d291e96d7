"""Tests of nestmg.io's surface writer: precision of OBJ/OFF/PLY, atomic writes, no trimesh import."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from nestmg.io import load_mesh, save_mesh


@pytest.fixture
def mesh():
    rng = np.random.default_rng(7)
    V = rng.random((40, 3)) * np.array([1e-7, 3.3, 1e5])  # mixed magnitudes
    F = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 39]], dtype=np.int64)
    return V, F


@pytest.mark.parametrize("ext, rtol", [("obj", 1e-14), ("off", 1e-14), ("ply", 0.0)])
def test_surface_round_trip_keeps_coordinates(tmp_path, mesh, ext, rtol):
    V, F = mesh
    path = tmp_path / f"m.{ext}"
    save_mesh(path, V, F)
    V2, F2 = load_mesh(path)
    assert np.array_equal(F2, F)
    assert np.all(np.abs(V2 - V) <= rtol * np.abs(V))
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file left


def test_saving_an_obj_does_not_import_trimesh(tmp_path):
    code = ("import sys, numpy as np; from nestmg.io import save_mesh; "
            f"save_mesh({str(tmp_path / 'm.obj')!r}, np.eye(3), np.array([[0, 1, 2]])); "
            "sys.exit(int('trimesh' in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], cwd=tmp_path).returncode == 0


def test_written_files_get_a_plain_opens_permissions(tmp_path):
    """Outputs are written through a temporary file (mkstemp: owner-only); the result has 0o666 less the
    umask, as any program's output, so others the umask allows can read the meshes and reports."""
    import os
    import stat

    from nestmg.cache import atomic_write_bytes
    from nestmg.io import save_tet_mesh

    mask = os.umask(0o022)
    try:
        V = np.eye(4, 3)
        save_mesh(tmp_path / "s.obj", V, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]))
        save_mesh(tmp_path / "s.ply", V, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]))
        save_tet_mesh(tmp_path / "t.vtu", V, np.array([[0, 1, 2, 3]]))
        atomic_write_bytes(tmp_path / "r.json", b"{}")
    finally:
        os.umask(mask)
    for name in ("s.obj", "s.ply", "t.vtu", "r.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name
