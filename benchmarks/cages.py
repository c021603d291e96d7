"""Benchmark the cage backends (``nested``, ``sdf``, ``lazy``) against the reference wheel ``nested-cages`` 0.1.0.

Usage::

    python benchmarks/cages.py MESH_DIR --out DIR [--timeout 300] [--levels 3] [--no-wheel]
                               [--counts bunny.off=1000,250 ...] [--only gargo.off ...]
                               [--methods nested,sdf,lazy] [--tag cages] [--wheel-timeout 180] [--audit]
                               [--counts none]

``--audit`` runs :func:`cagegen.audit.audit_mesh` (self-intersections included) on every closed input: a
refused input (e.g. the self-intersecting cow) is recorded under ``refused_by_audit``, only ``sdf`` (which
audits its own input) runs on it, and the cases run smallest first. ``--wheel-timeout`` gives the slow
wheel its own timeout; ``--counts none`` drops the default extra case. Each row records the input genus.

For every closed mesh of ``MESH_DIR`` (open ones are detected from their boundary edges and
skipped), both methods get the same input and face counts (default: 4x fewer faces per layer,
``cagegen.default_face_counts``; plus the cases given with ``--counts``, by default the reference's
known failure ``bunny.off=1000,250``). Each run is a subprocess with a timeout. For each method and
mesh the JSON records: success / error, wall and CPU seconds (nested: per phase; sdf, lazy: per layer),
achieved face counts, the verdict of :func:`cagegen.verify_nesting` with its figures (min gap, min
winding), and per layer (``layers``): max distance (Hausdorff) and mean distance of the cage to the input
(area-weighted, centroid + edge-midpoint rule) over the input's bounding-box diagonal, volume ratio,
genus, smallest angle, MIPS mean / max w.r.t. equilateral triangles (2 = perfect); ``tightness`` keeps
the older volume ratio + Hausdorff pair. The 1-minute load average before and after each run is
recorded (shared machine). The time ratio wheel / nested is given where both finished. Writes
``DIR/<tag>.json`` and ``DIR/<tag>.png``; the JSON is also printed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from exp_common import (in_subprocess, is_closed, layer_figures, put_layers, read_mesh, run_wheel,
                        verify_layers)

MESH_EXT = (".off", ".obj", ".ply", ".stl")


def _tightness(V, F, layers) -> list[dict]:
    import igl

    from cagegen._geometry import signed_volume

    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    vol0 = signed_volume(V, F)
    out = []
    for Vk, Fk in layers:
        out.append({
            "n_faces": len(Fk),
            "volume_ratio": float(signed_volume(Vk, Fk) / vol0),
            "hausdorff_relative": float(igl.hausdorff(Vk, Fk, V, F)) / diag,
        })
    return out


def _nested_details(info: dict) -> dict:
    """Per-phase and per-layer seconds, recovery and clearance of a ``nested`` run."""
    phases: dict = {}
    for li in info["layers"]:
        for k, v in li["seconds"].items():
            if k != "total":
                phases[k] = phases.get(k, 0.0) + float(v)
    return {"per_layer_seconds": [li["seconds"].get("total") for li in info["layers"]],
            "seconds_per_phase": phases, "recovery": info["recovery"],
            "min_gap_relative": [li["min_gap_relative"] for li in info["layers"]]}


def _run_ours(path: str, counts: list[int], q) -> None:
    """Runner of ``nested`` (:func:`cagegen.nested.nested_backend`) for :func:`in_subprocess`."""
    def build(V, F):
        from cagegen.nested import nested_backend

        return nested_backend(V, F, counts, progress=False)

    put_layers(q, path, build, _nested_details)


def _backend_details(method: str, info: dict) -> dict:
    """Per-layer seconds (and the sdf phases) of a registered backend's run."""
    per = info.get("layers", [])
    res = {"per_layer_seconds": [li["seconds"]["total"] if isinstance(li.get("seconds"), dict)
                                 else li.get("seconds") for li in per]}
    if method == "sdf":
        res["genus_changes"] = info.get("genus_changes", [])
        res["per_layer"] = [{
            "seconds": li["seconds"], "c_used": li["c_used"], "attempts": li["attempts"],
            "grids_tried": li["envelope"].get("grids_tried"), "n_active": li["envelope"]["n_active"],
            "envelope_faces": li["envelope"]["n_faces"], "genus_envelope": li["genus_envelope"],
            "prepass": li["prepass"], "simplify": li["simplify"],
            "optimized_cage_kept": li["optimize"].get("certified", False),
            "optimize_steps": li["optimize"].get("steps"),
            "bridge_retry": li.get("bridge_retry")} for li in per]
    return res


def _run_backend(method: str):
    """Runner of a registered cage backend (``sdf``, ``lazy``, ...) for :func:`in_subprocess`."""
    def run(path: str, counts: list[int], q) -> None:
        def build(V, F):
            from cagegen import build_cages

            # build_cages loops over the layers of a per-layer backend (sdf, lazy, decimate); the layers
            # are verified afterwards (_summarise), not by it
            layers, info = build_cages(V, F, method=method, face_counts=counts, verify=False,
                                       return_info=True)
            return layers[1:], info["backend"]

        put_layers(q, path, build, lambda info: _backend_details(method, info))
    return run


def _git_head() -> str | None:
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent, capture_output=True,
                              text=True, timeout=10).stdout.strip() or None
    except Exception:  # noqa: BLE001 -- not a git checkout
        return None


def _children_cpu() -> float:
    """CPU seconds (user + system) of the finished subprocesses of this run."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _summarise(V, F, res: dict, counts=()) -> dict:
    out = {k: v for k, v in res.items() if k not in ("layers", "traceback")}
    if res.get("ok"):
        layers = res["layers"]
        out["face_counts"] = [len(b) for _, b in layers]
        out["exact_face_counts"] = out["face_counts"] == list(counts)
        out["verification"] = verify_layers(V, F, layers)
        out["tightness"] = _tightness(V, F, layers)
        out["layers"] = layer_figures(V, F, layers)
    return out


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [f"{r['mesh']}\n{r['face_counts']}" for r in results]
    x = np.arange(len(results))
    fig, axes = plt.subplots(1, 3, figsize=(17, 5))

    def val(r, m, key, layer=0):
        mr = r.get(m) or {}
        if not mr.get("ok"):
            return np.nan
        if key == "seconds":
            return mr["seconds"]
        return mr["tightness"][layer][key]

    for ax, key, title in [(axes[0], "seconds", "seconds (log)"),
                           (axes[1], "volume_ratio", "layer-1 volume / input volume"),
                           (axes[2], "hausdorff_relative", "layer-1 Hausdorff / bbox diagonal")]:
        ours = [val(r, "nested", key) for r in results]
        wheel = [val(r, "wheel", key) for r in results]
        ax.bar(x - 0.2, ours, 0.4, label="nestmg nested")
        ax.bar(x + 0.2, wheel, 0.4, label="nested-cages wheel")
        for i, r in enumerate(results):
            for m, dx in (("nested", -0.2), ("wheel", 0.2)):
                mr = r.get(m) or {}
                if mr and not mr.get("ok"):
                    ax.text(i + dx, 0, "fail", rotation=90, ha="center", va="bottom", color="red", fontsize=8)
                elif mr and not mr.get("verification", {}).get("ok", True):
                    ax.text(i + dx, 0, "invalid", rotation=90, ha="center", va="bottom", color="red", fontsize=8)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=60, fontsize=7)
        ax.set_title(title)
        if key == "seconds" and np.nanmax(np.r_[ours, wheel, 0.0]) > 0:
            ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh_dir")
    ap.add_argument("--out", required=True)
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per mesh and method")
    ap.add_argument("--wheel-timeout", type=float, default=None,
                    help="seconds per mesh for the wheel (default: --timeout)")
    ap.add_argument("--audit", action="store_true",
                    help="audit every closed input (cagegen.audit.audit_mesh, self-intersections included); a "
                         "refused input is recorded as such and only sdf (which audits its own input) runs on it")
    ap.add_argument("--levels", type=int, default=3, help="layers including the input (default 3)")
    ap.add_argument("--counts", action="append", default=None,
                    help="extra case NAME=c1,c2,... (default: bunny.off=1000,250; 'none': no extra case)")
    ap.add_argument("--only", action="append", default=None, help="restrict to these file names")
    ap.add_argument("--no-wheel", action="store_true")
    ap.add_argument("--no-default", action="store_true", help="run only the --counts cases")
    ap.add_argument("--methods", default="nested,sdf,lazy",
                    help="comma-separated backends (nested, sdf, lazy, ...); the wheel is added unless --no-wheel")
    ap.add_argument("--tag", default="cages", help="output names DIR/<tag>.json and DIR/<tag>.png")
    args = ap.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]

    from cagegen import LevelsError, default_face_counts

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extra = args.counts if args.counts is not None else ["bunny.off=1000,250"]
    extra = [s for s in extra if s and s != "none"]
    cases = []
    files = sorted(p for p in Path(args.mesh_dir).iterdir() if p.suffix.lower() in MESH_EXT)
    skipped, refused = [], []
    for p in files:
        if args.no_default or (args.only and p.name not in args.only):
            continue
        V, F = read_mesh(p)
        closed, why = is_closed(F)
        if not closed:
            skipped.append({"mesh": p.name, "reason": why})
            continue
        if args.audit:
            from cagegen.audit import audit_mesh

            t_a = time.perf_counter()
            a = audit_mesh(V, F, name=p.name)
            if not a.ok:
                refused.append({"mesh": p.name, "n_faces": len(F), "problems": [str(x) for x in a.problems],
                                "n_self_intersections": a.n_self_intersections,
                                "audit_seconds": time.perf_counter() - t_a})
        levels = args.levels
        while True:
            try:
                cases.append((p, default_face_counts(len(F), levels)))
                break
            except LevelsError:  # small input: as many levels as fit
                levels -= 1
                if levels < 2:
                    skipped.append({"mesh": p.name, "reason": "too small for a cage"})
                    break
    if args.audit:  # smallest first: a run cut short still covers the most meshes
        cases.sort(key=lambda c: len(read_mesh(c[0])[1]))
    for spec in extra:
        name, counts = spec.split("=")
        p = Path(args.mesh_dir) / name
        if p.exists() and (not args.only or name in args.only):
            cases.append((p, [int(c) for c in counts.split(",")]))

    have_wheel = False
    if not args.no_wheel:
        try:
            import nested_cages  # noqa: F401

            have_wheel = True
        except ImportError:
            pass

    results = []
    t_all = time.perf_counter()

    def _summary() -> dict:
        return {"mesh_dir": str(args.mesh_dir), "command": " ".join(sys.argv), "methods": methods,
                "skipped_open": skipped, "refused_by_audit": refused, "wheel": have_wheel, "timeout": args.timeout,
                "wheel_timeout": args.wheel_timeout or args.timeout, "git_head": _git_head(),
                "wall_seconds": time.perf_counter() - t_all, "cpu_seconds_all_runs": _children_cpu(),
                "results": results}

    for p, counts in cases:
        V, F = read_mesh(p)
        rec = {"mesh": p.name, "n_faces": len(F), "face_counts": counts}
        try:
            from cagegen.sdf.backend import genus

            rec["input_genus"] = genus(V, F)
        except Exception:  # noqa: BLE001 -- a figure only
            pass
        ref = next((r for r in refused if r["mesh"] == p.name), None)
        if ref is not None:
            rec["refused_by_audit"] = ref["problems"]
        for m in methods + (["wheel"] if have_wheel else []):
            if ref is not None and m != "sdf":
                continue
            fn = _run_ours if m == "nested" else run_wheel if m == "wheel" else _run_backend(m)
            print(f"[cages] {p.name} {counts}: {m} ...", file=sys.stderr, flush=True)
            load0 = os.getloadavg()[0]
            tmo = (args.wheel_timeout or args.timeout) if m == "wheel" else args.timeout
            rec[m] = _summarise(V, F, in_subprocess(fn, p, counts, tmo), counts)
            rec[m]["loadavg_1min"] = [load0, os.getloadavg()[0]]
            print(f"[cages]   {m}: ok={rec[m].get('ok')} {rec[m].get('seconds', 0):.1f} s "
                  f"(cpu {rec[m].get('cpu_seconds', float('nan')):.1f}) "
                  f"valid={rec[m].get('verification', {}).get('ok')} {rec[m].get('error', '')}",
                  file=sys.stderr, flush=True)
        if rec.get("nested", {}).get("ok") and rec.get("wheel", {}).get("ok"):
            rec["time_ratio_wheel_over_nested"] = rec["wheel"]["seconds"] / rec["nested"]["seconds"]
        results.append(rec)
        (out / f"{args.tag}.json").write_text(json.dumps(_summary(), indent=1, default=float))
        _plot(results, out / f"{args.tag}.png")
    summary = _summary()
    print(json.dumps(summary, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
