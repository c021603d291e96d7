"""Quiet, clean exits (issue 27, item 6): third-party messages go to loggers, scripts exit with code 0.

ipctk prints its spdlog warnings on the C-level stdout ("Small gap ... Additive CCD can lead to missed
collisions"): :mod:`cagegen._log` routes them to the ``cagegen.ipctk`` logger. VTK prints through
vtkLogger on stderr ("bad X server connection" of an off-screen render window): :mod:`nestmg.render`
routes it to ``nestmg.vtk``. The PETSc exits are tested in ``tests/test_petsc.py``.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent

# A cage tetrahedron whose lowest vertex sits 1e-15 above a fine triangle, moving down: ipctk's additive
# CCD warns "Small gap 1e-16 <= eps in Additive CCD can lead to missed collisions" (measured).
_NEAR_TOUCH = """
import numpy as np
Vc = np.array([[0.2, 0.2, 1e-15], [1.0, 0.2, 1.0], [0.2, 1.0, 1.0], [1.0, 1.0, 1.5]])
Fc = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
Vf = np.array([[-1.0, -1.0, 0.0], [3.0, -1.0, 0.0], [-1.0, 3.0, 0.0]])
Ff = np.array([[0, 1, 2]])
"""


def _near_touch():
    ns: dict = {}
    exec(_NEAR_TOUCH, ns)
    return ns["Vc"], ns["Fc"], ns["Vf"], ns["Ff"]


def _env() -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env.pop("DISPLAY", None)  # off-screen rendering without a display: VTK's warning case
    return env


def _run(cmd, tmp_path, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, check=False, capture_output=True, text=True, env=_env(), timeout=timeout,
                          cwd=tmp_path)


# --------------------------------------------------------------------------------------------- ipctk
def test_ipctk_warning_goes_to_the_cagegen_logger(capfd, caplog, monkeypatch):
    pytest.importorskip("ipctk")
    import cagegen._log
    from cagegen.collision import PairMesh

    monkeypatch.setattr(cagegen._log, "_seen", set())  # as in a fresh process

    Vc, Fc, Vf, Ff = _near_touch()
    pm = PairMesh(Vc, Fc, Vf, Ff)
    X0 = pm.stack(Vc, Vf)
    X1 = X0.copy()
    X1[:4, 2] -= 0.5
    print("before")
    with caplog.at_level(logging.DEBUG, logger="cagegen.ipctk"):
        alphas = [pm.stepsize(X0, X1) for _ in range(3)]
    print("after")
    out, err = capfd.readouterr()
    assert out == "before\nafter\n" and err == ""  # nothing of ipctk on the terminal, our own prints kept
    assert all(0 <= a < 1e-12 for a in alphas)  # the CCD still stops the motion at the contact
    recs = [r for r in caplog.records if r.name == "cagegen.ipctk" and "Small gap" in r.getMessage()]
    assert len(recs) == 3, [r.getMessage() for r in caplog.records]
    # the first of its kind at ipctk's level (warning), the repeats at DEBUG
    assert [r.levelno for r in recs] == [logging.WARNING, logging.DEBUG, logging.DEBUG]
    assert "[ipctk]" not in recs[0].getMessage() and "\x1b[" not in recs[0].getMessage()


def test_ipctk_outside_a_capture_is_quiet(capfd):
    """A direct ipctk call (no capture window) prints nothing either: ipctk's level is 'error' there."""
    ipctk = pytest.importorskip("ipctk")
    import cagegen.collision  # noqa: F401  (sets the level at import)

    Vc, Fc, Vf, Ff = _near_touch()
    X0 = np.vstack([Vc, Vf])
    X1 = X0.copy()
    X1[:4, 2] -= 0.5
    F = np.vstack([Fc, Ff + 4]).astype(np.int32)
    cm = ipctk.CollisionMesh(X0, ipctk.edges(F), F)
    ipctk.compute_collision_free_stepsize(cm, X0, X1, 0.0, ipctk.LBVH(), ipctk.AdditiveCCD())
    assert capfd.readouterr() == ("", "")


def test_ipctk_capture_off_when_the_logger_is_off(capfd, caplog):
    pytest.importorskip("ipctk")
    from cagegen._log import ipctk_to_log
    from cagegen.collision import PairMesh

    Vc, Fc, Vf, Ff = _near_touch()
    pm = PairMesh(Vc, Fc, Vf, Ff)
    X0 = pm.stack(Vc, Vf)
    X1 = X0.copy()
    X1[:4, 2] -= 0.5
    logging.getLogger("cagegen.ipctk").setLevel(logging.ERROR)
    try:
        with ipctk_to_log():
            print("inside")  # no capture window: stays on stdout
        pm.stepsize(X0, X1)
    finally:
        logging.getLogger("cagegen.ipctk").setLevel(logging.NOTSET)
    assert capfd.readouterr() == ("inside\n", "")
    assert not [r for r in caplog.records if r.name == "cagegen.ipctk"]


_CAGE_SCRIPT = """
import logging, sys
logging.getLogger().addHandler(logging.FileHandler(sys.argv[1]))  # a log file: the terminal stays clean
logging.getLogger().setLevel(logging.DEBUG)
from cagegen import build_cages
from cagegen.collision import PairMesh
from nestmg import shapes
""" + _NEAR_TOUCH + """
pm = PairMesh(Vc, Fc, Vf, Ff)
X0 = pm.stack(Vc, Vf)
X1 = X0.copy()
X1[:4, 2] -= 0.5
pm.stepsize(X0, X1)  # ipctk warns here (without the routing: on stdout)
V, F = shapes.torus(24)
layers = build_cages(V, F, levels=3, method="nested")
print("OK", [len(f) for _, f in layers])
"""


def test_small_nested_cage_script_prints_nothing_of_ipctk(tmp_path):
    """A script that builds nested cages of a procedural torus (and meets ipctk's warning): exit 0,
    stdout is the script's own line, stderr empty, ipctk's warning in the log file."""
    pytest.importorskip("ipctk")
    (tmp_path / "s.py").write_text(_CAGE_SCRIPT)
    proc = _run([sys.executable, "s.py", str(tmp_path / "run.log")], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr == ""
    lines = proc.stdout.splitlines()
    assert len(lines) == 1 and lines[0].startswith("OK ["), proc.stdout
    faces = [int(v) for v in lines[0][4:-1].split(",")]
    assert len(faces) == 3 and faces[0] > faces[1] > faces[2] >= 4
    assert "Small gap" in (tmp_path / "run.log").read_text()


# ----------------------------------------------------------------------------------------------- VTK
def test_vtk_messages_go_to_the_nestmg_logger(capfd, caplog):
    pytest.importorskip("pyvista")
    from vtkmodules.vtkIOImage import vtkPNGReader

    from nestmg.render import third_party_to_log

    with caplog.at_level(logging.DEBUG, logger="nestmg"), third_party_to_log():
        r = vtkPNGReader()
        r.SetFileName("/no/such/file.png")
        r.Update()  # VTK error: "Unable to open file"
    assert capfd.readouterr() == ("", "")
    recs = [rec for rec in caplog.records if rec.name == "nestmg.vtk"]
    assert any(rec.levelno == logging.ERROR and "Unable to open file" in rec.getMessage() for rec in recs), \
        [rec.getMessage() for rec in caplog.records]
    assert all(getattr(rec, "third_party", None) == "VTK" for rec in recs)
    # and VTK's own output is back after the block, as before it
    r2 = vtkPNGReader()
    r2.SetFileName("/no/such/other.png")
    r2.Update()
    assert "Unable to open file /no/such/other.png" in capfd.readouterr().err


def test_render_layers_prints_nothing(tmp_path):
    pytest.importorskip("pyvista")
    script = (
        "from nestmg import shapes\n"
        "from nestmg.render import render_layers\n"
        "V, F = shapes.sphere(10)\n"
        f"render_layers([(V, F), (1.2 * V, F)], {str(tmp_path / 'l.png')!r}, title='t')\n"
    )
    proc = _run([sys.executable, "-c", script], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (proc.stdout, proc.stderr) == ("", "")
    assert (tmp_path / "l.png").stat().st_size > 1000


# ----------------------------------------------------------------------------------------------- CLI
def test_cli_cages_exits_0_without_third_party_lines(tmp_path):
    """``nestmg cages shape:torus ... --png`` (nested cages + a VTK render): exit 0, stdout holds the
    command's two lines, stderr only its ``[nestmg]`` stage lines (stderr is not a terminal here)."""
    pytest.importorskip("ipctk")
    pytest.importorskip("pyvista")
    out = tmp_path / "cages"
    proc = _run([sys.executable, "-m", "nestmg.cli", "cages", "shape:torus", "--levels", "3", "--out",
                 str(out), "--no-cache", "--png"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("torus: 3 layers") and "verifier ok=True" in lines[0], lines
    assert lines[1].startswith("wrote ")
    stray = [ln for ln in proc.stderr.splitlines() if not ln.startswith("[nestmg] ")]
    assert not stray, stray
    assert (out / "layers.png").exists() and (out / "layer_2.obj").exists()


@pytest.mark.parametrize("args,expect", [
    (["--epsilon", "0"], "argument --epsilon: must be > 0"),
    (["--epsilon", "-1"], "argument --epsilon: must be > 0"),
    (["--out", "afile"], "afile: File exists"),
])
def test_cli_misuse_is_one_line(tmp_path, args, expect):
    """Misuses met in issue 27 end in one line on stderr and exit code 2 (TetWild segfaulted on a negative
    envelope and hung on 0; an --out naming a file was a FileExistsError traceback after the work)."""
    (tmp_path / "afile").write_text("x")
    base = ["cages", "shape:sphere", "--levels", "2", "--no-cache", "--quiet"]
    if "--out" not in args:
        base += ["--out", str(tmp_path / "o")]
    proc = _run([sys.executable, "-m", "nestmg.cli", *base, *args], tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert proc.stderr.splitlines() == [proc.stderr.strip()] and expect in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
