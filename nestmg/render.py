"""Pictures: cage layers (pyvista, off-screen PNG) and convergence plots (matplotlib PNG)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["plot_convergence", "render_layers"]

_COLORS = ["#d9d9d9", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"]


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    pl.screenshot(str(tmp))
    pl.close()
    os.replace(tmp, path)
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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path
