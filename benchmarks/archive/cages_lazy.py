"""Cage tightness on the dev zoo: ``lazy`` beside ``nested`` and the reference wheel, in one run.

For every closed mesh of the zoo (inputs that fail :func:`cagegen.audit_mesh` are listed as skipped),
normalised to a unit bounding-box diagonal, with the face counts of
:func:`cagegen.default_face_counts` (``--levels`` layers, input included; fewer if the mesh is small):

* ``lazy``   -- ``build_cages(method="lazy")`` (gpytoolbox, GPL);
* ``nested`` -- ``build_cages(method="nested")`` (this project's Nested Cages);
* ``wheel``  -- ``nested_cages.nested_cages(V, F, num_faces=[...], quad_order=2, energy_expansion="None",
  energy_final="Volume", regular=[True]*k)`` (``pip install nested-cages==0.1.0``).

Each (mesh, method) runs in a child process with a time limit (``--timeout``); a failure or a timeout
is a result. Every hierarchy, whatever built it, goes through the same :func:`cagegen.verify_nesting`
and the same tightness measures per layer: seconds, max / mean distance of the cage to the input
(cage vertices plus ``--samples`` area-uniform surface points, over the input's diagonal), cage /
input volume ratio, genus, and the verifier's figures of the pair (ok, min gap, fine vertices
outside, crossing pairs).

Prints one JSON object (also written to ``--out/cages_lazy.json`` with the layers as ``.npz`` for
``benchmarks/archive/lazy_solvers.py``) and saves ``--png`` (tightness per mesh and method).

Usage::

    python benchmarks/archive/cages_lazy.py ZOO_DIR --out OUT \\
        --png docs/images/cages_lazy.png [--meshes gargo bunny] [--methods lazy nested wheel]
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import tightness  # noqa: E402

METHODS = ("lazy", "nested", "wheel")
MESH_SUFFIXES = (".off", ".obj", ".ply", ".stl")


def _run_method(method: str, V: np.ndarray, F: np.ndarray, counts: list[int], queue) -> None:
    """Child process: build the cages, put ``(layers, per-layer seconds, info)`` or an error on ``queue``."""
    try:
        t0 = time.perf_counter()
        if method == "wheel":
            import nested_cages

            k = len(counts)
            out = nested_cages.nested_cages(V, F, num_faces=list(counts), quad_order=2, energy_expansion="None",
                                            energy_final="Volume", regular=[True] * k)
            total = time.perf_counter() - t0
            # the wheel returns the cages, finest first (some versions prepend the input: drop it)
            cages = [(np.asarray(a, float), np.asarray(b, np.int64)) for a, b in out]
            if len(cages) == k + 1:
                cages = cages[1:]
            queue.put({"ok": True, "layers": cages, "seconds": [total / k] * k, "seconds_total": total,
                       "seconds_per_layer_measured": False, "info": {}})
            return
        from cagegen import build_cages

        layers, info = build_cages(V, F, face_counts=counts, method=method, return_info=True)
        total = time.perf_counter() - t0
        per = [float(li.get("seconds", {}).get("total", np.nan)) if isinstance(li.get("seconds"), dict)
               else float(li["seconds"]) for li in info["backend"]["layers"]]
        slim = {"genus_changes": info["backend"].get("genus_changes"),
                "recovery": info["backend"].get("recovery"),
                "offset_relative": [li.get("offset_relative") for li in info["backend"]["layers"]]}
        queue.put({"ok": True, "layers": layers[1:], "seconds": per, "seconds_total": total,
                   "seconds_per_layer_measured": True, "info": slim})
    except Exception as exc:  # noqa: BLE001 - a failing method is a result
        queue.put({"ok": False, "error": f"{type(exc).__name__}: {exc}",
                   "trace": traceback.format_exc(limit=3)})


def run_with_timeout(method, V, F, counts, timeout):
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_run_method, args=(method, V, F, counts, q))
    t0 = time.perf_counter()
    p.start()
    try:
        res = q.get(timeout=timeout)
    except Exception:  # noqa: BLE001 - queue.Empty: the child is still running
        res = {"ok": False, "error": f"timeout after {timeout:.0f} s"}
    p.join(5)
    if p.is_alive():
        p.terminate()
        p.join()
    res["wall"] = time.perf_counter() - t0
    return res


def evaluate(V, F, res, n_samples) -> dict:
    """Verifier + tightness figures for a finished method."""
    from cagegen import verify_nesting
    from cagegen.copyleft.lazy import genus

    layers = res["layers"]
    rep = verify_nesting([(V, F)] + layers)
    rows = []
    for k, ((Vc, Fc), p) in enumerate(zip(layers, rep.pairs), start=1):
        rows.append({
            "layer": k,
            "n_faces": len(Fc),
            "seconds": res["seconds"][k - 1],
            **tightness(Vc, Fc, V, F, n_samples),
            "genus": genus(Vc, Fc),
            "verifier": {"ok": p.ok, "min_gap_rel": p.min_gap_rel, "n_outside_vertices": p.n_outside_vertices,
                         "n_intersecting_pairs": p.n_intersecting_pairs, "min_winding": p.min_winding,
                         "seconds": p.seconds, "reason": p.reason},
        })
    return {"certified": rep.ok, "seconds_total": res["seconds_total"],
            "seconds_per_layer_measured": res["seconds_per_layer_measured"], "layers": rows, "info": res["info"]}


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = [m for m, r in results["meshes"].items() if "methods" in r]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    width = 0.8 / len(METHODS)
    x = np.arange(len(meshes))
    for j, meth in enumerate(METHODS):
        for ax, key, lab in zip(axes, ("max_dist_rel", "volume_ratio", "seconds"),
                                ("max distance cage->input / diag (layer 1)", "cage / input volume (layer 1)",
                                 "seconds per layer (layer 1)")):
            vals = []
            for m in meshes:
                r = results["meshes"][m]["methods"].get(meth, {})
                vals.append(r["layers"][0][key] if r.get("layers") else np.nan)
            ax.bar(x + (j - 1) * width, vals, width, label=meth)
            ax.set_title(lab, fontsize=10)
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels(meshes, rotation=60, fontsize=8)
    axes[2].set_yscale("log")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def merge_runs(runs: list[dict]) -> dict:
    """Merge result dicts: for each (mesh, method) a result beats a failure, a real failure a timeout."""
    merged: dict = {}
    for i_run, res in enumerate(runs, start=1):
        for mesh, entry in res["meshes"].items():
            m = merged.setdefault(mesh, {k: v for k, v in entry.items() if k != "methods"})
            if "skipped" in entry:
                m.setdefault("skipped", entry["skipped"])
                continue
            meths = m.setdefault("methods", {})
            for meth, r in entry.get("methods", {}).items():
                old = meths.get(meth)
                if old is None or ("failed" in old and ("failed" not in r or old["failed"].startswith("timeout"))):
                    meths[meth] = dict(r, run=i_run)  # a result beats a failure, a real failure a timeout
    return {"runs": len(runs), "meshes": merged}


def markdown_table(res: dict) -> str:
    """One row per (mesh, method, layer) of a :func:`merge_runs` result."""
    merged, n_runs = res["meshes"], res["runs"]
    rows = [("| mesh (faces, genus) | method | layer: faces | s / layer | max dist | mean dist | vol ratio | genus "
            "| verifier: ok, min gap, out, crossing |"), "|---|---|---|---|---|---|---|---|---|"]
    for mesh, m in merged.items():
        if "methods" not in m:
            rows.append(f"| {mesh} | skipped: {m.get('skipped', '')[:90]} | | | | | | | |")
            continue
        head = f"{mesh} ({m['n_faces']}, g{m['genus']})"
        for meth in METHODS:
            r = m["methods"].get(meth)
            if r is None:
                continue
            if n_runs > 1:
                meth = f"{meth} (run {r['run']})"
            if "failed" in r:
                rows.append(f"| {head} | {meth} | failed: {r['failed'][:80]} | | | | | | |")
                continue
            for x in r["layers"]:
                v = x["verifier"]
                sec = f"{x['seconds']:.1f}" + ("" if r["seconds_per_layer_measured"] else " (total/k)")
                rows.append(
                    f"| {head} | {meth} | {x['layer']}: {x['n_faces']} | {sec} | {x['max_dist_rel']:.4f} | "
                    f"{x['mean_dist_rel']:.4f} | {x['volume_ratio']:.3f} | {x['genus']} | "
                    f"{'yes' if v['ok'] else 'NO'}, {v['min_gap_rel']:.1e}, {v['n_outside_vertices']}, "
                    f"{v['n_intersecting_pairs']} |")
    return "\n".join(rows)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", nargs="?", help="folder of closed meshes (e.g. the dev zoo)")
    ap.add_argument("--table", nargs="+", metavar="JSON",
                    help="print a markdown table from result files (later files fill methods missing or "
                         "failed in earlier ones) and exit")
    ap.add_argument("--meshes", nargs="*", help="mesh stems to run (default: all)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--out", default=None, help="folder for cages_lazy.json and the layers (.npz)")
    ap.add_argument("--png", default=None, help="bar chart of layer-1 tightness and time (also with --table)")
    args = ap.parse_args(argv)
    if args.table:
        merged = merge_runs([json.loads(Path(f).read_text()) for f in args.table])
        print(markdown_table(merged))
        if args.png:
            plot(merged, args.png)
        return merged
    if not args.zoo:
        ap.error("give the mesh folder (or --table)")

    from cagegen import LevelsError, audit_mesh, default_face_counts
    from nestmg.io import load_mesh, normalize

    out_dir = Path(args.out) if args.out else None
    if out_dir:
        out_dir.mkdir(parents=True, exist_ok=True)
    paths = sorted(p for p in Path(args.zoo).iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if args.meshes:
        paths = [p for p in paths if p.stem in args.meshes]
    results: dict = {"levels": args.levels, "methods": args.methods, "meshes": {}}
    for path in paths:
        name = path.stem
        try:
            V, F = load_mesh(path)
        except Exception as exc:  # noqa: BLE001 - an unreadable file is a result
            results["meshes"][name] = {"skipped": f"cannot load: {exc}"}
            continue
        V = normalize(V)[0]
        F = np.asarray(F, dtype=np.int64)
        aud = audit_mesh(V, F)
        if not aud.ok:
            results["meshes"][name] = {"skipped": "audit: " + "; ".join(aud.problems)}
            print(f"[cages_lazy] {name}: skipped ({aud.problems[0]})", file=sys.stderr, flush=True)
            continue
        levels = args.levels
        while True:
            try:
                counts = default_face_counts(len(F), levels)
                break
            except LevelsError:
                levels -= 1
        if levels < 2:
            results["meshes"][name] = {"skipped": f"too small ({len(F)} faces)"}
            continue
        entry = {"n_faces": len(F), "genus": aud.genus, "face_counts": counts, "methods": {}}
        results["meshes"][name] = entry
        for meth in args.methods:
            res = run_with_timeout(meth, V, F, counts, args.timeout)
            if not res["ok"]:
                entry["methods"][meth] = {"failed": res["error"], "wall": res["wall"]}
            else:
                entry["methods"][meth] = evaluate(V, F, res, args.samples)
                if out_dir:
                    arrs = {"V0": V, "F0": F}
                    for k, (Vc, Fc) in enumerate(res["layers"], start=1):
                        arrs[f"V{k}"], arrs[f"F{k}"] = Vc, Fc
                    np.savez(out_dir / f"{name}_{meth}.npz", **arrs)
            r = entry["methods"][meth]
            msg = r.get("failed") or " ".join(
                f"L{x['layer']}:{x['n_faces']}f {x['seconds']:.1f}s max {x['max_dist_rel']:.3f} "
                f"vol {x['volume_ratio']:.2f} g{x['genus']} {'ok' if x['verifier']['ok'] else 'NOT NESTED'}"
                for x in r["layers"])
            print(f"[cages_lazy] {name} {meth}: {msg}", file=sys.stderr, flush=True)
            if out_dir:
                (out_dir / "cages_lazy.json").write_text(json.dumps(results, indent=1, default=float))
    if args.png:
        plot(results, args.png)
    print(json.dumps(results, indent=1, default=float))
    return results


if __name__ == "__main__":
    main()
