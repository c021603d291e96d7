"""Issue 14: sizing decided first, one cage path in the user's frame, stage lines in logs."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import igl
import numpy as np
import pytest

from nestmg import SizingOptions, shapes
from nestmg.sizing import (
    SizingError,
    edge_length_for_tets,
    enclosed_volume,
    expected_tets,
    plan_hierarchy,
)


@pytest.fixture(scope="module")
def ball():
    return shapes.sphere(res=16)


def test_enclosed_volume_and_inverse_sizing(ball):
    V, F = ball
    r = np.linalg.norm(V, axis=1).mean()
    assert enclosed_volume(V, F) == pytest.approx(4 / 3 * np.pi * r**3, rel=0.03)
    h = edge_length_for_tets(V, F, 200_000, "tetwild")
    assert expected_tets(enclosed_volume(V, F), h, "tetwild") == pytest.approx(200_000, abs=1)
    # 8x the tets at half the edge
    assert edge_length_for_tets(V, F, 1_600_000, "tetwild") == pytest.approx(h / 2, rel=1e-9)


def test_plan_follows_budget(ball):
    V, F = ball
    big = V * 1000.0 + 7.0  # the rule is scale-free: the plan scales with the input
    p = plan_hierarchy(V, F, 3, max_tets=50_000)
    q = plan_hierarchy(big, F, 3, max_tets=50_000)
    assert q.edge_length == pytest.approx(1000.0 * p.edge_length, rel=1e-9)
    assert p.rule in ("max_tets", "input resolution")
    assert p.expected_tets[0] <= 50_000 * 1.001
    assert p.edge_lengths == pytest.approx([p.edge_length * 2**k for k in range(3)])
    # a tighter cap gives a coarser mesh; a time budget can only make it coarser still
    p2 = plan_hierarchy(V, F, 3, max_tets=5_000)
    assert p2.rule == "max_tets" and p2.edge_length > p.edge_length
    p3 = plan_hierarchy(V, F, 3, max_tets=5_000, mesh_time_budget=1e-3 + 1e-3 * len(F))
    assert p3.edge_length >= p2.edge_length
    # the user's explicit edge wins, unless it breaks an explicit cap: then the message names both options
    assert plan_hierarchy(V, F, 2, edge_length=0.05).rule == "user"
    with pytest.raises(SizingError, match=r"--edge-length .*--max-tets"):
        plan_hierarchy(V, F, 2, edge_length=0.002, max_tets=10_000)


def test_impossible_request_refused_before_any_cage(ball, monkeypatch, capsys, tmp_path):
    """The early refusal happens in milliseconds, before the cage backend is ever called."""
    import cagegen
    from nestmg import build_hierarchy
    from nestmg.cli import main
    from nestmg.memory import TetMeshMemoryError

    def no_cages(*a, **k):  # pragma: no cover - reaching it is the failure
        raise AssertionError("a cage was built before the sizing check")

    monkeypatch.setattr(cagegen, "build_cages", no_cages)
    V, F = ball
    t0 = time.perf_counter()
    with pytest.raises(TetMeshMemoryError, match="--edge-length"):
        build_hierarchy(V, F, levels=3, sizing=SizingOptions(edge_length=1e-3), cache=False,
                        progress=False)  # ~1e9 tets
    with pytest.raises(SizingError, match="--max-tets"):
        build_hierarchy(V, F, levels=3, sizing=SizingOptions(edge_length=0.01, max_tets=1000), cache=False,
                        progress=False)
    assert time.perf_counter() - t0 < 2.0
    rc = main(["solve", "shape:sphere", "--edge-length", "0.0005", "--no-cache", "--quiet",
               "--json", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "--edge-length" in err
    assert not (tmp_path / "r.json").exists()


def _winding(Vc, Fc, P):
    return igl.fast_winding_number(np.asarray(Vc, float), np.asarray(Fc, np.int64), np.asarray(P, float))


def test_cages_written_in_the_input_frame_contain_it(tmp_path):
    """`nestmg cages` on a mesh scaled by 1000 and shifted: the written layers contain the mesh as given."""
    from nestmg.cli import main
    from nestmg.io import load_mesh, save_mesh

    V, F = shapes.sphere(res=12)
    V = V * 1000.0 + np.array([5e3, -2e3, 1e4])
    src = tmp_path / "big.obj"
    save_mesh(src, V, F)
    rc = main(["cages", str(src), "--method", "nested", "--levels", "2", "--face-counts", "120",
               "--out", str(tmp_path / "out"), "--quiet", "--no-cache"])
    assert rc == 0
    V0, F0 = load_mesh(tmp_path / "out" / "layer_0.obj")
    V1, F1 = load_mesh(tmp_path / "out" / "layer_1.obj")
    Vin, _ = load_mesh(src)
    assert np.allclose(V0, Vin) and np.array_equal(F0, F)
    w = _winding(V1, F1, Vin)
    assert w.min() > 0.999  # every input vertex inside the written cage
    # the clearance of `solve` (2.5 x TetWild's epsilon of the diagonal) is kept, in user units
    diag = np.linalg.norm(Vin.max(0) - Vin.min(0))
    d2, _, _ = igl.point_mesh_squared_distance(Vin, V1, F1)
    assert np.sqrt(d2.min()) >= 2.5e-3 * diag * 0.99
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["frame"]["scale"] == pytest.approx(diag)
    from cagegen import verify_nesting

    assert verify_nesting([(Vin, F), (V1, F1)]).ok


def test_hierarchy_gives_both_frames():
    from nestmg import build_hierarchy

    V, F = shapes.sphere(res=12)
    Vu = 50.0 * V + 3.0
    h = build_hierarchy(Vu, F, 2, "decimate", sizing=SizingOptions(face_counts=[100], max_tets=4000),
                        cache=False,
                        progress=False)
    assert h.surfaces[0][0] is Vu or np.array_equal(h.surfaces[0][0], Vu)
    Vt, _ = h.tets[0]
    # tets in the user's frame enclose the user's surface (TetWild's boundary within epsilon of it)
    assert np.allclose(Vt.min(0), Vu.min(0), atol=2e-3 * 50 * np.sqrt(3) * 2)
    Vn = h.tets_in("normalized")[0][0]
    assert np.linalg.norm(Vn.max(0) - Vn.min(0)) == pytest.approx(1.0, abs=5e-3)
    assert np.allclose(h.to_user(Vn), Vt)
    assert h.to_dict()["frame"]["scale"] == pytest.approx(np.linalg.norm(Vu.max(0) - Vu.min(0)))
    assert h.options["plan"]["expected_tets"][0] <= 4000 * 1.001
    assert len(h.tets[0][1]) < 3 * 4000  # the cap holds for the real mesh too (TetWild ratio ~1.1)


def test_non_terminal_run_prints_stage_lines(tmp_path):
    """A run whose output is a pipe prints one line per stage as it goes (not a silent wait)."""
    p = subprocess.run(
        [sys.executable, "-m", "nestmg.cli", "solve", "shape:sphere", "--method", "decimate", "--levels", "2",
         "--face-counts", "200", "--max-tets", "3000", "--no-cache", "--json", str(tmp_path / "r.json")],
        check=False, capture_output=True, text=True, timeout=600,
    )
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("[nestmg]")]
    text = "\n".join(lines)
    for stage in ("sizing:", "cages (decimate)", "tets level 0:", "tets level 1:", "prolongation 0<-1", "hierarchy:"):
        assert stage in text, text
    assert all(" s  " in ln for ln in lines)  # elapsed seconds on every line
    # one clock for the whole run, the cage backend's own lines included
    seconds = [float(ln.split()[1]) for ln in lines]
    assert seconds == sorted(seconds), text
    assert sum("cages (decimate): " in ln for ln in lines) >= 2, text  # the backend's lines, not only the summary


def test_non_terminal_cages_run_reports_each_layer(tmp_path):
    """`nestmg cages` in a log says which cage layer it is on while it works, not only at the end."""
    p = subprocess.run(
        [sys.executable, "-m", "nestmg.cli", "cages", "shape:sphere", "--method", "nested", "--levels", "3",
         "--face-counts", "400", "100", "--no-cache", "--out", str(tmp_path / "out")],
        check=False, capture_output=True, text=True, timeout=600,
    )
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("[nestmg]") and "cages (nested): " in ln]
    text = "\n".join(lines)
    assert "layer 1: target 400 faces" in text and "layer 2: target 100 faces" in text, p.stderr
    assert text.index("layer 1:") < text.index("layer 2:")
    assert all(" s  " in ln for ln in lines)


def test_input_much_finer_than_the_tets_is_decimated_first():
    """A fine input meshed coarsely is QEM-decimated within TetWild's envelope before meshing."""
    from nestmg import build_hierarchy

    V, F = shapes.sphere(res=48)
    h = build_hierarchy(V, F, 2, "decimate", sizing=SizingOptions(face_counts=[300], max_tets=20000),
                        cache=False,
                        progress=False)
    pre = h.cage_info["predecimation"]
    assert pre["faces_out"] < 0.5 * pre["faces_in"]
    diag = np.linalg.norm(V.max(0) - V.min(0))
    assert pre["hausdorff"] <= 1e-3 + 1e-12  # normalised units (the envelope is 1e-3 of the diagonal)
    Vs, Fs = h.surfaces[0]
    assert len(Fs) == pre["faces_out"]
    d2, _, _ = igl.point_mesh_squared_distance(Vs, V, F)
    assert np.sqrt(d2.max()) <= 1e-3 * diag * 1.01
    # the fine tets still follow the input within TetWild's envelope plus the decimation error
    Vt, T = h.tets[0]
    from solvers.fem import boundary_faces

    bn = np.unique(boundary_faces(T)[0])
    d2, _, _ = igl.point_mesh_squared_distance(Vt[bn], V, F)
    assert np.sqrt(d2.max()) <= 2.1e-3 * diag
    assert h.timings["epsilon"][0] == 1e-3  # a decimation within the envelope keeps it


def test_noisy_input_gets_the_envelope_of_its_predecimation():
    """A noisy scan's predecimation errs more than TetWild's envelope: the input's level is meshed with that
    error as its envelope (capped at 2 epsilon: not held to follow the kept noise), the cages keep their
    clearance of 2.5 epsilon and the hierarchy is certified at the tet level."""
    from nestmg import build_hierarchy
    from solvers.fem import boundary_faces

    V, F = shapes.sphere(res=48)
    V = V * (1 + 0.004 * np.random.default_rng(0).uniform(-1, 1, (len(V), 1)))  # radial noise, 0.4%
    h = build_hierarchy(V, F, 2, "nested", sizing=SizingOptions(face_counts=[300], max_tets=20000),
                        cache=False, progress=False)
    pre = h.cage_info["predecimation"]
    err = pre["hausdorff"]
    assert pre["faces_out"] < 0.2 * pre["faces_in"] and 2e-3 < err < 4e-3
    assert h.timings["epsilon"] == [2e-3, 1e-3]  # the input's level (capped at 2 epsilon), then the cage's
    assert h.options["cages"]["min_gap"] == 2.5e-3
    assert h.certified and h.n_outside == [0]
    diag = np.linalg.norm(V.max(0) - V.min(0))
    Vt, T = h.tets[0]
    bn = np.unique(boundary_faces(T)[0])
    d2, _, _ = igl.point_mesh_squared_distance(Vt[bn], V, F)
    assert np.sqrt(d2.max()) <= (err + 2e-3) * 1.02 * diag  # the decimation's error plus the envelope


def test_fine_envelope_rule():
    """The envelope of a predecimated input's levels: its Hausdorff error within [epsilon, 2 epsilon]."""
    from nestmg import MeshingOptions
    from nestmg.hierarchy import fine_envelope

    m = MeshingOptions()
    decimated = {"faces_in": 1000, "faces_out": 200, "hausdorff": 1.5e-3}
    assert fine_envelope(m, decimated) == 1.5e-3
    assert fine_envelope(m, dict(decimated, hausdorff=5e-3)) == 2 * m.epsilon
    assert fine_envelope(m, dict(decimated, hausdorff=2e-4)) == m.epsilon
    assert fine_envelope(m, dict(decimated, faces_out=1000)) == m.epsilon  # meshed as it is
    assert fine_envelope(MeshingOptions(mesher="tetgen"), decimated) == m.epsilon
