"""Benchmark the ``sdf`` cage backend beside ``nested`` and ``lazy`` (and optionally the wheel) on a mesh zoo.

Usage::

    nice -n 10 python benchmarks/cages_sdf.py MESH_DIR --out DIR [--methods sdf,nested,lazy] [--wheel]
                                   [--levels 3] [--timeout 600] [--only bunny.off ...] [--tag NAME]
                                   [--sdf-opt c=0.008 ...]
    python benchmarks/cages_sdf.py --table RUN.json   # Markdown table of a benchmarks/cages.py JSON

Every closed mesh of ``MESH_DIR`` (open ones are skipped, as in ``benchmarks/cages.py``) gets the same
face counts for every method (``cagegen.default_face_counts``: 4x fewer faces per layer). Each run is
a subprocess with a timeout. Per method and mesh the JSON records success / error, wall and CPU
seconds (in total and, for ``sdf``, per layer and phase), the achieved face counts, the verdict and
figures of :func:`cagegen.verify_nesting` (min gap, min winding, ...), and per layer: max distance to
the input (Hausdorff) and mean distance of the cage to the input (area-weighted, centroid and edge-
midpoint rule) over the input's bounding-box diagonal, volume ratio to the input, genus, smallest
angle, MIPS mean / max (w.r.t. equilateral triangles; 2 is perfect). The 1-minute load average is
recorded before and after each run (the machine is shared). Writes ``DIR/<tag>.json``; the JSON is
also printed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from exp_common import (in_subprocess, is_closed, layer_figures, put_layers, read_mesh, run_wheel,
                        verify_layers)

MESH_EXT = (".off", ".obj", ".ply", ".stl")
SDF_OPTS: dict = {}


def _details(method: str, info: dict) -> dict:
    """Per-layer phases of an ``sdf`` run, recovery of a ``nested`` one, per-layer seconds."""
    if method == "sdf":
        return {"per_layer": [{
            "seconds": li["seconds"], "c_used": li["c_used"], "attempts": li["attempts"],
            "prepass": li["prepass"], "simplify": li["simplify"],
            "optimize": {k: v for k, v in li["optimize"].items() if k != "rejected_reason"},
            "optimized_cage_kept": li["optimize"].get("certified", False),
            "genus_envelope": li["genus_envelope"], "envelope_faces": li["envelope"]["n_faces"],
            "n_active": li["envelope"]["n_active"],
            "tighten": li.get("tighten", {"ran": False}),
            "bridge_retry": li.get("bridge_retry")} for li in info["layers"]]}
    if method == "nested":
        return {"recovery": info.get("recovery", []),
                "per_layer_seconds": [li["seconds"].get("total") for li in info["layers"]]}
    if method == "lazy":
        return {"per_layer_seconds": [li["seconds"] for li in info["layers"]]}
    return {}


def _run(method: str):
    """Runner of a registered cage backend (``SDF_OPTS`` for sdf) for :func:`in_subprocess`."""
    def run(path: str, counts: list[int], q) -> None:
        def build(V, F):
            from cagegen import build_cages

            opts = dict(SDF_OPTS) if method == "sdf" else {}
            # build_cages loops over the layers of a per-layer backend (sdf, lazy, decimate); the layers
            # are verified afterwards (verify_layers), not by it
            layers, info = build_cages(V, F, method=method, face_counts=counts, verify=False,
                                       return_info=True, **opts)
            return layers[1:], info["backend"]

        put_layers(q, path, build, lambda info: _details(method, info))
    return run


def _write(args, methods, skipped, results) -> dict:
    doc = {"mesh_dir": str(args.mesh_dir), "methods": methods, "levels": args.levels, "sdf_options": SDF_OPTS,
           "timeout": args.timeout, "skipped_open": skipped, "results": results}
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{args.tag}.json").write_text(json.dumps(doc, indent=1, default=float))
    return doc


def _fmt(xs, f):
    return " / ".join("--" if x is None else format(x, f) for x in xs)


def markdown_table(doc: dict, methods=("sdf", "nested", "lazy", "wheel")) -> str:
    """Markdown table (one row per mesh and method) of a ``benchmarks/cages.py`` JSON.

    Usage: ``python benchmarks/cages_sdf.py --table RUN.json``. Columns: wall s (CPU s) for all layers,
    wall s per layer where the backend reports it, then per layer (finest first) max / mean distance
    to the input in % of its diagonal, volume ratio, genus (input genus in brackets), smallest angle, MIPS
    mean / max, and the verifier's verdict with the min gap / diagonal per pair.
    """
    head = ("| mesh | faces | cage faces | method | wall s (CPU s) | s per layer | max dist % | mean dist % | "
            "vol. ratio | genus (input) | min angle ° | MIPS mean | MIPS max | certified, min gap / diag |")
    lines = [head, "|" + "---|" * 14]
    for r in doc["results"]:
        for m in methods:
            res = r.get(m)
            if res is None:
                continue
            cf = _fmt(res.get("face_counts") or r["face_counts"], "d")
            if not res.get("ok"):
                err = " ".join((res.get("error") or "").split())[:160].replace("|", "/")
                lines.append(f"| {r['mesh']} | {r['n_faces']} | {cf} | {m} | -- ({res.get('seconds', 0):.1f}) | | | | "
                             f"| | | | | fails: {err} |")
                continue
            L = res["layers"]
            per = res.get("per_layer_seconds")
            per_s = _fmt(per, ".1f") if per else ""
            cpu = res.get("cpu_seconds")
            ver = res["verification"]
            gaps = _fmt([q.get("min_gap_rel") for q in ver["pairs"]], ".1e")
            lines.append(
                f"| {r['mesh']} | {r['n_faces']} | {cf} | {m} | {res['seconds']:.1f} "
                f"({'--' if cpu is None else format(cpu, '.1f')}) | {per_s} | "
                f"{_fmt([100 * x['max_distance_relative'] for x in L], '.2f')} | "
                f"{_fmt([100 * x['mean_distance_relative'] for x in L], '.2f')} | "
                f"{_fmt([x['volume_ratio'] for x in L], '.3f')} | "
                f"{_fmt([x['genus'] for x in L], 'd')} ({r.get('input_genus', '?')}) | "
                f"{_fmt([x['min_angle_deg'] for x in L], '.1f')} | {_fmt([x['mips_mean'] for x in L], '.2f')} | "
                f"{_fmt([x['mips_max'] for x in L], '.1f')} | {'yes' if ver['ok'] else 'NO'}, {gaps} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--table":
        for f in argv[1:]:
            print(markdown_table(json.loads(Path(f).read_text())))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh_dir")
    ap.add_argument("--out", required=True)
    ap.add_argument("--methods", default="sdf,nested,lazy")
    ap.add_argument("--wheel", action="store_true", help="also run the nested-cages wheel (slow)")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--only", action="append", default=None)
    ap.add_argument("--tag", default="cages_sdf")
    ap.add_argument("--sdf-opt", action="append", default=[], help="key=value passed to the sdf backend")
    args = ap.parse_args(argv)
    for kv in args.sdf_opt:
        k, v = kv.split("=", 1)
        SDF_OPTS[k] = json.loads(v)
    from cagegen import default_face_counts

    methods = [m for m in args.methods.split(",") if m] + (["wheel"] if args.wheel else [])
    paths = sorted(p for p in Path(args.mesh_dir).iterdir() if p.suffix.lower() in MESH_EXT)
    if args.only:
        paths = [p for p in paths if p.name in args.only]
    paths.sort(key=lambda p: len(read_mesh(p)[1]))  # smallest first: a cut-short run still covers many meshes
    results, skipped = [], []
    for p in paths:
        V, F = read_mesh(p)
        ok, why = is_closed(F)
        if not ok:
            skipped.append({"mesh": p.name, "reason": why})
            continue
        try:
            counts = default_face_counts(len(F), args.levels)
        except Exception as exc:  # noqa: BLE001
            counts = default_face_counts(len(F), 2)
            print(f"{p.name}: {exc}; using {counts}", file=sys.stderr)
        row = {"mesh": p.name, "n_faces": len(F), "face_counts": counts}
        for m in methods:
            load0 = os.getloadavg()[0]
            fn = run_wheel if m == "wheel" else _run(m)
            res = in_subprocess(fn, p, counts, args.timeout)
            out = {k: v for k, v in res.items() if k not in ("layers", "traceback")}
            if res.get("ok"):
                layers = res["layers"]
                out["face_counts"] = [len(b) for _, b in layers]
                out["exact_face_counts"] = out["face_counts"] == counts
                out["verification"] = verify_layers(V, F, layers)
                out["layers"] = layer_figures(V, F, layers)
            elif "traceback" in res:
                out["traceback"] = res["traceback"]
            out["loadavg_1min"] = [load0, os.getloadavg()[0]]
            row[m] = out
            print(f"{p.name} {m}: ok={out.get('ok')} {out.get('seconds', 0):.1f} s "
                  f"{out.get('error', '')}", file=sys.stderr, flush=True)
        results.append(row)
        _write(args, methods, skipped, results)  # after every mesh: a long run leaves usable partial results
    doc = _write(args, methods, skipped, results)
    print(json.dumps(doc, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
