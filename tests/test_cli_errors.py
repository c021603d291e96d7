"""Every misuse of the ``nestmg`` command line ends in one error line and a non-zero exit, never a traceback.

Each case runs the real console entry point in a subprocess (``python -m nestmg.cli``) and fails before
any cage or tet mesh is built, so the whole file takes a few seconds per case.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: (arguments, a fragment the error line must contain); ``{tmp}`` is replaced by a temporary folder
CASES = [
    (["solve", "shape:torus", "--levels", "1"], "--levels: must be >= 2"),
    (["demo", "--levels", "1"], "--levels: must be >= 2"),
    (["solve", "shape:torus", "--levels", "-2"], "--levels: must be >= 2"),
    (["solve", "shape:torus", "--levels", "two"], "expected an integer"),
    (["cages", "shape:torus", "--out", "{tmp}/o", "--levels", "0"], "--levels: must be >= 2"),
    (["solve", "{tmp}/missing.obj"], "not found"),
    (["solve", "{tmp}/garbage.obj"], "garbage.obj"),
    (["solve", "{tmp}/garbage.vtu"], "could not read garbage.vtu"),
    (["solve", "{tmp}/empty.stl"], "empty.stl"),
    (["solve", "shape:nosuch"], "unknown built-in shape"),
    (["solve", "shape:torus", "--problem", "heat"], "--problem: invalid choice"),
    (["solve", "shape:torus", "--method", "magic"], "unknown --method"),
    (["compare", "shape:torus", "--methods", "nested", "magic"], "unknown --method"),
    (["solve", "shape:torus", "--cycle", "X"], "--cycle: invalid choice"),
    (["solve", "shape:torus", "--max-tets", "-5"], "--max-tets"),
    (["solve", "shape:torus", "--edge-length", "-0.1"], "argument --edge-length: must be > 0"),
    (["solve", "shape:torus", "--face-counts", "-10", "-20"], "--face-counts"),
    (["solve", "shape:torus", "--epsilon", "0"], "argument --epsilon: must be > 0"),
    (["solve", "shape:torus", "--mesh-time-budget", "-1"], "argument --mesh-time-budget: must be >= 0"),
    (["solve", "shape:torus", "--smoothing", "fast", "--nu", "1"],
     "argument --smoothing: 'fast' is a preset"),
    (["solve", "shape:torus", "--coarsening", "0.5"], "argument --coarsening: must be > 1"),
    (["cages", "shape:torus", "--out", "{tmp}/o", "--method", "sdf", "--cage-time-budget", "-5"],
     "--cage-time-budget: must be >= 0"),
    (["solve", "shape:torus", "--method", "decimate", "--cage-time-budget", "5"],
     "applies to --method nested and sdf only"),
    (["cages", "shape:torus", "--out", "{tmp}/o", "--method", "sdf", "--cage-threads", "1"],
     "--cage-threads applies to --method nested only"),
    (["cages", "shape:torus", "--out", "{tmp}/o", "--cage-threads", "0"], "--cage-threads: must be >= 1"),
    (["solve", "shape:torus", "--tol", "-1"], "--tol: must be > 0"),
    (["solve", "shape:torus", "--tol", "nan"], "--tol: must be > 0"),
    (["solve", "shape:torus", "--maxiter", "0"], "--maxiter: must be >= 1"),
    (["solve", "shape:torus", "--nu", "-1"], "--nu: must be >= 1"),
    (["solve", "shape:torus", "--lam", "-1"], "--lam: must be > 0"),
    (["solve"], "required: mesh"),
    (["frobnicate"], "invalid choice"),
]


def _inputs(tmp: Path) -> None:
    (tmp / "garbage.obj").write_text("this is not a mesh\n")
    (tmp / "garbage.vtu").write_text("<VTKFile> truncated\n")
    (tmp / "empty.stl").write_bytes(b"")


@pytest.mark.parametrize("argv, fragment", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_cli_misuse_is_one_line_and_nonzero(tmp_path, argv, fragment):
    _inputs(tmp_path)
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    env = dict(os.environ, OMP_NUM_THREADS="1", NESTMG_CACHE=str(tmp_path / "cache"))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    p = subprocess.run([sys.executable, "-m", "nestmg.cli", *argv, "--quiet"], capture_output=True, text=True,
                       env=env, cwd=tmp_path, timeout=120)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode != 0, (argv, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr, p.stderr
    # nestmg's own output is the last line, alone (a multi-line message would leave another line last);
    # lines before it may only be a mesh reader's own warnings (libigl prints from C++)
    ours = [ln for ln in lines if ln.startswith("nestmg")]
    assert len(ours) == 1 and lines[-1] == ours[0], f"{argv}: expected one error line, got:\n{p.stderr}"
    assert "error:" in ours[0] and fragment in ours[0], (fragment, ours[0])
    assert all("error" not in ln.lower() for ln in lines[:-1]), p.stderr


def test_python_dash_m_nestmg_is_the_command(tmp_path):
    """``python -m nestmg`` runs the ``nestmg`` command: its help (exit 0), its one-line errors (non-zero)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    ok = subprocess.run([sys.executable, "-m", "nestmg", "solve", "--help"], capture_output=True, text=True,
                        env=env, cwd=tmp_path, timeout=120)
    assert ok.returncode == 0 and "usage: nestmg solve" in ok.stdout, ok.stderr
    bad = subprocess.run([sys.executable, "-m", "nestmg", "solve", str(tmp_path / "missing.obj"), "--quiet"],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr and "missing.obj" in bad.stderr, bad.stderr
