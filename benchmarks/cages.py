"""Benchmark the ``nested`` cage backend against the reference wheel ``nested-cages`` 0.1.0.

Usage::

    python benchmarks/cages.py MESH_DIR --out DIR [--timeout 300] [--levels 3] [--no-wheel]
                               [--counts bunny.off=1000,250 ...] [--only gargo.off ...]

For every closed mesh of ``MESH_DIR`` (open ones are detected from their boundary edges and
skipped), both methods get the same input and face counts (default: 4x fewer faces per layer,
``cagegen.default_face_counts``; plus the cases given with ``--counts``, by default the reference's
known failure ``bunny.off=1000,250``). Each run is a subprocess with a timeout. For each method and
mesh the JSON records: success / error, seconds (ours: per phase), achieved face counts, the verdict
of :func:`cagegen.verify_nesting` with its figures (min gap, min winding), and tightness per layer:
cage volume / input volume and Hausdorff distance to the input relative to the bounding-box
diagonal. The time ratio wheel / ours is given where both finished. Writes ``DIR/cages.json`` and
``DIR/cages.png``; the JSON is also printed.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
import traceback
from pathlib import Path

import numpy as np

MESH_EXT = (".off", ".obj", ".ply", ".stl")


def _read(path: Path):
    import igl

    V, F = igl.read_triangle_mesh(str(path))[:2]
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


def _is_closed(F: np.ndarray) -> tuple[bool, str]:
    """Closed = every edge has exactly two faces (no boundary, no non-manifold edge)."""
    E = np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(E, axis=0, return_counts=True)
    n_boundary = int(np.sum(counts == 1))
    n_nonmanifold = int(np.sum(counts > 2))
    if n_boundary or n_nonmanifold:
        return False, f"{n_boundary} boundary edges, {n_nonmanifold} non-manifold edges"
    return True, ""


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


def _verify(V, F, layers) -> dict:
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


def _run_ours(path: str, counts: list[int], q) -> None:
    t = time.perf_counter()
    try:
        from cagegen.nested import nested_backend

        V, F = _read(Path(path))
        t = time.perf_counter()
        layers, info = nested_backend(V, F, counts, progress=False)
        sec = time.perf_counter() - t
        phases: dict = {}
        for li in info["layers"]:
            for k, v in li["seconds"].items():
                if k != "total":
                    phases[k] = phases.get(k, 0.0) + float(v)
        q.put({
            "ok": True,
            "seconds": sec,
            "seconds_per_phase": phases,
            "recovery": info["recovery"],
            "min_gap_relative": [li["min_gap_relative"] for li in info["layers"]],
            "layers": [(np.asarray(a), np.asarray(b)) for a, b in layers],
        })
    except Exception as exc:  # noqa: BLE001 -- any failure is reported in the JSON
        q.put({"ok": False, "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t,
               "traceback": traceback.format_exc()[-2000:]})


def _run_wheel(path: str, counts: list[int], q) -> None:
    t = time.perf_counter()
    try:
        import nested_cages

        V, F = _read(Path(path))
        t = time.perf_counter()
        out = nested_cages.nested_cages(
            np.asfortranarray(V), np.asfortranarray(F, dtype=np.int32), num_faces=list(counts), quad_order=2,
            energy_expansion="None", energy_final="Volume", regular=[True] * len(counts))
        sec = time.perf_counter() - t
        q.put({"ok": True, "seconds": sec,
               "layers": [(np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.int64))
                          for a, b in out]})
    except Exception as exc:  # noqa: BLE001 -- any failure is reported in the JSON
        q.put({"ok": False, "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t})


def _in_subprocess(fn, path: Path, counts: list[int], timeout: float) -> dict:
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


def _summarise(V, F, res: dict) -> dict:
    out = {k: v for k, v in res.items() if k not in ("layers", "traceback")}
    if res.get("ok"):
        layers = res["layers"]
        out["face_counts"] = [len(b) for _, b in layers]
        out["verification"] = _verify(V, F, layers)
        out["tightness"] = _tightness(V, F, layers)
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
        if key == "seconds":
            ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh_dir")
    ap.add_argument("--out", required=True)
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per mesh and method")
    ap.add_argument("--levels", type=int, default=3, help="layers including the input (default 3)")
    ap.add_argument("--counts", action="append", default=None,
                    help="extra case NAME=c1,c2,... (default: bunny.off=1000,250)")
    ap.add_argument("--only", action="append", default=None, help="restrict to these file names")
    ap.add_argument("--no-wheel", action="store_true")
    ap.add_argument("--no-default", action="store_true", help="run only the --counts cases")
    args = ap.parse_args(argv)

    from cagegen import LevelsError, default_face_counts

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extra = args.counts if args.counts is not None else ["bunny.off=1000,250"]
    cases = []
    files = sorted(p for p in Path(args.mesh_dir).iterdir() if p.suffix.lower() in MESH_EXT)
    skipped = []
    for p in files:
        if args.no_default or (args.only and p.name not in args.only):
            continue
        V, F = _read(p)
        closed, why = _is_closed(F)
        if not closed:
            skipped.append({"mesh": p.name, "reason": why})
            continue
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
    for p, counts in cases:
        V, F = _read(p)
        rec = {"mesh": p.name, "n_faces": len(F), "face_counts": counts}
        print(f"[cages] {p.name} {counts}: nested ...", file=sys.stderr, flush=True)
        rec["nested"] = _summarise(V, F, _in_subprocess(_run_ours, p, counts, args.timeout))
        print(f"[cages]   nested: ok={rec['nested'].get('ok')} {rec['nested'].get('seconds', 0):.1f} s "
              f"valid={rec['nested'].get('verification', {}).get('ok')}", file=sys.stderr, flush=True)
        if have_wheel:
            print(f"[cages] {p.name} {counts}: wheel ...", file=sys.stderr, flush=True)
            rec["wheel"] = _summarise(V, F, _in_subprocess(_run_wheel, p, counts, args.timeout))
            print(f"[cages]   wheel: ok={rec['wheel'].get('ok')} {rec['wheel'].get('seconds', 0):.1f} s "
                  f"valid={rec['wheel'].get('verification', {}).get('ok')} {rec['wheel'].get('error', '')}",
                  file=sys.stderr, flush=True)
            if rec["nested"].get("ok") and rec["wheel"].get("ok"):
                rec["time_ratio_wheel_over_nested"] = rec["wheel"]["seconds"] / rec["nested"]["seconds"]
        results.append(rec)
        summary = {"mesh_dir": str(args.mesh_dir), "skipped_open": skipped, "wheel": have_wheel,
                   "timeout": args.timeout, "results": results}
        (out / "cages.json").write_text(json.dumps(summary, indent=1, default=float))
        _plot(results, out / "cages.png")

    summary = {"mesh_dir": str(args.mesh_dir), "skipped_open": skipped, "wheel": have_wheel,
               "timeout": args.timeout, "results": results}
    print(json.dumps(summary, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
