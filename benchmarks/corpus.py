"""The defaults on a whole folder of meshes: one JSON and one table (issue 27, item 7).

    OMP_NUM_THREADS=1 python benchmarks/corpus.py ZOO_DIR --out benchmarks/results/corpus/NAME.json \
        --md docs/corpus.md

For every closed surface file of ``ZOO_DIR`` (OBJ/OFF/PLY/STL; files with boundary or non-manifold edges
are listed as skipped, with the reason, unless ``--repair`` is given: it closes a scan's small holes):

* ``solve``: the hierarchy ``nestmg solve FILE --levels 3 --no-cache`` builds by default (nested cages,
  TetWild), then the three model problems (Dirichlet / Neumann Poisson, Neumann diffusion) with the
  default cycle, as V-cycles and as MG-PCG: certified (surfaces and n_outside = 0 per level), seconds per
  stage, tets per level, V-cycle factor, cycles, MG-PCG iterations, operator complexity;
* ``cages:M`` for each backend ``M`` (``--backends``): ``nestmg cages FILE --levels 3 --method M
  --no-cache``: certified, faces per layer, seconds, fallbacks;
* ``wheel``: the reference ``nested_cages`` wheel (extra ``bench``) at the face counts of our nested
  cages, on the same (normalised) surface, for the speed ratio.

Every case runs in its own process (``--timeout`` seconds, then killed), so a crash or a hang is a row of
the table, not the end of the run; its peak resident memory (the process and its mesher worker) is
recorded. A ``cages`` or ``wheel`` case first runs once, untimed, on a small procedural sphere in its
process (``warm_up_seconds``): imports and first calls stay outside the clock on both sides of the ratio.
``--table JSON`` rewrites the markdown table from a JSON without running anything.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import replace
from pathlib import Path

import numpy as np

from nestmg.problems import FACTOR_GOALS, PROBLEMS

MESH_EXT = (".off", ".obj", ".ply", ".stl")
#: goals of issue 27 item 3: V-cycle factor per problem (the ones the defaults deflate down to), MG-PCG
#: iterations, operator complexity
GOALS = {**FACTOR_GOALS, "pcg": 10, "complexity": 1.5}


# ------------------------------------------------------------------------------------------ inputs
#: set by ``--repair`` for the case processes: every case then runs with ``--repair``
REPAIR_ENV = "NESTMG_CORPUS_REPAIR"
BUDGET_ENV = "NESTMG_CORPUS_CAGE_TIME_BUDGET"  # --cage-time-budget for the case processes

def read_surface(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a surface file, as ``nestmg`` reads it."""
    from nestmg.io import load_mesh

    V, F = load_mesh(path)
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


def closed_reason(F: np.ndarray) -> str:
    """'' when every edge has exactly two faces, else what is wrong."""
    E = np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(E, axis=0, return_counts=True)
    nb, nn = int(np.sum(counts == 1)), int(np.sum(counts > 2))
    return f"{nb} boundary edges, {nn} non-manifold edges" if nb or nn else ""


def _peak_mb() -> float:
    """Peak resident memory (MB) of this process or of its largest finished child (the mesher worker)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0


# ------------------------------------------------------------------------------------ cases (child)
def _cli_args(command: str, mesh: Path, extra: list[str]):
    from nestmg.cli import _typed_options, build_parser

    out = ["--out", os.path.join(tempfile.gettempdir(), "corpus-unused")] if command == "cages" else []  # not written
    if os.environ.get(REPAIR_ENV):
        extra = [*extra, "--repair"]
    if os.environ.get(BUDGET_ENV):
        extra = [*extra, "--cage-time-budget", os.environ[BUDGET_ENV]]
    args = build_parser().parse_args([command, str(mesh), "--levels", "3", "--no-cache", "--quiet", *out, *extra])
    _typed_options(args)  # args.sizing / .meshing / .solver, as `nestmg` builds them
    return args


def case_solve(mesh: Path) -> dict:
    """The default hierarchy of ``nestmg solve`` and the three model problems on it."""
    from nestmg.cli import _bodies, _hierarchy, _load, _solve

    args = _cli_args("solve", mesh, [])
    V, F, _ = _load(str(mesh))
    V, F, bodies = _bodies(V, F, args.repair)
    if bodies:
        return _case_solve_bodies(V, F, bodies, args)
    t = time.perf_counter()
    h = _hierarchy(V, F, args)
    rec: dict = {"hierarchy_seconds": time.perf_counter() - t, "certified": h.certified,
                 "surfaces_nested": h.surfaces_nested, "n_outside": h.n_outside, "fallbacks": h.fallbacks,
                 "faces": [len(Fk) for _, Fk in h.surfaces], "tets": [len(T) for _, T in h.tets],
                 "nodes": [len(Vt) for Vt, _ in h.tets], "levels": h.levels,
                 "levels_note": (h.options.get("plan", {}).get("levels") or {}).get("note"),
                 "stages": {k: v for k, v in h.timings.items() if isinstance(v, (int, float))},
                 "cage_layer_seconds": h.cage_info.get("layer_seconds"),
                 "predecimation": {k: h.cage_info.get("predecimation", {}).get(k)
                                   for k in ("faces_in", "faces_out", "hausdorff")},
                 "sizing_rule": h.options.get("plan", {}).get("rule"),
                 # the sizing's estimate of the fine level's meshing against each level's measured seconds
                 "planned_mesh_seconds": h.options.get("plan", {}).get("expected_seconds"),
                 "tet_seconds": h.timings.get("tet_seconds"), "problems": {}}
    solver = args.solver
    for problem in PROBLEMS:
        args.problem = problem
        args.solver = replace(solver, accel=None)
        r = _solve(h, args)
        args.solver = replace(solver, accel="cg")
        c = _solve(h, args)
        rec["problems"][problem] = {
            "factor": r["factor"], "cycles": r["iterations"], "converged": r["converged"],
            "pcg_iterations": c["iterations"], "pcg_converged": c["converged"],
            "operator_complexity": r.get("operator_complexity"), "solve_seconds": r["seconds"],
            "pcg_seconds": c["seconds"], "deflation": r.get("deflation"),
            "solve_cpu_seconds": r.get("cpu_seconds"), "pcg_cpu_seconds": c.get("cpu_seconds"),
            "coarsest": c.get("coarsest"),
            "constructor": constructor_pcg(h, problem, args.solver),
        }
    return rec


def constructor_pcg(h, problem: str, solver) -> dict:
    """MG-PCG to 1e-8 with ``MultigridSolver(A, P)``'s defaults (the problem's coarse operators and null
    space only) on the problem ``nestmg solve`` poses (``default``: ``deflate="auto"``, the coarse levels'
    probe within ``AUTO_PROBE_MAX_COMPLEXITY``) and with ``deflate=0`` (``no_probe``): CG iterations, set-up
    and solve CPU seconds, the ``deflate`` used, operator complexity, the probe's levels. (The run at
    e9b70b9, when the default was ``deflate=0``, recorded ``default`` and ``coarse_probe``, ``deflate=8``,
    plus one-way boundary-layer sweeps, ``layer`` and ``layer_probe``.)"""
    from nestmg.problems import setup_problem
    from solvers import MultigridSolver

    pr = setup_problem(h.tets_in("normalized"), h.P, problem, coarse=solver.coarse, lam=solver.lam)
    out = {}
    for name, kw in (("default", {}), ("no_probe", {"deflate": 0})):
        t = time.process_time()
        ml = MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace, **kw)
        setup = time.process_time() - t
        t = time.process_time()
        _, info = ml.solve(pr.b, tol=solver.tol, accel="cg", return_info=True)
        out[name] = {"pcg_iterations": info["iterations"], "converged": bool(info["converged"]),
                     "setup_cpu_seconds": setup, "solve_cpu_seconds": time.process_time() - t,
                     "deflate": int(ml.deflate), "operator_complexity": ml.operator_complexity(),
                     "probe": [{"level": d["level"], "probe_factor": d["probe_factor"], "vectors": d["vectors"],
                                "local_solve": (d.get("local_solve") or {}).get("nodes")
                                if (d.get("local_solve") or {}).get("kept") else None}
                               for d in ml.deflation]}
    return out


def _ctor_iterations(c: dict) -> tuple[int, int]:
    """(MG-PCG iterations with the coarse probe, without it) of a :func:`constructor_pcg` record, whichever
    of the two was the default when it was recorded (each variant records its ``deflate``). When no variant
    probed (``deflate="auto"`` skips the probe above its complexity limit), both are the default's."""
    plain = [v for k, v in c.items() if k in ("default", "no_probe", "coarse_probe")]
    none = next(v for v in plain if not v["deflate"])
    probe = next((v for v in plain if v["deflate"]), none)
    return probe["pcg_iterations"], none["pcg_iterations"]


def _case_solve_bodies(V, F, bodies, args) -> dict:
    """:func:`case_solve` on an input of several disjoint bodies (``nestmg solve``'s per-body path): per
    level the tets summed over the bodies that have it; per problem the worst body's factor, the most
    iterations, the largest operator complexity, summed seconds (:func:`nestmg.bodies.solve_bodies`)."""
    from nestmg.bodies import file_frame, solve_bodies, summed_timings
    from nestmg.cli import _body_hierarchies

    t = time.perf_counter()
    hs = _body_hierarchies(V, F, bodies, args)
    n_levels = max(h.levels for h in hs)

    def per_level(f):
        return [sum(f(h)[k] for h in hs if k < h.levels) for k in range(n_levels)]

    rec: dict = {"hierarchy_seconds": time.perf_counter() - t, "certified": all(h.certified for h in hs),
                 "surfaces_nested": all(h.surfaces_nested for h in hs),
                 "n_outside": [sum(h.n_outside[k] for h in hs if k < h.levels - 1) for k in range(n_levels - 1)],
                 "fallbacks": [dict(d, body=b) for b, h in enumerate(hs) for d in h.fallbacks],
                 "faces": per_level(lambda h: [len(Fk) for _, Fk in h.surfaces]),
                 "tets": per_level(lambda h: [len(T) for _, T in h.tets]),
                 "nodes": per_level(lambda h: [len(Vt) for Vt, _ in h.tets]), "levels": n_levels,
                 "bodies": [{"faces": [len(Fk) for _, Fk in h.surfaces], "tets": [len(T) for _, T in h.tets],
                             "certified": h.certified} for h in hs],
                 "stages": summed_timings(hs), "problems": {}}
    solver, frame = args.solver, file_frame(V)
    for problem in PROBLEMS:
        r = solve_bodies(hs, frame, problem, replace(solver, accel=None))
        c = solve_bodies(hs, frame, problem, replace(solver, accel="cg"))
        rec["problems"][problem] = {
            "factor": r["factor"], "cycles": r["iterations"], "converged": r["converged"],
            "pcg_iterations": c["iterations"], "pcg_converged": c["converged"],
            "operator_complexity": r["operator_complexity"], "solve_seconds": r["seconds"],
            "pcg_seconds": c["seconds"], "solve_cpu_seconds": r.get("cpu_seconds"),
            "pcg_cpu_seconds": c.get("cpu_seconds"),
        }
    return rec


def case_cages(mesh: Path, method: str) -> dict:
    """``nestmg cages FILE --levels 3 --method M`` (the same function and clearance as ``solve``)."""
    from cagegen.build import fallback_layers
    from nestmg.cli import _bodies, _body_cages, _cage_options, _load
    from nestmg.hierarchy import build_cage_surfaces

    args = _cli_args("cages", mesh, ["--method", method])
    V, F, _ = _load(str(mesh))
    t = time.perf_counter()
    V, F, bodies = _bodies(V, F, args.repair)
    if bodies:  # `nestmg cages`' per-body path: certified when every body's cages are
        _, infos = _body_cages(bodies, args.levels, args, mesh.name, method)
        oks = [bool((i.get("verification") or {}).get("ok")) for i in infos]
        return {"seconds": time.perf_counter() - t, "certified": all(oks),
                "faces": [i["faces"] for i in infos], "fallbacks": [dict(d, body=b) for b, i in enumerate(infos)
                                                                 for d in fallback_layers(i)],
                "layers": [_layer_costs(i) for i in infos], "bodies": len(bodies),
                "min_gap": (infos[0].get("cage_options") or {}).get("min_gap")}
    layers, info = build_cage_surfaces(V, F, args.levels, method, meshing=args.meshing, cache=False,
                                       progress=False,
                                       cages=_cage_options(args, method))
    ver = info.get("verification") or {}
    return {"seconds": time.perf_counter() - t, "certified": bool(ver.get("ok")) if ver else None,
            "faces": [len(Fk) for _, Fk in layers], "fallbacks": fallback_layers(info),
            # the repair (`--repair`: the surface the wheel is given, outside its timer) within `seconds`
            "repair_seconds": (info.get("solid") or {}).get("repair_seconds", 0.0),
            "layers": _layer_costs(info),
            "min_gap": (info.get("cage_options") or {}).get("min_gap")}


def _layer_costs(info: dict) -> list[dict]:
    """Per cage layer of a backend that reports them (``nested``): seconds, the attempts that failed before
    the layer was made, and the re-inflation's Newton iterations (reverse steps, final phase): the same
    command's seconds vary from run to run, and these say whether the work did."""
    out = []
    for layer in (info.get("backend") or {}).get("layers") or []:
        r, sec = layer.get("reinflate") or {}, layer.get("seconds")
        out.append({"seconds": sec.get("total") if isinstance(sec, dict) else sec,
                    "failed_attempts": len(layer.get("failed_attempts") or []),
                    "newton_iterations": r.get("newton_iterations"), "final_iterations": r.get("final_iterations")})
    return out


def case_wheel(mesh: Path, counts: list[int]) -> dict:
    """The reference wheel at our face counts, on the normalised surface (unit diagonal, centred)."""
    import nested_cages

    V, F = _wheel_input(mesh)
    V = (V - 0.5 * (V.min(0) + V.max(0))) / float(np.linalg.norm(V.max(0) - V.min(0)))
    t = time.perf_counter()
    out = nested_cages.nested_cages(np.asfortranarray(V), np.asfortranarray(F, dtype=np.int32),
                                    num_faces=list(counts), quad_order=2, energy_expansion="None",
                                    energy_final="Volume", regular=[True] * len(counts))
    return {"seconds": time.perf_counter() - t, "faces": [len(Fk) for _, Fk in out]}


def _wheel_input(mesh: Path) -> tuple[np.ndarray, np.ndarray]:
    """The surface the wheel gets: the file's, or with ``--repair`` the one ``nestmg cages --repair`` cages
    (the same repairs in the same order: the union of crossing pieces, the hole filling or TetWild's solid,
    the cheap repairs), so both get one closed, clean solid at the same face counts."""
    if not os.environ.get(REPAIR_ENV):
        return read_surface(mesh)
    import cagegen
    from nestmg.cli import _bodies, _cage_options, _load
    from nestmg.hierarchy import _solid_input

    args = _cli_args("cages", mesh, ["--method", "nested"])
    V, F, bodies = _bodies(*_load(str(mesh))[:2], True)
    if bodies:
        raise ValueError(f"{len(bodies)} bodies after the repair: the wheel cages one solid")
    V, F = _solid_input(V, F, _cage_options(args, "nested"), args.meshing, None)[:2]
    V, F = cagegen.check_mesh(V, F, repair=True, name="input")
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


#: resolution of the warm-up sphere (:func:`_warm_up`): 536 faces
WARM_UP_RES = 8
#: modules the cage code imports inside functions, imported by :func:`_warm_up` too
LAZY_IMPORTS = ("scipy.spatial", "skimage.measure")


def _warm_up(kind: str, arg: str) -> float | None:
    """Run a ``cages`` or ``wheel`` case once on a small procedural sphere in this process, so that module
    imports and first calls are outside the timed case on both sides of the wheel ratio (the wheel's import
    already was). Returns its seconds (None for ``solve`` cases, which are not compared)."""
    if kind not in ("cages", "wheel"):
        return None
    import importlib

    from nestmg.io import save_mesh
    from nestmg.shapes import sphere

    for name in LAZY_IMPORTS:  # a sphere's cages need no envelope target, the zoo's do
        importlib.import_module(name)
    V, F = sphere(WARM_UP_RES)
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="corpus-warm-") as tmp:
        path = Path(tmp) / "warm_up_sphere.obj"
        save_mesh(path, V, F)
        try:
            if kind == "cages":
                case_cages(path, arg)
            else:
                case_wheel(path, [len(F) // 4])
        except Exception as exc:  # noqa: BLE001 -- the imports happened; the timed case reports its own failure
            print(f"[corpus] warm-up failed: {type(exc).__name__}: {exc}", file=sys.stderr)
    return time.perf_counter() - t


def _child(kind: str, mesh: Path, arg: str, result: Path) -> None:
    from nestmg.progress import enable_stage_lines

    enable_stage_lines(sys.stderr)  # the parent keeps the last lines of a case it had to stop
    warm = _warm_up(kind, arg)
    t = time.perf_counter()
    try:
        if kind == "solve":
            rec = case_solve(mesh)
        elif kind == "cages":
            rec = case_cages(mesh, arg)
        else:
            rec = case_wheel(mesh, [int(c) for c in arg.split(",")])
        rec["ok"] = True
    except Exception as exc:  # noqa: BLE001 -- every failure is a row of the table
        # the traceback without this machine's paths (the repository's files relative, the interpreter's named)
        tb = traceback.format_exc().replace(str(Path(__file__).resolve().parents[1]) + os.sep, "")
        tb = tb.replace(sys.prefix, "PYTHON").replace(str(mesh.parent), "ZOO_DIR")
        rec = {"ok": False, "error": " ".join(f"{type(exc).__name__}: {exc}".split())[:400],
               "traceback": tb[-1500:]}
    rec["repair"] = bool(os.environ.get(REPAIR_ENV))
    rec["wall_seconds"] = time.perf_counter() - t
    if warm is not None:
        rec["warm_up_seconds"] = warm
    rec["peak_mb"] = _peak_mb()
    result.write_text(json.dumps(rec, default=float))


# ----------------------------------------------------------------------------------- runner (parent)
def run_case(kind: str, mesh: Path, arg: str, timeout: float) -> dict:
    """One case in a fresh process group, killed after ``timeout`` seconds."""
    with tempfile.TemporaryDirectory(prefix="corpus-case-") as tmp:
        result = Path(tmp) / "r.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--case", kind, str(mesh), arg, str(result)]
        t = time.perf_counter()
        # one BLAS thread unless the caller says otherwise, set before the child imports numpy (a limit set
        # after the import left OpenBLAS with its threads: set-ups 6x slower on a loaded machine)
        env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
        proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                env=env)
        try:
            _, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
            last = [ln for ln in err.decode(errors="replace").splitlines() if ln.startswith("[nestmg]")][-2:]
            return {"ok": False, "error": f"timeout after {timeout:.0f} s", "last_stage_lines": last,
                    "wall_seconds": time.perf_counter() - t, "repair": bool(os.environ.get(REPAIR_ENV))}
        if result.exists():
            return json.loads(result.read_text())
        tail = err.decode(errors="replace").strip().splitlines()[-3:]
        return {"ok": False, "error": f"process ended with code {proc.returncode}: {' / '.join(tail)}"[:400],
                "wall_seconds": time.perf_counter() - t}


# ------------------------------------------------------------------------------------------- table
def _err(r: dict) -> str:
    """A case's error on one line (older records kept only the first line: the traceback has the rest)."""
    err, tb = r.get("error") or "", r.get("traceback") or ""
    if err.endswith(":") and err in tb:
        err = " ".join(tb[tb.rindex(err):].split())
    return err


def _f(x, fmt="{:.3f}") -> str:
    return "–" if x is None else fmt.format(x)


def _mark(ok: bool) -> str:
    return "" if ok else " ✗"


def solve_row(entry: dict) -> str:
    """One markdown row of the solve table."""
    s = entry.get("solve") or {}
    if not s:
        return f"| {entry['mesh']} | {entry['faces']:,} | not run | | | | | | | | |"
    if not s.get("ok"):
        mended = " with `--repair`" if s.get("repair") else ""
        took = _f(s.get("wall_seconds"), "{:.0f}")
        return (f"| {entry['mesh']} | {entry['faces']:,} | **failed**{mended} ({took} s): {_err(s)} "
                "| | | | | | | | |")
    st = s["stages"]
    probs = s["problems"]
    cells = []
    for p in PROBLEMS:
        r = probs[p]
        cells.append(f"{r['factor']:.3f}{_mark(r['factor'] <= GOALS[p])} / {r['pcg_iterations']}"
                     f"{_mark(r['pcg_iterations'] <= GOALS['pcg'])}")
    ctor = [_ctor_iterations(c) if c else None for c in (probs[p].get("constructor") for p in PROBLEMS)]
    ctor_cell = " / ".join("–" if c is None else f"{c[0]}{_mark(c[0] <= GOALS['pcg'])}"
                           + (f" ({c[1]})" if c[1] != c[0] else "") for c in ctor)
    oc = max(r["operator_complexity"] or 0 for r in probs.values())
    tets = " / ".join(f"{n / 1000:.0f}k" if n >= 1000 else str(n) for n in s["tets"])
    cert = ("yes" if s["certified"] else "**no**") + (" (`--repair`)" if s.get("repair") else "")
    fb = f" (fallback {[d['fallback'] for d in s['fallbacks']]})" if s.get("fallbacks") else ""
    return (f"| {entry['mesh']} | {entry['faces']:,} | {cert}{fb} | {tets} | {_f(st.get('cages'), '{:.0f}')} / "
            f"{_f(st.get('tets'), '{:.0f}')} / {s['wall_seconds']:.0f} | " + " | ".join(cells)
            + f" | {ctor_cell} | {oc:.2f}{_mark(oc <= GOALS['complexity'])} | {s['peak_mb'] / 1024:.1f} |")


def cages_row(entry: dict, backends: list[str]) -> str:
    """One markdown row of the cages table: certified and seconds per backend, wheel ratio."""
    cells = []
    for b in backends:
        r = entry.get(f"cages:{b}") or {}
        if not r:
            cells.append("not run")
        elif r.get("ok"):
            fb = "*" if r.get("fallbacks") else ""
            mended = " (`--repair`)" if r.get("repair") else ""
            cells.append(f"{'yes' if r['certified'] else 'no'}{fb} {math.ceil(r['seconds'])} s{mended}")  # up: against us
        else:
            mended = " with `--repair`" if r.get("repair") else ""
            cells.append(f"**fails**{mended} {_f(r.get('wall_seconds'), '{:.0f}')} s: {_err(r)[:160]}")
    w, n = entry.get("wheel") or {}, entry.get("cages:nested") or {}
    if w.get("ok") and n.get("ok"):
        ratio = f"{math.floor(10 * w['seconds'] / n['seconds']) / 10:.1f}x ({math.floor(w['seconds'])} s)"  # down
    elif w:
        ratio = f"wheel fails ({_f(w.get('wall_seconds'), '{:.0f}')} s): {w.get('error', '')[:80]}"
    else:
        ratio = "–"
    commits = entry.get("commits") or {}
    if w.get("reused_from"):
        ratio += f" (wheel run at {str(w['reused_from'])[:7]})"
    elif w and commits.get("wheel") and commits.get("wheel") != commits.get("cages:nested"):
        ratio += f" (wheel run at {str(commits['wheel'])[:7]}: not the same run)"
    faces = (entry.get("cages:nested") or {}).get("faces")
    if faces and isinstance(faces[0], list):  # several bodies: one list each
        faces = f"{len(faces)} bodies, the first {faces[0]}"
    return f"| {entry['mesh']} | {entry['faces']:,} | {faces or '–'} | " + " | ".join(cells) + f" | {ratio} |"


def _is_column(key: str) -> bool:
    return key in ("solve", "wheel") or key.startswith("cages:")


def merge_runs(docs: list[dict]) -> dict:
    """One corpus from runs over parts of a folder or over some of its columns, column by column.

    A later run's column (``solve``, ``cages:<method>``, ``wheel``) replaces the same column of an earlier
    run and keeps the others (a re-run of ``solve`` after a solver change keeps the older cage columns);
    ``commits`` records each column's commit, and ``commit`` the row's when all its columns share one.
    """
    rows: dict = {}
    for d in docs:
        for e in d["meshes"]:
            r = rows.setdefault(e["mesh"], {"commits": {}})
            given = e.get("commits") or {}
            for k, v in e.items():
                if k in ("commit", "commits"):
                    continue
                r[k] = v
                if _is_column(k):
                    r["commits"][k] = given.get(k) or e.get("commit") or d.get("commit")
    for r in rows.values():
        distinct = set(map(str, r["commits"].values()))
        r["commit"] = distinct.pop() if len(distinct) == 1 else None
    runs = list({(r["command"], str(r.get("commit"))): r for d in docs for r in _runs(d)}.values())
    # the latest run's commit first: the table marks the columns run at other commits
    return dict(docs[0], runs=runs, command=" ; ".join(dict.fromkeys(r["command"] for r in runs)),
                commit=" / ".join(dict.fromkeys(str(d.get("commit")) for d in reversed(docs))),
                # the latest run's date (ISO "YYYY-MM-DD HH:MM UTC" sorts as text), not the last file's: a
                # re-merged older run (one column put back) comes last
                date=max((str(r["date"]) for r in runs if r.get("date")), default=docs[-1].get("date")),
                timeout=docs[-1].get("timeout", docs[0].get("timeout")),
                meshes=[rows[k] for k in sorted(rows)])


def _runs(doc: dict) -> list[dict]:
    """The runs behind a corpus JSON: ``{command, commit, date}`` each (a merge lists those it merged)."""
    return doc.get("runs") or [{k: doc.get(k) for k in ("command", "commit", "date")}]


def _provenance(doc: dict) -> list[str]:
    """Markdown lines naming the commands behind the shown columns (older merged runs: the JSON's ``runs``)."""
    shown = {str(c) for e in doc["meshes"] for c in (e.get("commits") or {}).values()}
    runs = _runs(doc)
    used = [r for r in runs if str(r.get("commit")) in shown]
    if len(runs) == 1 or not used:
        return [f"Run: `{doc['command']}` at commit {doc['commit']}, {doc['date']}; "
                f"{doc['timeout']:.0f} s per case."]
    # merged runs had their own time limits: each command's --timeout (default 900 s), not the last file's
    lines = ["Runs whose columns are shown (time limit per case: the command's `--timeout`, default 900 s; each "
             "row names the commit of its columns when it differs from the first):", ""]
    lines += [f"- `{r['command']}` at {r.get('commit')}, {r.get('date')}" for r in used]
    mine = {r["command"] for r in used}
    older = len({c for r in runs for c in r["command"].split(" ; ")} - mine)
    if older:
        lines += ["", f"Columns marked \"at\" another commit come from {older} earlier runs, merged into the JSON "
                  "(its `runs`, with their commands and commits)."]
    return lines


def _at(entry: dict, columns, main: str) -> dict:
    """The row with its mesh name marked "(at X)" when the shown columns were run at another commit."""
    commits = entry.get("commits") or {}
    seen = {str(commits.get(c, entry.get("commit"))) for c in columns if c in entry}
    seen.discard("None")
    other = sorted(c for c in seen if c != main)
    if not other or "(at " in entry["mesh"]:
        return entry
    return dict(entry, mesh=f"{entry['mesh']} (at {', '.join(other)})")


def write_markdown(doc: dict, path: Path, source: Path) -> None:
    """The corpus tables (solve; cages per backend) as a markdown file, generated from the JSON."""
    b = doc["backends"]
    lines = [f"<!-- generated by `python benchmarks/corpus.py --table {source} --md {path}`; do not edit -->",
             "", "# The defaults on a folder of meshes", "",
             "`benchmarks/corpus.py FOLDER --out JSON --md PAGE` runs what a new user runs, with the defaults, on "
             "every closed surface file of a folder: `nestmg solve FILE --levels 3` (nested cages, TetWild; the "
             "three model problems as V-cycles and as MG-PCG) and `nestmg cages FILE --levels 3 --method M` for "
             "each backend, each case in its own process under a time limit (a hang or a crash is a row, not the "
             "end of the run), plus the reference `nested_cages` wheel at the same face counts (extra `bench`). "
             "Timings are wall seconds of one run on a 2-core machine; when the run was split over the two cores "
             "(one process per core, `--merge`), each case had one core and the other was busy. Since 449909b a "
             "cages or wheel case first runs once, untimed, on a 536-face sphere in its process (imports and first "
             "calls outside the clock on both sides).", "",
             *_provenance(doc), *(["", doc["summary"]] if doc.get("summary") else []), "",
             "### `nestmg solve FILE --levels 3` (defaults: nested cages, TetWild)", "",
             "Cells: V-cycle factor / MG-PCG iterations to 1e-8 (✗: above the goal "
             f"{GOALS['poisson-dirichlet']} Dirichlet, {GOALS['poisson-neumann']} Neumann and diffusion, "
             f"{GOALS['pcg']} iterations, operator complexity {GOALS['complexity']}). Seconds: cages / tets / "
             "whole case (hierarchy + 6 solves). `MultigridSolver(A, P)`: MG-PCG iterations to 1e-8 with the "
             "constructor's defaults (the problem's coarse operators and null space only; `deflate=\"auto\"` "
             "probes the coarse levels of these hierarchies, operator complexity at most 1.5) for Dirichlet / "
             "Neumann / diffusion, in brackets without the probe (`deflate=0`) where that differs (–: not "
             "recorded, e.g. multi-body files).", "",
             "| mesh | faces | certified | tets per level | seconds | Dirichlet | Neumann | diffusion | "
             "`MultigridSolver(A, P)` | op. cx | peak GB |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    skipped = []
    main = str(doc.get("commit")).split(" / ")[0]
    for e in doc["meshes"]:  # rows re-run at another commit say so
        e = _at(e, ["solve"], main)
        if "solve" in e:  # an open surface too when it was run with --repair (holes closed)
            lines.append(solve_row(e))
        elif not e["closed"]:
            skipped.append(f"{e['mesh']} ({e['skipped']})")
    if b:
        lines += ["", "### `nestmg cages FILE --levels 3 --method M`", "",
                  "Cells: certified, seconds (* a layer by a fallback). Wheel: the reference `nested_cages` "
                  "at the nested face counts, its seconds over ours.", "",
                  "| mesh | faces | nested faces | " + " | ".join(b) + " | wheel |",
                  "|---|---|---|" + "---|" * len(b) + "---|"]
        lines += [cages_row(_at(e, [f"cages:{m}" for m in b], main), b) for e in doc["meshes"]
                  if e["closed"] or any(f"cages:{m}" in e for m in b)]
    if skipped:
        lines += ["", "Not closed (skipped): " + "; ".join(skipped) + "."]
    failures = [f"- {e['mesh']} `{k}`: {_err(r)}" + (f" (last stage: {r['last_stage_lines'][-1]})"
                                                           if r.get("last_stage_lines") else "")
                for e in doc["meshes"] for k, r in e.items()
                if isinstance(r, dict) and k not in ("wheel",) and r.get("ok") is False]
    if failures:
        lines += ["", "### Cases that did not finish", "", *failures]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def _git_head() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parent,
                              capture_output=True, text=True, timeout=10).stdout.strip() or None
    except Exception:  # noqa: BLE001 -- not a git checkout
        return None


def _tree_state() -> dict:
    """The commit the case processes will import and whether tracked files differ from it (each case imports
    the source tree anew: a commit or an edit during a run changes the code of the cases after it)."""
    try:
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", ".", ":!benchmarks/results"],
                               cwd=Path(__file__).resolve().parents[1], timeout=10, check=False).returncode == 1
    except Exception:  # noqa: BLE001 -- not a git checkout
        dirty = False
    return {"commit": _git_head(), "dirty": dirty}


def _note_tree(doc: dict, entry: dict, key: str, before: dict) -> None:
    """Record, on the case ``entry[key]``, the source trees seen before and after it when either is not the
    run's clean starting commit (its process may have imported either)."""
    clean = {"commit": doc.get("commit"), "dirty": False}
    after = _tree_state()
    if before != clean or after != clean:
        entry[key]["tree"] = {"before": before, "after": after}
        print(f"[corpus] warning: {entry['mesh']} {key} ran while the source tree was "
              f"{before['commit']}{' (edited)' if before['dirty'] else ''} -> "
              f"{after['commit']}{' (edited)' if after['dirty'] else ''}, not the run's {doc.get('commit')}: "
              "run benchmarks from a clone", file=sys.stderr, flush=True)


def survey(folder: Path, names: list[str] | None) -> list[dict]:
    """One entry per surface file: name, faces, closed or the reason it is skipped."""
    out = []
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() not in MESH_EXT or (names and path.name not in names):
            continue
        try:
            F = read_surface(path)[1]
            reason = closed_reason(F)
        except Exception as exc:  # noqa: BLE001 -- an unreadable file is a row too
            F, reason = np.zeros((0, 3), int), f"unreadable: {exc}"
        out.append({"mesh": path.name, "path": str(path), "faces": len(F), "closed": not reason,
                    "skipped": reason or None})
    return out


def _earlier_wheel_rows(paths: list[Path]) -> dict:
    """``{(mesh, face counts): wheel row}`` from earlier corpus JSONs, each row marked ``reused_from``."""
    rows: dict = {}
    for p in paths:
        doc = json.loads(p.read_text())
        for e in doc["meshes"]:
            w, n = e.get("wheel"), e.get("cages:nested") or {}
            counts = (w or {}).get("counts") or (n.get("faces") or [None])[1:]
            if w and counts and None not in counts:
                rows[(e["mesh"], tuple(int(c) for c in counts))] = dict(
                    w, counts=[int(c) for c in counts], reused_from=w.get("reused_from") or doc.get("commit"))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, nargs="?")
    ap.add_argument("--out", type=Path, help="JSON written (and rewritten after every case)")
    ap.add_argument("--md", type=Path, default=None, help="markdown table written from the JSON")
    ap.add_argument("--meshes", nargs="+", default=None, help="only these file names")
    ap.add_argument("--backends", default="nested,decimate,sdf,lazy", help="comma-separated; '' for none")
    ap.add_argument("--no-solve", action="store_true")
    ap.add_argument("--wheel", action="store_true", help="run the reference wheel at our nested face counts")
    ap.add_argument("--wheel-from", type=Path, nargs="+", default=None,
                    help="reuse the wheel rows of these JSONs when they were run at the same face counts "
                         "(the wheel does not change between our commits; its runs take minutes)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per case")
    ap.add_argument("--repair", action="store_true",
                    help="pass --repair to every case (for inputs the defaults refuse; the table marks them)")
    ap.add_argument("--cage-time-budget", default=None,
                    help="pass --cage-time-budget to every case (0: no limit; e.g. to time inputs the default refuses)")
    ap.add_argument("--table", type=Path, default=None, help="only rewrite --md from this JSON")
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="merge these JSONs (runs over parts of one folder, e.g. one per core) into --out")
    ap.add_argument("--case", nargs=4, metavar=("KIND", "MESH", "ARG", "RESULT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        _child(args.case[0], Path(args.case[1]), args.case[2], Path(args.case[3]))
        return 0
    if args.merge:
        doc = merge_runs([json.loads(p.read_text()) for p in args.merge])
        args.out.write_text(json.dumps(doc, indent=1, default=float))
        args.table = args.out
    if args.table:
        doc = json.loads(args.table.read_text())
        if args.md:
            write_markdown(doc, args.md, args.table)
        return 0
    if args.folder is None or args.out is None:
        ap.error("give FOLDER and --out (or --table JSON --md FILE)")
    backends = [b for b in args.backends.split(",") if b]
    if args.repair:
        os.environ[REPAIR_ENV] = "1"  # read by the case processes (_cli_args)
    if args.cage_time_budget is not None:
        os.environ[BUDGET_ENV] = str(args.cage_time_budget)
    # the command as anyone would type it: the folder and the output named, not this machine's paths
    named = {str(args.folder): "ZOO_DIR", str(args.out): f"OUT/{args.out.name}"}
    if args.md:
        named[str(args.md)] = str(args.md) if not args.md.is_absolute() else f"OUT/{args.md.name}"
    doc = {"command": " ".join(["python", "benchmarks/corpus.py", *(named.get(a, a) for a in (argv or sys.argv[1:]))]),
           "commit": _git_head(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "timeout": args.timeout, "backends": backends, "goals": GOALS, "meshes": survey(args.folder, args.meshes)}

    earlier = _earlier_wheel_rows(args.wheel_from or [])

    def save() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=1, default=float))
        if args.md:
            write_markdown(doc, args.md, args.out)

    for entry in doc["meshes"]:
        if not entry["closed"] and not args.repair:  # --repair closes a scan's small holes: open ones are run
            continue
        path = Path(entry.pop("path"))
        cases = [] if args.no_solve else [("solve", "")]
        cases += [("cages", b) for b in backends]
        for kind, arg in cases:
            key = kind if kind == "solve" else f"cages:{arg}"
            print(f"[corpus] {entry['mesh']} {key} ...", file=sys.stderr, flush=True)
            before = _tree_state()
            entry[key] = run_case(kind, path, arg, args.timeout)
            _note_tree(doc, entry, key, before)
            r = entry[key]
            print(f"[corpus] {entry['mesh']} {key}: ok={r.get('ok')} certified={r.get('certified')} "
                  f"{r.get('wall_seconds', 0):.1f} s {r.get('error', '')}", file=sys.stderr, flush=True)
            save()
        nested = entry.get("cages:nested") or {}
        if args.wheel and nested.get("ok") and not nested.get("bodies"):  # the wheel cages one solid
            counts = [int(n) for n in nested["faces"][1:]]
            known = earlier.get((entry["mesh"], tuple(counts)))
            if known:
                entry["wheel"] = known
            else:
                before = _tree_state()
                entry["wheel"] = dict(run_case("wheel", path, ",".join(map(str, counts)), args.timeout),
                                      counts=counts)
                _note_tree(doc, entry, "wheel", before)
            save()
    for entry in doc["meshes"]:
        entry.pop("path", None)
    save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
