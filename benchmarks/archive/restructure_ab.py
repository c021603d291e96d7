"""Behaviour unchanged by a restructuring? Hashes of cages, tets, P and solves at a commit; A/B verdicts.

Issue 28 restructured nestmg without meaning to change any result. This script fingerprints what the
pipeline computes at whatever ``nestmg`` is importable (put a checkout of the commit on ``PYTHONPATH``),
so the same command run at a merge's first parent and at the merge tells whether that step changed
behaviour. Per input mesh and cage method it records SHA-256 prefixes of

* the certified cage surfaces built with the TetWild clearance (``mesher="tetwild"``; the cages only:
  TetWild itself is not bitwise reproducible run to run),
* the whole TetGen pipeline (``build_hierarchy(..., mesher="tetgen")``): cage surfaces, tets per level,
  prolongations P (CSR arrays) and the certification flag,
* residual histories, convergence factors and iteration counts of Poisson-Dirichlet and Poisson-Neumann
  solves on that hierarchy, by the V-cycle and by MG-PCG (``solve_on_hierarchy`` defaults otherwise).

It speaks both the API before issue 28's typed options (keywords ``face_counts=``, ``mesher=``, ``accel=``)
and after it (``SizingOptions`` / ``MeshingOptions`` / ``SolverOptions``), chosen by
``hasattr(nestmg, "SizingOptions")``; what is hashed is the same in both.

Reproducibility needs ``NESTMG_MESH_TIME_LIMIT=none`` (TetGen's time-limited exact mode depends on the
clock) and one ipctk thread (its parallel reductions are not bitwise reproducible; set here). Run::

    export NESTMG_MESH_TIME_LIMIT=none OMP_NUM_THREADS=1
    PYTHONPATH=CHECKOUT python benchmarks/archive/restructure_ab.py run ZOO_DIR \\
        --meshes bunny.off spot.obj gargo_1000.off plate_holes.stl fandisk.obj --out BEFORE.json
    python benchmarks/archive/restructure_ab.py compare BEFORE.json[,MORE.json] AFTER.json[,MORE.json] \\
        --step SHA --out ab_SHA.json
    python benchmarks/archive/restructure_ab.py table ab_*.json    # the docs' step x input table
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import time
from pathlib import Path

import numpy as np

PROBLEMS = ("poisson-dirichlet", "poisson-neumann")
ACCELS = (None, "cg")
TIMING_KEYS = {"seconds"}  # recorded, never compared


def digest(*arrays: np.ndarray) -> str:
    """SHA-256 prefix (16 hex digits) of arrays' dtypes, shapes and bytes, in order."""
    m = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        m.update(str(a.dtype).encode() + str(a.shape).encode())
        m.update(a.tobytes())
    return m.hexdigest()[:16]


def _flat(pairs: list) -> list[np.ndarray]:
    return [a for pair in pairs for a in pair]


def _csr(P: list) -> list[np.ndarray]:
    return [a for p in P for a in (p.indptr, p.indices, p.data)]


def cage_fingerprint(nestmg, V: np.ndarray, F: np.ndarray, levels: int, method: str) -> dict:
    """Cage surfaces built with the TetWild clearance (no TetWild run): hashes, certification, faces."""
    from nestmg.hierarchy import build_cage_surfaces

    if hasattr(nestmg, "SizingOptions"):
        S, info = build_cage_surfaces(V, F, levels, method, sizing=nestmg.SizingOptions(),
                                      meshing=nestmg.MeshingOptions(mesher="tetwild"), cache=False,
                                      progress=False)
    else:
        S, info = build_cage_surfaces(V, F, levels, method=method, mesher="tetwild", cache=False,
                                      progress=False)
    return {"surfaces": digest(*_flat(S)), "layers": [digest(*VF) for VF in S],
            "certified": info.get("certified"), "faces": [len(f) for _, f in S]}


def _solve(nestmg, tets: list, P: list, problem: str, accel: str | None) -> dict:
    if hasattr(nestmg, "SolverOptions"):
        r = nestmg.solve_on_hierarchy(tets, P, problem, nestmg.SolverOptions(accel=accel), cost=False)
    else:
        r = nestmg.solve_on_hierarchy(tets, P, problem, accel=accel, cost=False)
    return {"residuals": digest(np.asarray(r["residuals"], dtype=float)), "factor": float(r["factor"]),
            "iterations": int(r["iterations"])}


def hierarchy_fingerprint(nestmg, V: np.ndarray, F: np.ndarray, levels: int, method: str) -> dict:
    """The TetGen pipeline: surfaces, tets and P per level, certification, and the four solves."""
    if hasattr(nestmg, "SizingOptions"):
        h = nestmg.build_hierarchy(V, F, levels, method, meshing=nestmg.MeshingOptions(mesher="tetgen"),
                                   cache=False, progress=False)
    else:
        h = nestmg.build_hierarchy(V, F, levels, method=method, mesher="tetgen", cache=False, progress=False)
    out = {"surfaces": digest(*_flat(h.surfaces)), "tets": digest(*_flat(h.tets)),
           "tets_per_level": [digest(*VT) for VT in h.tets], "P": digest(*_csr(h.P)),
           "P_per_level": [digest(*_csr([p])) for p in h.P], "certified": bool(h.certified),
           "n_tets": [int(len(T)) for _, T in h.tets], "solves": {}}
    tets = h.tets_in("normalized")
    for problem in PROBLEMS:
        for accel in ACCELS:
            out["solves"][f"{problem}/{accel or 'V'}"] = _solve(nestmg, tets, h.P, problem, accel)
    return out


def _guarded(fingerprint, *args) -> dict:
    """A fingerprint, or the error that ended it (a failure is behaviour too: it is compared like a hash)."""
    try:
        return fingerprint(*args)
    except Exception as exc:  # noqa: BLE001 -- any failure is recorded and compared, the run goes on
        return {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"}


def _commit_of(module) -> str:
    """Commit of the checkout a module was imported from ('unknown' outside git)."""
    folder = Path(module.__file__).resolve().parent
    r = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (r.stdout.strip() or "unknown") + ("-dirty" if dirty else "")


def _inputs(zoo: Path, meshes: list[str], shapes: list[str]):
    import nestmg
    from nestmg import shapes as procedural

    for name in shapes:
        yield f"shape:{name}", getattr(procedural, name)()
    for name in meshes:
        yield name, nestmg.load_mesh(str(zoo / name))


def _command(args: argparse.Namespace) -> str:
    """The run's command with no path of this machine (ZOO_DIR, OUT.json)."""
    parts = ["python benchmarks/archive/restructure_ab.py run ZOO_DIR", "--meshes", *args.meshes]
    parts += ["--shapes", *args.shapes] if args.shapes else []
    parts += ["--methods", ",".join(args.methods), "--levels", str(args.levels), "--out OUT.json"]
    return " ".join(parts)


def run(args: argparse.Namespace) -> dict:
    """Fingerprint every input x method at the importable nestmg; writes ``args.out`` after each case."""
    import ipctk

    import nestmg

    ipctk.set_num_threads(1)  # ipctk's parallel reductions are not bitwise reproducible across runs
    res = {"commit": _commit_of(nestmg), "api": "typed" if hasattr(nestmg, "SizingOptions") else "keywords",
           "command": _command(args),
           "levels": args.levels, "cases": {}}
    for name, (V, F) in _inputs(args.zoo, args.meshes, args.shapes):
        for method in args.methods:
            t = time.perf_counter()
            case = {"cages_tetwild_gap": _guarded(cage_fingerprint, nestmg, V, F, args.levels, method),
                    "hierarchy_tetgen": _guarded(hierarchy_fingerprint, nestmg, V, F, args.levels, method)}
            case["seconds"] = round(time.perf_counter() - t, 1)
            res["cases"][f"{name}/{method}"] = case
            h = case["hierarchy_tetgen"]
            said = h.get("error") or (f"certified {h['certified']}, tets {h['n_tets']}, surfaces "
                                      f"{h['surfaces']}, P {h['P']}")
            print(f"{res['commit'][:7]} {name}/{method}: {case['seconds']} s, {said}", flush=True)
            args.out.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
    return res


def _strip(x):
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in TIMING_KEYS}
    return x


def _differences(a, b, prefix: str = "") -> list[str]:
    """Paths of the leaves where two fingerprints differ (timings ignored)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k in TIMING_KEYS:
                continue
            out += _differences(a.get(k), b.get(k), f"{prefix}/{k}" if prefix else k)
        return out
    return [] if a == b else [prefix]


def merge_runs(paths: str) -> dict:
    """Runs of one commit (comma-separated files, e.g. one per cage method) as one run."""
    runs = [json.loads(Path(p).read_text()) for p in paths.split(",")]
    if len({r["commit"] for r in runs}) != 1:
        raise SystemExit(f"runs of different commits cannot be merged: {paths}")
    out = dict(runs[0], command=[r["command"] for r in runs], cases={})
    for r in runs:
        out["cases"].update(r["cases"])
    return out


def compare(args: argparse.Namespace) -> dict:
    """Case by case verdict of two runs: 'identical' or the differing fields."""
    before, after = merge_runs(args.before), merge_runs(args.after)
    verdict = {}
    for case in sorted(set(before["cases"]) | set(after["cases"])):
        diff = _differences(before["cases"].get(case), after["cases"].get(case))
        verdict[case] = "identical" if not diff else "different: " + ", ".join(diff)
    out = {"step": args.step, "before": before, "after": after, "verdict": verdict,
           "all_identical": all(v == "identical" for v in verdict.values())}
    args.out.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    for case, v in verdict.items():
        print(f"{args.step} {case}: {v}")
    return out


def _mesh_verdict(verdict: dict, mesh: str) -> str:
    cases = {k: v for k, v in verdict.items() if k.rsplit("/", 1)[0] == mesh}
    if all(v == "identical" for v in cases.values()):
        return "identical"
    fields = sorted({"/".join(f.split("/")[:2]) for v in cases.values() if v != "identical"
                     for f in v.removeprefix("different: ").split(", ")})
    return "different (" + ", ".join(fields) + ")"


def table(paths: list[Path], method: str | None = None) -> str:
    """Markdown table step x input -> identical / different (what), from ``compare`` outputs.

    With ``method`` only that cage method's cases count; a step without them is left out.
    """
    runs = [json.loads(Path(p).read_text()) for p in paths]
    if method:
        runs = [dict(r, verdict={k: v for k, v in r["verdict"].items() if k.endswith(f"/{method}")})
                for r in runs]
        runs = [r for r in runs if r["verdict"]]
    meshes = list(dict.fromkeys(k.rsplit("/", 1)[0] for r in runs for k in r["verdict"]))
    rows = ["| step | before -> after | " + " | ".join(meshes) + " |", "|---" * (len(meshes) + 2) + "|"]
    for r in runs:
        pair = f"{r['before']['commit'][:7]} -> {r['after']['commit'][:7]}"
        cells = [_mesh_verdict(r["verdict"], m) for m in meshes]
        rows.append(f"| {r['step']} | {pair} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="fingerprint the importable nestmg")
    r.add_argument("zoo", type=Path, help="folder of the meshes (ZOO_DIR)")
    r.add_argument("--meshes", nargs="*", default=["bunny.off", "spot.obj", "gargo_1000.off",
                                                   "plate_holes.stl", "fandisk.obj"])
    r.add_argument("--shapes", nargs="*", default=[], help="procedural shapes (nestmg.shapes names)")
    r.add_argument("--methods", type=lambda s: s.split(","), default=["nested"])
    r.add_argument("--levels", type=int, default=3)
    r.add_argument("--out", type=Path, required=True)
    c = sub.add_parser("compare", help="A/B verdict of two runs")
    c.add_argument("before", help="run JSON of the commit before (several: comma-separated)")
    c.add_argument("after", help="run JSON of the commit after (several: comma-separated)")
    c.add_argument("--step", required=True, help="the step's name, e.g. the merge commit")
    c.add_argument("--out", type=Path, required=True)
    t = sub.add_parser("table", help="Markdown table of compare outputs")
    t.add_argument("verdicts", type=Path, nargs="+")
    t.add_argument("--method", help="only this cage method's cases")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args)
    elif args.cmd == "compare":
        compare(args)
    else:
        print(table(args.verdicts, args.method))


if __name__ == "__main__":
    main()
