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
