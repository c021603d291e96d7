"""fTetWild's time against the order of its input: as given, shuffled, and renumbered along a Morton curve.

The same surface (normalised to a unit diagonal) is meshed three times at the same edge, in the same process,
with fTetWild's defaults and a uniform box (``outer_edge_factor`` off, to see the order alone): its vertices
and faces in the file's order, in a random order (seed 0), and in :func:`nestmg.tetmesh.spatial_order`'s
(what :func:`nestmg.tetmesh.tetrahedralize` now passes). Wall and CPU seconds and tets go to the JSON
(``benchmarks/results/tetwild/``), with the input's locality: the median distance between consecutive faces'
centroids in mean edge lengths.

    python benchmarks/tetwild_order.py ZOO_DIR/cheburashka.obj ZOO_DIR/homer.obj --edge 0.05 --out OUT.json
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from exp_common import cpu_seconds, mesh_rows_main, read_mesh

ORDERS = ("given", "shuffled", "spatial")


def face_jump(V: np.ndarray, F: np.ndarray) -> float:
    """Median distance between consecutive faces' centroids, in mean edge lengths (random order: tens)."""
    C = V[F].mean(axis=1)
    edge = float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
    return float(np.median(np.linalg.norm(np.diff(C, axis=0), axis=1)) / edge)


def ordered(V: np.ndarray, F: np.ndarray, order: str) -> tuple[np.ndarray, np.ndarray]:
    from nestmg.tetmesh import spatial_order

    if order == "spatial":
        return spatial_order(V, F)
    if order == "shuffled":
        rng = np.random.default_rng(0)
        perm = rng.permutation(len(V))
        rank = np.empty_like(perm)
        rank[perm] = np.arange(len(perm))
        return V[perm], rank[F][rng.permutation(len(F))]
    return V, F


def timed(V: np.ndarray, F: np.ndarray, edge: float) -> dict:
    """fTetWild called directly (no reordering), its defaults, uniform box, all cores."""
    from cagegen import in_temp_dir
    from nestmg._mesh_worker import run_job

    opts = {"edge_length_abs": edge, "epsilon": 1e-3, "num_threads": 0, "quiet": True, "stop_energy": 10.0,
            "num_opt_iter": 80, "coarsen": False, "simplify": True}
    c, t = cpu_seconds(), time.perf_counter()
    with in_temp_dir():  # fTetWild writes scratch files in the working directory
        _, T = run_job("tetwild", V, F, opts)
    return {"wall_seconds": time.perf_counter() - t, "cpu_seconds": cpu_seconds() - c, "tets": len(T)}


def measure(path: Path, edge: float) -> dict:
    from cagegen import normalize

    V, F = read_mesh(path)
    V = np.ascontiguousarray(normalize(V)[0], dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    row = {"mesh": path.name, "faces": len(F), "edge": edge}
    for order in ORDERS:
        W, G = ordered(V, F, order)
        row[order] = {"face_jump": face_jump(W, G), **timed(W, G, edge)}
        r = row[order]
        print(f"{path.name} {order}: {r['wall_seconds']:.1f} s wall, {r['cpu_seconds']:.1f} CPU s, {r['tets']:,} tets "
              f"(face jump {r['face_jump']:.1f})", flush=True)
    return row


def main(argv: list[str] | None = None) -> None:
    mesh_rows_main("tetwild_order.py", __doc__.splitlines()[0], measure,
                   ("edge", 0.05, "target edge, fraction of the bounding-box diagonal"), argv)


if __name__ == "__main__":
    sys.exit(main())
