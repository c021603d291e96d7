"""Shared helpers of the paper-reproduction experiments (``benchmarks/exp_*.py``, docs/experiments.md).

Hierarchies compared on the *same* fine tet mesh (TetGen keeps the input boundary, so every hierarchy
of one mesh shares level 0 exactly):

``nested``
    ``cagegen`` nested cages, tet-meshed per layer; fine nodes outside a coarse tet mesh (rare,
    touching cages) use the default clamped rule.
``naive-<rule>``
    plain decimations (``method="decimate"``) with one of the four extrapolation rules of
    :mod:`nestmg.prolongation` for the fine nodes sticking out of the coarse mesh.

Only the prolongations differ between the naive variants: the tet meshes are built once and ``P`` is
recomputed per rule.
"""

from __future__ import annotations

import json
import platform
import resource
import time
from pathlib import Path

import numpy as np

ZOO = Path("/work/shared/data/meshes")
NAIVE_RULES = ("clamped", "linear", "closest_point", "nearest_vertex")


def edge_for_tets(V: np.ndarray, F: np.ndarray, target: int) -> float:
    """Target edge length giving roughly ``target`` TetGen tets in the solid ``(V, F)``.

    TetGen with a volume bound ``h^3/(6 sqrt 2)`` (regular tet of edge ``h``) produces about 2.1x more
    tets than ``volume / bound`` (measured on gargo and bunny), hence the factor.
    """
    import trimesh

    vol = trimesh.Trimesh(V, F, process=False).volume
    return float((2.1 * 6 * np.sqrt(2) * vol / target) ** (1 / 3))


def load_zoo(name: str, zoo: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A dev-zoo mesh normalised to a unit bounding-box diagonal, centred at the origin."""
    from nestmg.io import load_mesh, normalize

    V, F = load_mesh(Path(zoo if zoo is not None else ZOO) / name)
    V, _, _ = normalize(V)
    return V, F


def build_pair(V, F, levels: int, fine_tets: int, *, same_domain: int = 0, rules=NAIVE_RULES,
               face_counts: list[int] | None = None) -> dict:
    """Nested and naive hierarchies of ``(V, F)`` on one fine TetGen mesh.

    Parameters
    ----------
    V : (n,3) float array, F : (m,3) int array
        Normalised input surface.
    levels : int
        Total number of levels (fine level included).
    fine_tets : int
        Approximate number of fine tets.
    same_domain : int
        Number of extra levels that re-mesh the *input* surface at 2x, 4x, ... the fine edge length
        before the cages start (ENVIRONMENT.md "At scale"); ``levels - same_domain`` surface layers
        come from the cage backend.
    rules : tuple of str
        Extrapolation rules of the naive hierarchy.
    face_counts : list of int, optional
        Cage face counts (coarser layers only; default 4x fewer per layer).

    Returns
    -------
    dict
        ``hierarchies``: name -> ``(tets, P, reports)``; ``info``: name -> JSON summary (node / tet
        counts, n_outside, stage seconds, certification).
    """
    from nestmg.hierarchy import tet_hierarchy
    from nestmg.prolongation import prolongation

    h0 = edge_for_tets(V, F, fine_tets)
    n_cage_levels = levels - same_domain
    out: dict = {"hierarchies": {}, "info": {}, "fine_edge_length": h0}
    for method in ("nested", "decimate"):
        t0 = time.perf_counter()
        if n_cage_levels >= 2:
            surfaces, cinfo = cages(V, F, n_cage_levels, method, face_counts)
            cage_seconds = cinfo.get("seconds", 0.0)
            nested_ok = (cinfo.get("verification") or {}).get("ok")
        else:
            surfaces, cage_seconds, nested_ok = [(V, F)], 0.0, None
        t1 = time.perf_counter()
        layers = [(V, F)] * (same_domain + 1) + list(surfaces[1:])
        tets, P, reps, tt = tet_hierarchy(layers, mesher="tetgen", edge_length_fac=h0, progress=False)
        t2 = time.perf_counter()
        base = {
            "nodes": [len(Vk) for Vk, _ in tets],
            "tets": [len(Tk) for _, Tk in tets],
            "surface_faces": [len(Fk) for _, Fk in layers],
            "same_domain_levels": same_domain,
            "surfaces_nested": nested_ok,
            "seconds": {"cages": cage_seconds, "cages_wall": t1 - t0, "tets": tt.get("tets", 0.0),
                        "prolongation": tt.get("prolongation", 0.0), "tet_hierarchy_wall": t2 - t1},
        }
        if method == "nested":
            out["hierarchies"]["nested"] = (tets, P, reps)
            out["info"]["nested"] = {**base, "n_outside": [r.n_outside for r in reps],
                                     "max_outside_rel": [r.max_distance_rel for r in reps]}
        else:
            for rule in rules:
                if rule == "clamped":
                    Pr, rr = P, reps
                else:
                    pr = [prolongation(tets[k][0], tets[k + 1][0], tets[k + 1][1], extrapolation=rule)
                          for k in range(len(tets) - 1)]
                    Pr, rr = [p for p, _ in pr], [r for _, r in pr]
                out["hierarchies"][f"naive-{rule}"] = (tets, Pr, rr)
                out["info"][f"naive-{rule}"] = {**base, "n_outside": [r.n_outside for r in rr],
                                                "max_outside_rel": [r.max_distance_rel for r in rr]}
    return out


def cages(V, F, levels: int, method: str, face_counts: list[int] | None = None) -> tuple[list, dict]:
    """Cage layers of ``(V, F)`` (finest = input first) through nestmg's on-disk cache.

    Uses the same cache key as :func:`nestmg.build_hierarchy`, so cages built by either are reused.
    """
    import cagegen
    from nestmg.cache import cache_key, load_entry, save_entry

    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    opts = {"stage": "cages", "method": method, "levels": levels, "face_counts": face_counts}
    key = cache_key([V, F], opts)
    hit = load_entry(key)
    if hit is not None:
        arrays, info = hit
        return [(arrays[f"V{k}"], arrays[f"F{k}"]) for k in range(levels)], dict(info, cached=True)
    t0 = time.perf_counter()
    surfaces, info = cagegen.build_cages(V, F, levels, method=method, face_counts=face_counts, return_info=True,
                                         progress=False)
    info = dict(info, seconds=time.perf_counter() - t0)
    arrays = {}
    for k, (Vk, Fk) in enumerate(surfaces):
        arrays[f"V{k}"], arrays[f"F{k}"] = Vk, Fk
    save_entry(key, arrays, info)
    return surfaces, info


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def environment() -> dict:
    """Machine facts recorded with every result."""
    import os

    return {"python": platform.python_version(), "cpus": os.cpu_count(), "load_avg": os.getloadavg(),
            "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}


def write_json(obj: dict, path: Path) -> None:
    """Write ``obj`` as indented JSON (numpy scalars converted)."""

    from nestmg.io import json_default

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, default=json_default))


# plot style (colour, marker, line) of every hierarchy the experiments compare
STYLES = {"nested": ("k", "o", "-"), "naive-clamped": ("tab:blue", "s", "--"),
          "naive-linear": ("tab:red", "^", "--"), "naive-closest_point": ("tab:green", "v", "--"),
          "naive-nearest_vertex": ("tab:orange", "D", "--")}


def save_figure(fig, path: Path, dpi: int = 70) -> None:
    """Lay out, write (creating the folder) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def run_child(code: str, payload: dict, *, timeout: float | None = None, stderr_through: bool = False) -> dict:
    """Run ``python -c code json(payload)`` in a fresh process (its own peak memory) and return the JSON
    it prints on a line ``RESULT {...}``; ``{"error": ...}`` when it printed none or timed out.

    ``stderr_through``: let the child's stderr (stage lines) pass to ours instead of capturing it.
    """
    import subprocess
    import sys

    try:
        p = subprocess.run([sys.executable, "-c", code, json.dumps(payload)], check=False, stdout=subprocess.PIPE,
                           stderr=None if stderr_through else subprocess.PIPE, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout:.0f} s", "seconds": float("inf")}
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    return {"error": ((p.stderr or "") + p.stdout)[-2000:], "returncode": p.returncode}


def best_cpu_time(f, repeat: int) -> float:
    """Smallest CPU time (``time.process_time``) of ``repeat`` calls of ``f()`` (robust on a shared machine)."""
    ts = []
    for _ in range(repeat):
        t0 = time.process_time()
        f()
        ts.append(time.process_time() - t0)
    return min(ts)
