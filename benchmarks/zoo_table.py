"""Trust table: every mesh of a folder x every cage backend -> certified result or the error, with times.

Each cell runs in its own subprocess with a wall-clock timeout, so a slow backend (or a crash inside a
C++ library) cannot block or kill the table. A cell loads the mesh with :func:`nestmg.io.load_mesh`
(libigl for OBJ/OFF/PLY), normalises it, and calls ``cagegen.build_cages(V, F, levels, method=...)``
with the verifier on. The outcome is one of

* ``certified``: every pair verified nested (certified methods only);
* ``built, not nested`` / ``built, nested``: the ``decimate`` baseline (verified, never gated);
* ``error``: one of nestmg's error classes (``NestmgError`` subclasses), with its message;
* ``CRASH``: any other exception, or the process died (signal) -- a bug to fix;
* ``timeout``: the cell did not finish within ``--timeout`` seconds.

A method ``hierarchy:METHOD:MESHER`` runs the whole pipeline (``nestmg.build_hierarchy``, no cache):
cages, tet layers and prolongations; ``certified`` then also means no fine node outside a coarse tet
mesh (``n_outside`` all 0).

The pseudo-method ``audit`` compares the input audit after loading through libigl (what nestmg does)
and through ``trimesh.load(process=False)`` (which splits OBJ vertices along texture seams).

Results are written (atomically, after every cell) to ``--json`` and printed as a Markdown table.

Usage::

    python benchmarks/zoo_table.py ZOO_DIR --methods audit decimate nested lazy \
        --timeout 300 --json zoo_table.json --markdown zoo_table.md
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from nestmg import MeshingOptions

MESH_EXTS = (".obj", ".off", ".ply", ".stl")


def _short(msg: str, n: int = 300) -> str:
    msg = " ".join(str(msg).split())
    return msg if len(msg) <= n else msg[: n - 3] + "..."


def _audit_summary(a) -> dict:
    return {
        "ok": a.ok,
        "n_vertices": a.n_vertices,
        "n_faces": a.n_faces,
        "genus": a.genus,
        "n_components": a.n_components,
        "n_boundary_edges": a.n_boundary_edges,
        "problems": [p.split(":")[0] for p in a.problems],
    }


def run_hierarchy_cell(path: str, method: str, levels: int, mesher: str) -> dict:
    """Cages + tet layers + prolongations (``nestmg.build_hierarchy``): certified at the tet level?"""
    from cagegen import NestmgError
    from nestmg import build_hierarchy
    from nestmg.io import load_mesh, normalize
    from solvers import SolverError

    out: dict = {"mesh": Path(path).stem, "file": Path(path).name, "method": f"hierarchy:{method}:{mesher}"}
    t0 = time.perf_counter()
    try:
        V, F = load_mesh(path)
        Vn, _, _ = normalize(V)
        h = build_hierarchy(Vn, F, levels, method, meshing=MeshingOptions(mesher=mesher), cache=False,
                            progress=False)
        out["faces"] = [len(Fk) for _, Fk in h.surfaces]
        out["tets"] = [len(T) for _, T in h.tets]
        out["n_outside"] = h.n_outside
        out["certified"] = h.certified
        out["timings"] = {k: (round(v, 2) if isinstance(v, float) else v) for k, v in h.timings.items()}
        out["status"] = "certified" if h.certified else (
            "built, nested" if h.surfaces_nested and not any(h.n_outside) else "built, not nested")
    except (NestmgError, SolverError) as exc:
        out["status"] = "error"
        out["error_class"] = type(exc).__name__
        out["message"] = _short(exc)
    except Exception as exc:  # noqa: BLE001
        out["status"] = "CRASH"
        out["error_class"] = f"{type(exc).__module__}.{type(exc).__name__}"
        out["message"] = _short(exc)
    out["seconds"] = round(time.perf_counter() - t0, 2)
    return out


def run_cell(path: str, method: str, levels: int) -> dict:
    """One (mesh, method) cell in this process; returns a JSON-serialisable dict.

    ``method`` may be ``"hierarchy:<method>:<mesher>"`` for the whole pipeline (:func:`run_hierarchy_cell`).
    """
    if method.startswith("hierarchy:"):
        _, m, mesher = method.split(":")
        return run_hierarchy_cell(path, m, levels, mesher)
    from cagegen import NestmgError, audit_mesh, build_cages, repair_mesh
    from nestmg.io import load_mesh, normalize

    out: dict = {"mesh": Path(path).stem, "file": Path(path).name, "method": method}
    t0 = time.perf_counter()
    try:
        if method == "audit":
            V, F = load_mesh(path)
            Vn, _, _ = normalize(V)
            out["libigl"] = _audit_summary(audit_mesh(Vn, F, name=Path(path).name))
            import trimesh

            m = trimesh.load(path, force="mesh", process=False)
            Vt, _, _ = normalize(m.vertices)
            out["trimesh"] = _audit_summary(audit_mesh(Vt, m.faces, name=Path(path).name))
            try:  # what the documented repair makes of trimesh's reading
                Vr, Fr = repair_mesh(Vt, m.faces)
                out["trimesh_repaired"] = _audit_summary(audit_mesh(Vr, Fr, name=Path(path).name))
            except NestmgError as exc:
                out["trimesh_repaired"] = {"ok": False, "problems": [_short(exc, 80)]}
            out["status"] = "audited"
        else:
            V, F = load_mesh(path)
            Vn, _, _ = normalize(V)
            out["faces_in"] = len(F)
            layers, info = build_cages(Vn, F, levels, method=method, return_info=True)
            out["faces"] = [len(Fk) for _, Fk in layers]
            out["nested"] = info["nested"]
            out["certified"] = info["certified"]
            out["seconds_stages"] = {k: round(v, 3) for k, v in info["seconds"].items()}
            if info["certified"]:
                out["status"] = "certified"
            else:
                out["status"] = "built, nested" if info["nested"] else "built, not nested"
                ver = info.get("verification") or {}
                bad = [p for p in ver.get("pairs", []) if not p.get("ok")]
                if bad:
                    p = bad[0]
                    out["first_failing_pair"] = {k: p.get(k) for k in (
                        "fine", "coarse", "n_outside_vertices", "n_intersecting_pairs", "min_winding")}
    except NestmgError as exc:
        out["status"] = "error"
        out["error_class"] = type(exc).__name__
        out["message"] = _short(exc)
    except Exception as exc:  # noqa: BLE001 - the point of the table is to find these
        out["status"] = "CRASH"
        out["error_class"] = f"{type(exc).__module__}.{type(exc).__name__}"
        out["message"] = _short(exc)
    out["seconds"] = round(time.perf_counter() - t0, 2)
    return out


def run_cell_subprocess(path: Path, method: str, levels: int, timeout: float) -> dict:
    """Run :func:`run_cell` in a child process (own process group) with a wall-clock timeout."""
    cmd = [sys.executable, os.path.abspath(__file__), "--cell", str(path), method, "--levels", str(levels)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the child and anything it started
        proc.communicate()
        return {"mesh": path.stem, "file": path.name, "method": method, "status": "timeout",
                "message": f"no result within {timeout:g} s", "seconds": round(time.perf_counter() - t0, 1)}
    for line in reversed(stdout.strip().splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    return {"mesh": path.stem, "file": path.name, "method": method, "status": "CRASH",
            "message": f"process exited with code {proc.returncode}: {_short(stderr[-500:])}",
            "seconds": round(time.perf_counter() - t0, 1)}


def cell_text(c: dict) -> str:
    """Short Markdown text of one cell."""
    s = c["status"]
    t = f"{c.get('seconds', 0):.1f} s"
    if s == "audited":
        def one(a):
            return "closed, ok" if a["ok"] else ", ".join(a["problems"])
        txt = f"libigl: {one(c['libigl'])}; trimesh: {one(c['trimesh'])}"
        if "trimesh_repaired" in c and not c["trimesh"]["ok"]:
            txt += f"; trimesh + repair: {one(c['trimesh_repaired'])}"
        return txt
    if s in ("certified", "built, nested", "built, not nested"):
        if "tets" in c:
            return f"**{s}** {c['tets']} tets, n_outside {c['n_outside']}, {t}"
        return f"**{s}** {c['faces']} faces, {t}"
    if s == "error":
        msg = c["message"].replace("input is not a usable closed surface: - ", "").split(" - ")[0]
        return f"{c['error_class']}: {_short(msg, 110)} ({t})"
    return f"**{s}**: {c.get('message', '')} ({t})"


def markdown(results: list[dict], methods: list[str]) -> str:
    """Markdown table: one row per mesh, one column per method."""
    meshes = list(dict.fromkeys(c["file"] for c in results))
    by = {(c["file"], c["method"]): c for c in results}
    lines = ["| mesh | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for m in meshes:
        cells = [cell_text(by[(m, k)]).replace("|", "/") if (m, k) in by else "" for k in methods]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", nargs="?", default=os.environ.get("NESTMG_ZOO"),
                    help="folder of meshes (default: $NESTMG_ZOO; not needed with --merge)")
    ap.add_argument("--methods", nargs="+", default=["audit", "decimate", "nested", "lazy"],
                    help="cage methods, 'audit', or 'hierarchy:METHOD:MESHER' (whole pipeline)")
    ap.add_argument("--meshes", nargs="+", default=None, help="mesh stems (default: every mesh file)")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per cell")
    ap.add_argument("--json", default="zoo_table.json")
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="only render: merge the cells of earlier --json outputs (later files win) into a table")
    ap.add_argument("--cell", nargs=2, metavar=("MESH", "METHOD"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.merge:
        cells: dict = {}
        for f in args.merge:
            for c in json.loads(Path(f).read_text())["cells"]:
                cells[(c["file"], c["method"])] = c
        methods = list(dict.fromkeys(m for _, m in cells)) if args.methods == ap.get_default("methods") \
            else args.methods
        print(markdown(sorted(cells.values(), key=lambda c: c["file"]), methods))
        return 0

    if args.cell:
        print(json.dumps(run_cell(args.cell[0], args.cell[1], args.levels)), flush=True)
        return 0

    if args.zoo is None:
        ap.error("give the mesh folder ZOO_DIR (or set NESTMG_ZOO)")
    from nestmg.cache import atomic_write_bytes

    zoo = Path(args.zoo)
    files = sorted(p for p in zoo.iterdir() if p.suffix.lower() in MESH_EXTS)
    if args.meshes:
        files = [p for p in files if p.stem in set(args.meshes)]
    results: list[dict] = []
    meta = {"zoo": str(zoo), "levels": args.levels, "timeout": args.timeout, "methods": args.methods}
    for method in args.methods:  # column by column: the fast columns are complete first
        for p in files:
            c = run_cell_subprocess(p, method, args.levels, args.timeout)
            results.append(c)
            print(f"[zoo_table] {p.name:<22} {method:<9} {cell_text(c)}", file=sys.stderr, flush=True)
            atomic_write_bytes(Path(args.json), json.dumps({**meta, "cells": results}, indent=1).encode())
    table = markdown(results, args.methods)
    if args.markdown:
        atomic_write_bytes(Path(args.markdown), (table + "\n").encode())
    print(json.dumps({**meta, "cells": results}))
    print(table, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
