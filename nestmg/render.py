"""Pictures: cage layers (pyvista, off-screen PNG) and convergence plots (matplotlib PNG).

Third-party messages of the rendering go to loggers, not the terminal: VTK's (e.g. "bad X server
connection" of an off-screen render window without a display) to ``nestmg.vtk``, Python warnings
raised by pyvista / matplotlib while drawing to ``nestmg.render`` (see :func:`third_party_to_log`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from .progress import log_third_party

__all__ = ["plot_convergence", "render_layers", "third_party_to_log"]

vtk_log = logging.getLogger("nestmg.vtk")
warn_log = logging.getLogger("nestmg.render")

# one vtkLogger (loguru) line: "2026-12-02 18:51:26.491 (   0.463s) [    7F12...]  file.cxx:331    ERR| text"
_VTK_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d+ \([^)]*\) \[[^\]]*\]\s*\S+\s+(\w+)\| ?(.*)$")
_VTK_LEVELS = {"FATAL": logging.CRITICAL, "ERR": logging.ERROR, "WARN": logging.WARNING, "INFO": logging.INFO}


def _vtk_records(text: str) -> list[tuple[int, str]]:
    """(level, message) of each vtkLogger record in a log file's text (continuation lines joined)."""
    out: list[tuple[int, str]] = []
    for line in text.splitlines():
        m = _VTK_LINE.match(line)
        if m:
            out.append((_VTK_LEVELS.get(m.group(1), logging.DEBUG), m.group(2).rstrip()))
        elif out and line.strip():
            out[-1] = (out[-1][0], f"{out[-1][1]} / {line.strip()}")
    return [(lvl, msg) for lvl, msg in out if not msg.startswith("Logging to ")]  # loguru's own header


@contextlib.contextmanager
def third_party_to_log() -> Iterator[None]:
    """Route VTK's messages and Python warnings raised inside the block to loggers.

    VTK prints its warnings and errors (``vtkWarningMacro``, ``vtkLogF``) through ``vtkLogger`` on
    stderr. Inside the block vtkLogger's stderr output is off and its records go to a temporary log
    file instead (``vtkLogger.LogToFile``); afterwards each record is logged on ``nestmg.vtk`` at its
    level (WARN -> WARNING, ERR -> ERROR, INFO and verbosity levels -> INFO / DEBUG). The macros also
    reach ``vtkOutputWindow``, which pyvista (at import) points at Python's *root* logger: inside the
    block the output window is a silent ``vtkStringOutputWindow``, so each message is logged once, on
    ``nestmg.vtk``. Python warnings are recorded and logged on ``nestmg.render`` (WARNING). Records
    carry ``third_party`` so the CLI's stage lines leave them out. Everything is restored afterwards.
    """
    try:
        from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow
    except ImportError:  # pragma: no cover - pyvista always brings vtk
        vtkLogger = None
    path = None
    if vtkLogger is not None:
        fd, path = tempfile.mkstemp(prefix="nestmg-vtk-", suffix=".log")
        os.close(fd)
        window = vtkOutputWindow.GetInstance()  # (the python reference keeps it alive)
        vtkOutputWindow.SetInstance(vtkStringOutputWindow())
        stderr_level = vtkLogger.GetCurrentVerbosityCutoff()
        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
        vtkLogger.LogToFile(path, vtkLogger.TRUNCATE, vtkLogger.VERBOSITY_INFO)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    finally:
        if path is not None:
            vtkLogger.EndLogToFile(path)
            vtkLogger.SetStderrVerbosity(stderr_level)
            vtkOutputWindow.SetInstance(window)
            with open(path, encoding="utf-8", errors="replace") as f:
                records = _vtk_records(f.read())
            os.unlink(path)
            for level, msg in records:
                log_third_party(vtk_log, level, "VTK", msg)
        for w in caught:
            log_third_party(warn_log, logging.WARNING, w.category.__name__,
                            f"{w.message} ({Path(w.filename).name}:{w.lineno})")

_COLORS = ["#d9d9d9", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"]


def _write_png(path: Path, save: Callable[[str], None]) -> Path:
    """``save(tmp)`` writes the picture beside ``path``, then one rename puts it in place (never a torn PNG)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    save(str(tmp))
    os.replace(tmp, path)
    return path


def _polydata(V: np.ndarray, F: np.ndarray):
    import pyvista as pv

    faces = np.hstack([np.full((len(F), 1), 3), np.asarray(F)]).astype(np.int64).ravel()
    return pv.PolyData(np.asarray(V, dtype=float), faces)


def render_layers(
    surfaces: list[tuple[np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    *,
    title: str | None = None,
    window_size: tuple[int, int] = (1600, 500),
) -> Path:
    """Render every layer beside the input (one panel per cage) to a PNG, off-screen.

    Parameters
    ----------
    surfaces : list of (V, F)
        Layers, finest (the input) first.
    path : str or PathLike
        Output PNG.
    title : str, optional
        Text in the first panel.
    window_size : (int, int)
        Pixels.

    Returns
    -------
    Path
        The written file.
    """
    with third_party_to_log():
        return _render_layers(surfaces, Path(path), title, window_size)


def _render_layers(surfaces, path: Path, title, window_size) -> Path:
    import pyvista as pv

    pv.OFF_SCREEN = True
    n = max(1, len(surfaces) - 1)
    pl = pv.Plotter(off_screen=True, shape=(1, n), window_size=window_size, border=False)
    base = _polydata(*surfaces[0])
    for j in range(n):
        pl.subplot(0, j)
        pl.add_mesh(base, color=_COLORS[0], smooth_shading=True)
        if len(surfaces) > 1:
            cage = _polydata(*surfaces[j + 1])
            pl.add_mesh(cage, color=_COLORS[(j + 1) % len(_COLORS)], opacity=0.35, show_edges=True,
                        edge_color="#333333", line_width=0.6)
            pl.add_text(f"layer {j + 1}: {len(surfaces[j + 1][1])} faces", font_size=10)
        elif title:
            pl.add_text(title, font_size=10)
        pl.view_isometric()
        pl.camera.zoom(1.5)
    if title and len(surfaces) > 1:
        pl.subplot(0, 0)
        pl.add_text(title, position="lower_left", font_size=9)
    _write_png(path, pl.screenshot)
    pl.close()
    return path


def plot_convergence(
    histories: dict[str, list[float]],
    path: str | os.PathLike,
    *,
    title: str = "",
    xlabel: str = "cycle",
) -> Path:
    """Relative residual vs cycle (log scale), one line per labelled history, saved as PNG.

    Parameters
    ----------
    histories : dict of str -> list of float
        Relative residual norms, first entry = initial residual (1.0).
    path : str or PathLike
        Output PNG.
    title, xlabel : str
        Axis annotations.

    Returns
    -------
    Path
        The written file.
    """
    with third_party_to_log():
        return _plot_convergence(histories, Path(path), title, xlabel)


def _plot_convergence(histories, path: Path, title: str, xlabel: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for label, res in histories.items():
        res = np.asarray(res, dtype=float)
        ax.semilogy(np.arange(len(res)), np.maximum(res, 1e-300), marker="o", ms=3, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("relative residual")
    ax.grid(True, which="both", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _write_png(path, fig.savefig)
    plt.close(fig)
    return path


def _curved_surface(X: np.ndarray, F6: np.ndarray, order: int = 4):
    """Flat triangles (4^k per facet) and facet-edge polylines of 6-node facets, for drawing."""
    from solvers.fem_p2 import _p2_tri_basis

    st = np.array([(i / order, j / order) for j in range(order + 1) for i in range(order + 1 - j)])
    idx = {(i, j): k for k, (i, j) in enumerate((round(a * order), round(b * order)) for a, b in st)}
    tris = []
    for j in range(order):
        for i in range(order - j):
            tris.append([idx[i, j], idx[i + 1, j], idx[i, j + 1]])
            if i + j < order - 1:
                tris.append([idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]])
    N, _ = _p2_tri_basis(st)
    P = np.einsum("qa,fad->fqd", N, X[F6])  # (f, q, 3)
    q = len(st)
    F = (np.asarray(tris)[None] + q * np.arange(len(F6))[:, None, None]).reshape(-1, 3)
    s = np.linspace(0, 1, order + 1)
    edges = [np.c_[s, 0 * s], np.c_[1 - s, s], np.c_[0 * s, 1 - s]]
    lines = [np.einsum("qa,fad->fqd", _p2_tri_basis(e)[0], X[F6]) for e in edges]
    return P.reshape(-1, 3), F, np.concatenate(lines, axis=0)


def render_curved(X: np.ndarray, F6: np.ndarray, Xs: np.ndarray, path: str | os.PathLike, *,
                  titles: tuple[str, str] = ("straight", "curved P2"), window_size=(1600, 800)) -> Path:
    """Straight and curved boundaries of a quadratic tet mesh side by side (off-screen PNG).

    Parameters
    ----------
    X, Xs : (N,3) float arrays
        Curved and straight P2 nodes (:class:`nestmg.curved.CurvedMesh` ``X`` and ``straight().X``).
    F6 : (f,6) int array
        Boundary facets (:meth:`nestmg.curved.CurvedMesh.boundary_facets`).
    """
    with third_party_to_log():
        import pyvista as pv

        pv.OFF_SCREEN = True
        pl = pv.Plotter(off_screen=True, shape=(1, 2), window_size=window_size, border=False)
        for j, (Y, title) in enumerate(((Xs, titles[0]), (X, titles[1]))):
            pl.subplot(0, j)
            P, F, L = _curved_surface(np.asarray(Y), np.asarray(F6))
            pl.add_mesh(_polydata(P, F), color="#d9d9d9", smooth_shading=True)
            seg = np.stack([L[:, :-1], L[:, 1:]], axis=2).reshape(-1, 3)
            pl.add_mesh(pv.line_segments_from_points(seg), color="#1f4e79", line_width=1.2)
            pl.add_text(title, font_size=12)
            pl.view_xy()
        pl.link_views()
        _write_png(Path(path), pl.screenshot)
        pl.close()
    return Path(path)
