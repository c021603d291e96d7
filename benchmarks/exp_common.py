"""Shared helpers of the benchmark scripts (benchmarks/README.md): imported as ``from exp_common import ...``
(Python puts the running script's folder, ``benchmarks/``, first on ``sys.path``).

Sections: the paper-reproduction experiments (``benchmarks/exp_*.py``, docs/experiments.md), the cage
benchmarks (reading a surface, closedness, per-layer figures, verification, running a backend or the
reference wheel in a child process with a time limit, tightness) and the reuse benchmarks.

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

from nestmg import MeshingOptions, SizingOptions

#: folder of the dev-zoo meshes: set by the experiments from their required ``--zoo`` argument
ZOO: Path | None = None
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

    folder = zoo if zoo is not None else ZOO
    if folder is None:
        raise ValueError(f"no mesh folder for {name!r}: pass zoo= or set exp_common.ZOO (the --zoo argument)")
    V, F = load_mesh(Path(folder) / name)
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
        tets, P, reps, tt = tet_hierarchy(layers, sizing=SizingOptions(edge_length=h0, coarsening=None),
                                          meshing=MeshingOptions(mesher="tetgen"), progress=False)
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


def git_commit() -> str:
    """Short hash of the checkout this script runs from ("" outside a git checkout)."""
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, check=False).stdout.strip()
    except OSError:
        return ""


def write_json(obj: dict, path: Path) -> None:
    """Write ``obj`` as indented JSON (numpy scalars converted)."""

    from nestmg.io import json_default

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, default=json_default))


# plot style (colour, marker, line) of every hierarchy the experiments compare
STYLES = {"nested": ("k", "o", "-"), "naive-clamped": ("tab:blue", "s", "--"),
          "naive-linear": ("tab:red", "^", "--"), "naive-closest_point": ("tab:green", "v", "--"),
          "naive-nearest_vertex": ("tab:orange", "D", "--")}


def timed_pcg(make, b) -> tuple:
    """``ml = make()`` and ``ml.solve(b, tol=1e-8, accel="cg")``: ``(ml, setup CPU s, solve CPU s, info)``."""
    t = time.process_time()
    ml = make()
    setup = time.process_time() - t
    t = time.process_time()
    _, info = ml.solve(b, tol=1e-8, accel="cg", return_info=True)
    return ml, setup, time.process_time() - t, info


#: the three scalar model problems of the per-mesh studies (``nestmg.setup_problem`` names)
MODEL_PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


def model_problems(mesh: Path) -> tuple[dict, list]:
    """The default hierarchy of ``mesh`` (``build_hierarchy(V, F, levels=3)``, cached) and its model problems
    in the normalised frame, as ``nestmg solve`` poses them (diffusion's ``λ`` is relative to it; before
    3416f2e they were set up in the file's coordinates, where a large model made the diffusion problem a mass
    matrix): ``({"mesh", "tets", "rows": []}, [(name, Problem), ...])`` for :data:`MODEL_PROBLEMS`."""
    from nestmg import build_hierarchy, load_mesh, setup_problem

    V, F = load_mesh(mesh)[:2]
    H = build_hierarchy(V, F, levels=3, progress=False)
    head = {"mesh": mesh.name, "tets": [len(t) for _, t in H.tets], "rows": []}
    tets = H.tets_in("normalized")
    return head, [(name, setup_problem(tets, H.P, name)) for name in MODEL_PROBLEMS]


def mesh_study_main(script: str, description: str, measure, argv=None) -> None:
    """Command line of a per-mesh study: ``MESH [MESH ...] --out FILE.json``; writes ``{"command", "clock",
    "runs": [measure(mesh) for each mesh]}`` (``measure`` times with ``time.process_time``)."""
    import argparse
    import warnings

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("meshes", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    runs = [measure(m) for m in args.meshes]
    args.out.write_text(json.dumps({"command": script, "clock": "process_time", "runs": runs}, indent=1))


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all its threads: fTetWild's and ipctk's too)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def mesh_rows_main(script: str, description: str, measure, option: tuple, argv=None) -> None:
    """Command line of a per-mesh study with one numeric option: ``MESH [MESH ...] --NAME X --out FILE.json``.

    ``option`` is ``(name, default, help)``; ``measure(mesh, value)`` returns one row. Writes ``{"command",
    "meshes_given", "commit", "environment", "rows"}``, rewritten after each mesh (the command names the
    meshes' files, not this machine's paths)."""
    import argparse

    name, default, help_ = option
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("meshes", nargs="+", type=Path, help="closed surface files")
    ap.add_argument(f"--{name}", type=float, default=default, help=help_)
    ap.add_argument("--out", type=Path, required=True, help="JSON to write (rewritten after each mesh)")
    a = ap.parse_args(argv)
    value = getattr(a, name)
    out = {"command": f"python benchmarks/{script} " + " ".join(f"ZOO_DIR/{m.name}" for m in a.meshes)
           + f" --{name} {value} --out OUT/{a.out.name}", "meshes_given": [m.name for m in a.meshes],
           "commit": git_commit(), "environment": environment(), "rows": []}
    for m in a.meshes:
        out["rows"].append(measure(m, value))
        write_json(out, a.out)


def figure(rows: int, cols: int, **kwargs):
    """``(fig, axes)`` of ``matplotlib.pyplot.subplots(rows, cols, **kwargs)`` drawn off-screen (Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(rows, cols, **kwargs)


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


def cpu_times(f, repeat: int) -> list[float]:
    """CPU times (``time.process_time``) of ``repeat`` calls of ``f()``."""
    ts = []
    for _ in range(repeat):
        t0 = time.process_time()
        f()
        ts.append(time.process_time() - t0)
    return ts


def best_cpu_time(f, repeat: int) -> float:
    """Smallest CPU time of ``repeat`` calls of ``f()`` (robust on a shared machine)."""
    return min(cpu_times(f, repeat))


# ------------------------------------------------------------------ cage benchmarks (cages.py, cages_sdf.py, ...)
def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A surface file as read by libigl (not normalised): float64 ``V``, int64 ``F``, C-contiguous."""
    import igl

    V, F = igl.read_triangle_mesh(str(path))[:2]
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


def is_closed(F: np.ndarray) -> tuple[bool, str]:
    """Closed = every edge has exactly two faces (no boundary, no non-manifold edge)."""
    E = np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(E, axis=0, return_counts=True)
    n_boundary = int(np.sum(counts == 1))
    n_nonmanifold = int(np.sum(counts > 2))
    if n_boundary or n_nonmanifold:
        return False, f"{n_boundary} boundary edges, {n_nonmanifold} non-manifold edges"
    return True, ""


def layer_figures(V, F, layers) -> list[dict]:
    """Per cage layer: max / mean distance to the input over its diagonal, volume ratio, genus, quality."""
    import igl

    from cagegen._geometry import signed_volume
    from cagegen.sdf.backend import _min_angle_deg, genus
    from cagegen.sdf.optimize import mips

    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    vol0 = signed_volume(V, F)
    out = []
    for Vk, Fk in layers:
        X = Vk[Fk]
        A = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)
        Q = np.vstack([X.mean(1), 0.5 * (X[:, 0] + X[:, 1]), 0.5 * (X[:, 1] + X[:, 2]), 0.5 * (X[:, 2] + X[:, 0])])
        w = np.tile(A / 4, 4)
        d2 = igl.point_mesh_squared_distance(Q, V, F)[0]
        m = mips(Vk, Fk)
        out.append({
            "n_faces": len(Fk),
            "max_distance_relative": float(igl.hausdorff(Vk, Fk, V, F)) / diag,
            "mean_distance_relative": float(np.sum(w * np.sqrt(d2)) / np.sum(w)) / diag,
            "volume_ratio": float(signed_volume(Vk, Fk) / vol0),
            "genus": genus(Vk, Fk),
            "min_angle_deg": _min_angle_deg(Vk, Fk),
            "mips_mean": float(m.mean()),
            "mips_max": float(m.max()),
        })
    return out


def verify_layers(V, F, layers) -> dict:
    """:func:`cagegen.verify_nesting` of the input and its cage layers, as a JSON-ready summary."""
    from cagegen import verify_nesting

    rep = verify_nesting([(V, F)] + list(layers))
    d = rep.to_dict()
    return {
        "ok": bool(rep.ok),
        "pairs": [
            {k: p.get(k) for k in ("fine", "ok", "reason", "min_gap", "min_gap_rel", "min_winding",
                                   "n_outside_vertices", "n_coarse_inside_vertices", "n_intersecting_pairs",
                                   "self_intersections_coarse", "seconds") if k in p}
            for p in d.get("pairs", [])
        ],
    }


def put_layers(q, path: str, build, details=None) -> None:
    """The child's side of :func:`in_subprocess`: time a cage builder on a mesh file, put the record on ``q``.

    ``layers, info = build(V, F)`` runs on the mesh read from ``path`` (the reading is not timed). The record:
    ``ok``, ``seconds``, ``cpu_seconds``, ``layers`` (float64 / int64 arrays) and the keys of
    ``details(info)``; on any failure ``ok=False``, the ``error``, the times so far and the traceback's end.
    """
    import traceback

    t, c0 = time.perf_counter(), time.process_time()
    try:
        V, F = read_mesh(Path(path))
        t, c0 = time.perf_counter(), time.process_time()
        layers, info = build(V, F)
        res = {"ok": True, "seconds": time.perf_counter() - t, "cpu_seconds": time.process_time() - c0,
               "layers": [(np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.int64))
                          for a, b in layers]}
        q.put({**res, **(details(info) if details else {})})
    except Exception as exc:  # noqa: BLE001 -- any failure is reported in the JSON
        q.put({"ok": False, "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t,
               "cpu_seconds": time.process_time() - c0, "traceback": traceback.format_exc()[-2000:]})


def run_wheel(path: str, counts: list[int], q) -> None:
    """Runner of the reference ``nested_cages`` wheel for :func:`in_subprocess` (puts its result on ``q``)."""
    def build(V, F):
        import nested_cages

        return nested_cages.nested_cages(
            np.asfortranarray(V), np.asfortranarray(F, dtype=np.int32), num_faces=list(counts), quad_order=2,
            energy_expansion="None", energy_final="Volume", regular=[True] * len(counts)), None

    put_layers(q, path, build)


def in_subprocess(fn, path: Path, counts: list[int], timeout: float) -> dict:
    """``fn(str(path), counts, queue)`` in a forked child; its result, or an error after ``timeout`` seconds."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(str(path), counts, q))
    t = time.perf_counter()
    p.start()
    try:
        res = q.get(timeout=timeout)
    except Exception:  # noqa: BLE001 -- queue timeout
        p.kill()
        p.join()
        return {"ok": False, "error": f"timeout after {timeout:.0f} s", "seconds": time.perf_counter() - t}
    p.join()
    return res


def surface_samples(V: np.ndarray, F: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Vertices of ``(V, F)`` plus ``n`` area-uniform random points on it, (n_v + n, 3)."""
    rng = np.random.default_rng(seed)
    a = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    f = rng.choice(len(F), size=n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    P = np.einsum("ij,ijk->ik", w, V[F[f]])
    return np.vstack([V, P])


def tightness(Vc: np.ndarray, Fc: np.ndarray, V0: np.ndarray, F0: np.ndarray, n_samples: int) -> dict:
    """Distance of the cage ``(Vc, Fc)`` to the input ``(V0, F0)`` over the input's diagonal, volume ratio."""
    import igl

    from cagegen._geometry import bbox_diagonal, signed_volume

    diag = bbox_diagonal(V0)
    Q = surface_samples(Vc, Fc, n_samples)
    d = np.sqrt(np.maximum(igl.point_mesh_squared_distance(Q, V0, F0)[0], 0.0)) / diag
    return {
        "max_dist_rel": float(d.max()),
        "mean_dist_rel": float(d.mean()),
        "volume_ratio": signed_volume(Vc, Fc) / signed_volume(V0, F0),
    }


# ------------------------------------------------------------------ reuse benchmarks (issue 15 item 5)
def try_hierarchy(rec: dict, label: str, V, F, levels: int, method: str, edge_length: float | None,
                  mesher: str):
    """:func:`nestmg.build_hierarchy` of ``(V, F)`` at a fine ``edge_length`` with ``mesher``, or None.

    A failure is recorded in ``rec["error"]`` and printed after ``label``: a benchmark reports it and goes on.
    """
    from nestmg import MeshingOptions, SizingOptions, build_hierarchy

    try:
        return build_hierarchy(V, F, levels, method, sizing=SizingOptions(edge_length=edge_length),
                               meshing=MeshingOptions(mesher=mesher), progress=False)
    except Exception as exc:  # noqa: BLE001 -- a benchmark reports any failure and goes on
        rec["error"] = f"{type(exc).__name__}: {exc}"
        print(f"{label} ERROR {rec['error']}", flush=True)
        return None


def cached_hierarchy(path: Path, *, levels: int = 3, max_tets: int = 1_200_000, method: str = "nested",
                   edge_length: float | None = None):
    """``nestmg.build_hierarchy`` of a mesh file with the project defaults, through the on-disk cache
    (``edge_length``: fine edge / bounding-box diagonal, default the input's mean edge).

    Returns ``(hierarchy, seconds)``; on a cache hit ``seconds`` is the load time, and
    ``hierarchy.timings`` keeps the stage times of the original build.
    """
    import nestmg
    from nestmg.io import load_mesh

    V, F = load_mesh(Path(path))
    t0 = time.perf_counter()
    h = nestmg.build_hierarchy(V, F, levels, method, cache=True, progress=False,
                               sizing=nestmg.SizingOptions(max_tets=max_tets, edge_length=edge_length))
    return h, time.perf_counter() - t0


def blas_info() -> dict:
    """BLAS / LAPACK libraries mapped into this process (resolved paths, from ``/proc/self/maps``) and the
    thread count of a system OpenBLAS, if one is loaded. Call after importing the solvers to check."""
    import ctypes
    import os

    libs = set()
    with open("/proc/self/maps") as fh:
        for line in fh:
            p = line.split()[-1]
            if p.startswith("/") and any(s in os.path.basename(p) for s in ("blas", "lapack")):
                libs.add(os.path.realpath(p))
    info: dict = {"libraries": sorted(libs), "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")}
    sys_openblas = [p for p in libs if "openblas" in p and "site-packages" not in p]
    if sys_openblas:
        try:
            info["system_openblas_threads"] = int(ctypes.CDLL(sys_openblas[0]).openblas_get_num_threads())
        except (OSError, AttributeError):
            pass
    return info


def relres(A, b, x) -> float:
    """``||b - A x|| / ||b||`` (0 for ``b = 0``)."""
    nb = float(np.linalg.norm(b))
    return float(np.linalg.norm(b - A @ x) / nb) if nb else 0.0


def pyamg_sa_solve(A, b, *, x0=None, tol: float = 1e-8, maxiter: int = 500, ml=None,
                   nullspace: str | None = None) -> tuple[np.ndarray, dict]:
    """pyamg smoothed aggregation (defaults) + CG from ``x0``; set up unless ``ml`` (a hierarchy to reuse) is
    given. Returns ``(x, info)`` with ``setup``/``solve`` wall and ``setup_cpu``/``solve_cpu`` CPU seconds,
    iterations, the hierarchy ``ml``.

    ``nullspace="constant"`` (singular Neumann matrix): pyamg's own CG stagnates or diverges on these
    (measured: 500 iterations to a residual of 1.7 at 1M tets), so the SA cycle preconditions the project's
    CG with the constants projected out (:func:`solvers.krylov.pcg`, as for nestmg's MG-PCG): only the
    preconditioner differs.
    """
    import pyamg

    from solvers.krylov import pcg

    t0, c0 = time.perf_counter(), time.process_time()
    if ml is None:
        ml = pyamg.smoothed_aggregation_solver(A)
    t1, c1 = time.perf_counter(), time.process_time()
    if nullspace == "constant":
        r = pcg(A, b - b.mean(), M=ml.aspreconditioner(), x0=x0, tol=tol, maxiter=maxiter, nullspace="constant")
        x, its = r.x, r.iterations
    else:
        res: list = []
        x = ml.solve(b, x0=x0, tol=tol, maxiter=maxiter, accel="cg", residuals=res)
        its = len(res) - 1
    t2, c2 = time.perf_counter(), time.process_time()
    return x, {"setup": t1 - t0, "solve": t2 - t1, "setup_cpu": c1 - c0, "solve_cpu": c2 - c1,
               "iterations": its, "final_residual": relres(A, b, x),
               "operator_complexity": float(ml.operator_complexity()), "ml": ml}


class PetscAmg:
    """CG + PETSc GAMG or hypre BoomerAMG (1 rank), set up per matrix, reusable for many right-hand sides.

    :meth:`setup` with ``reuse_interpolation=False`` builds a new matrix, KSP and preconditioner (a full
    AMG setup). ``reuse_interpolation=True`` (GAMG only): after the first setup, new values (same
    pattern) are copied into the same matrix and GAMG keeps its prolongators
    (``-pc_gamg_reuse_interpolation``), re-doing only the Galerkin products and smoothers: AMG's own
    form of reuse. :meth:`apply` solves with the current setup. Tolerance: unpreconditioned
    ``||r|| <= tol ||b||``, as the other methods. ``nullspace="constant"`` attaches the constants.
    """

    def __init__(self, kind: str = "gamg", *, reuse_interpolation: bool = False, nullspace: str | None = None):
        from solvers.petsc_common import _petsc

        self.PETSc = _petsc()
        if kind not in ("gamg", "hypre") or (reuse_interpolation and kind != "gamg"):
            raise ValueError(f"kind must be 'gamg' or 'hypre' (reuse_interpolation only with gamg), got {kind!r}")
        self.kind, self.reuse, self.nullspace = kind, reuse_interpolation, nullspace
        self.mat = self.ksp = self.ns = self.A = None

    def _new(self, A):
        PETSc = self.PETSc
        it = PETSc.IntType
        self.destroy()
        self.mat = PETSc.Mat().createAIJ(size=A.shape, csr=(A.indptr.astype(it), A.indices.astype(it), A.data),
                                         comm=PETSc.COMM_SELF)
        self.mat.assemble()
        if self.nullspace == "constant":
            self.ns = PETSc.NullSpace().create(constant=True, comm=PETSc.COMM_SELF)
            self.mat.setNullSpace(self.ns)
            self.mat.setNearNullSpace(self.ns)
        ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
        ksp.setType("cg")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        pc = ksp.getPC()
        if self.kind == "gamg":
            pc.setType("gamg")
            pc.setGAMGType(PETSc.PC.GAMGType.AGG)
            if self.reuse:
                opts = PETSc.Options()
                opts["nestmg_reuse_pc_gamg_reuse_interpolation"] = "true"
                ksp.setOptionsPrefix("nestmg_reuse_")
                ksp.setFromOptions()
                del opts["nestmg_reuse_pc_gamg_reuse_interpolation"]
        else:
            pc.setType("hypre")
            pc.setHYPREType("boomeramg")
        self.ksp = ksp

    def setup(self, A) -> tuple[float, float]:
        """Set up for ``A`` (canonical csr); returns wall and CPU seconds (matrix copy included)."""
        PETSc = self.PETSc
        t0, c0 = time.perf_counter(), time.process_time()
        if self.reuse and self.mat is not None:
            it = PETSc.IntType
            self.mat.setValuesCSR(A.indptr.astype(it), A.indices.astype(it), A.data)
            self.mat.assemble()
        else:
            self._new(A)
        self.ksp.setOperators(self.mat)
        self.ksp.setUp()
        self.A = A
        return time.perf_counter() - t0, time.process_time() - c0

    def apply(self, b, *, x0=None, tol: float = 1e-8, maxiter: int = 500) -> tuple[np.ndarray, dict]:
        """Solve with the current setup from ``x0`` (default 0); returns ``(x, info)``."""
        t0, c0 = time.perf_counter(), time.process_time()
        self.ksp.setTolerances(rtol=tol, atol=1e-300, max_it=maxiter)
        xv, bv = self.mat.createVecs()
        bv.setArray(b)
        self.ksp.setInitialGuessNonzero(x0 is not None)
        if x0 is None:
            xv.set(0.0)
        else:
            xv.setArray(x0)
        self.ksp.solve(bv, xv)
        x = xv.getArray().copy()
        t1, c1 = time.perf_counter(), time.process_time()
        its, reason = self.ksp.getIterationNumber(), self.ksp.getConvergedReason()
        xv.destroy()
        bv.destroy()
        if self.nullspace == "constant":
            x -= x.mean()
        return x, {"solve": t1 - t0, "solve_cpu": c1 - c0, "iterations": int(its), "reason": int(reason),
                   "final_residual": relres(self.A, b, x)}

    def solve(self, A, b, *, x0=None, tol: float = 1e-8, maxiter: int = 500) -> tuple[np.ndarray, dict]:
        """:meth:`setup` then :meth:`apply`; ``info`` has ``setup``/``solve`` (wall) and ``*_cpu`` seconds."""
        ts, cs = self.setup(A)
        x, info = self.apply(b, x0=x0, tol=tol, maxiter=maxiter)
        return x, dict(info, setup=ts, setup_cpu=cs)

    def destroy(self) -> None:
        """Free the PETSc objects."""
        for obj in (self.ksp, self.mat, self.ns):
            if obj is not None:
                obj.destroy()
        self.mat = self.ksp = self.ns = None


class Cholmod:
    """CHOLMOD (scikit-sparse, optional, benchmark-only) for a sequence of SPD matrices with one pattern.

    The symbolic analysis (fill-reducing ordering, supernodes) is done once, at the first matrix; every
    :meth:`factor` re-does only the numeric factorisation (``cholesky_inplace``). ``pin``: drop row and
    column ``pin`` (a pure Neumann matrix; the solution gets 0 there, then zero mean).
    """

    def __init__(self, *, pin: int | None = None):
        from sksparse.cholmod import analyze  # optional; never imported by nestmg / solvers / cagegen

        self._analyze = analyze
        self.pin, self.factor_ = pin, None
        self.analyze_seconds = self.analyze_cpu = 0.0

    def _reduce(self, A):
        if self.pin is None:
            return A.tocsc()
        keep = np.delete(np.arange(A.shape[0]), self.pin)
        return A[keep][:, keep].tocsc()

    def factor(self, A) -> tuple[float, float]:
        """(Re-)factorise ``A``; returns the numeric factorisation's wall and CPU seconds (the first call's
        analysis is in :attr:`analyze_seconds` and :attr:`analyze_cpu`)."""
        t0, c0 = time.perf_counter(), time.process_time()
        Ak = self._reduce(A)
        if self.factor_ is None:
            ta, ca = time.perf_counter(), time.process_time()
            self.factor_ = self._analyze(Ak)
            self.analyze_seconds = time.perf_counter() - ta
            self.analyze_cpu = time.process_time() - ca
            t0 += self.analyze_seconds
            c0 += self.analyze_cpu
        self.factor_.cholesky_inplace(Ak)
        return time.perf_counter() - t0, time.process_time() - c0

    def solve(self, b) -> np.ndarray:
        """Solve with the current factor (full-length ``b``)."""
        if self.pin is None:
            return self.factor_(b)
        keep = np.delete(np.arange(len(b)), self.pin)
        x = np.zeros(len(b))
        x[keep] = self.factor_(b[keep])
        return x - x.mean()


def join_runs(files: list[Path], same: tuple[str, ...], joined: tuple[str, ...]) -> dict:
    """One result from the JSON of runs of the same meshes with other ``--methods`` (separate processes).

    The first file gives the frame (plus ``merged_from`` and every file's ``commands``); a mesh met again
    must agree on the ``same`` keys (else ``SystemExit``), and its ``runs`` and ``joined`` per-method dicts
    take the entries of that file's own runs.
    """
    import json

    res = None
    for f in files:
        r = json.loads(Path(f).read_text())
        if res is None:
            res = dict(r, merged_from=[str(x) for x in files], commands=[], meshes=[])
        res["commands"].append(r["params"]["command"])
        for rec in r["meshes"]:
            tgt = next((x for x in res["meshes"] if x["mesh"] == rec["mesh"]), None)
            if tgt is None:
                res["meshes"].append(rec)
                continue
            differ = [k for k in same if tgt[k] != rec[k]]
            if differ:
                raise SystemExit(f"{f}: {rec['mesh']} has other {' / '.join(differ)} than {files[0]}")
            for key in ("runs", *joined):
                tgt[key].update({m: v for m, v in rec[key].items() if m in rec["runs"]})
    return res


def add_hierarchy_arguments(ap) -> None:
    """Mesh files and their fine edge lengths (argparse) for :func:`hierarchies_from_args`."""
    ap.add_argument("meshes", type=Path, nargs="*", help="closed surface files (e.g. ZOO_DIR/*.off)")
    ap.add_argument("--edge-length", type=float, nargs="+", default=None,
                    help="fine edge / bounding-box diagonal, one per mesh (default: build_hierarchy's)")


def hierarchies_from_args(a) -> list[tuple[Path, float | None]]:
    """``(mesh path, edge_length)`` pairs from :func:`add_hierarchy_arguments`' arguments."""
    edges = a.edge_length or [None] * len(a.meshes)
    if len(edges) != len(a.meshes):
        raise SystemExit(f"--edge-length needs one value per mesh ({len(a.meshes)}), got {len(edges)}")
    return list(zip(a.meshes, edges))


def available_methods(requested, order) -> list[str]:
    """``requested`` methods in ``order``, minus those whose optional package is missing (said on stderr):
    CHOLMOD needs scikit-sparse, the PETSc baselines petsc4py."""
    import sys

    methods = [m for m in order if m in requested]
    if "cholmod" in methods:
        try:
            import sksparse.cholmod  # noqa: F401
        except ImportError:
            print("scikit-sparse not installed: CHOLMOD skipped", file=sys.stderr)
            methods.remove("cholmod")
    from solvers.petsc_common import petsc_available

    if not petsc_available():
        print("petsc4py not importable (scripts/install-petsc.sh): PETSc GAMG / hypre skipped", file=sys.stderr)
        methods = [m for m in methods if m not in ("gamg", "gamg_reuse", "hypre")]
    return methods
