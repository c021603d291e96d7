"""The Nested Cages paper's other uses of a cage hierarchy (issue 32, items 3–5), measured.

For each input surface (a certified ``nestmg`` hierarchy with the defaults, ``--levels`` levels, from the
cache when built before; normalised frame, unit bounding-box diagonal):

``embedded``  Clamped elasticity under gravity (E = 1, ν, the boundary in the lowest ``--band`` of x
              fixed) solved on the fine
              level by MG-PCG to 1e-8 (:func:`nestmg.elasticity.setup_elasticity`: assembly + multigrid
              set-up + solve), and on the coarsest (cage) level only with each model of
              :func:`nestmg.embedded.embedded_solve` (``filled``, ``fraction``, ``galerkin``), carried to
              the input surface's vertices through the prolongations. Errors at those vertices against the
              fine solve: ``‖u_e − u_f‖ / ‖u_f‖`` (all vertices, 2-norm) and
              ``max_i |u_e − u_f|_i /
              max_i |u_f|_i``. Seconds exclude locating the vertices in the fine tets (once per input,
              reused by both; recorded as ``locate_seconds``).
``harmonic``  Harmonic coordinates of the coarsest cage at the input's vertices
              (:func:`nestmg.harmonic.hierarchy_harmonic_coordinates`, ``--refine`` red refinements of the
              cage's tet level): block MG-PCG to 1e-10 with one set-up against one sparse factorisation
              (CHOLMOD when scikit-sparse is installed, otherwise SuperLU in symmetric mode), partition of
              unity and linear precision errors.
``culling``   (two or more inputs: the first two) Object B moved along a fixed direction to a range of
              offsets from object A; :func:`cagegen.cull_collisions` on their layers against the direct
              exact test on the inputs (:func:`cagegen.solids_intersect`), same answer required.

Every timing is the median of ``--repeat`` runs in one process, ``OMP_NUM_THREADS=1`` recommended::

    OMP_NUM_THREADS=1 python benchmarks/cage_uses.py ZOO_DIR/bunny.off ZOO_DIR/spot.obj --max-tets 300000 \\
        --out benchmarks/results/cage_uses/cage_uses.json --png docs/images
    python benchmarks/cage_uses.py --table benchmarks/results/cage_uses/cage_uses.json

``--png DIR`` writes ``embedded_<mesh>.png`` and ``harmonic_<mesh>.png`` for the first mesh.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

MODELS = ("filled", "fraction", "galerkin")
PARTS = ("embedded", "harmonic", "culling")


def _median_run(fn, repeat: int):
    """``fn()`` ``repeat`` times: the last result and the median wall seconds."""
    secs, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        secs.append(time.perf_counter() - t)
    return out, float(np.median(secs)), secs


def _hierarchy(path: str, max_tets: int, levels: int):
    import nestmg

    V, F = nestmg.load_mesh(path)
    t = time.perf_counter()
    h = nestmg.build_hierarchy(V, F, levels, "nested", sizing=nestmg.SizingOptions(max_tets=max_tets),
                               cache=True, progress=False)
    return h, time.perf_counter() - t


def _fine_solve(tets, P, nu, band):
    from nestmg.elasticity import setup_elasticity

    prob = setup_elasticity(tets, P, "elasticity-clamped", nu=nu, band=band)
    x, info = prob.multigrid().solve(prob.b, tol=1e-8, accel="cg", return_info=True)
    return prob.expand(x), info["iterations"]


def run_embedded(h, nu: float, band: float, repeat: int) -> dict:
    """Fine MG-PCG solve against the three embedded models, errors at the input's vertices."""
    from nestmg.embedded import embedded_solve
    from nestmg.prolongation import prolongation

    tets = h.tets_in("normalized")
    pts = h.to_normalized(h.surfaces[0][0])
    t = time.perf_counter()
    S, rep = prolongation(pts, *tets[0])
    out = {"nu": nu, "band": band, "locate_seconds": time.perf_counter() - t, "n_points": len(pts),
           "points_outside_fine_tets": rep.n_outside, "fine_nodes": len(tets[0][0]),
           "fine_tets": len(tets[0][1])}
    (u_f, its), fine_s, fine_all = _median_run(lambda: _fine_solve(tets, h.P, nu, band), repeat)
    us = S @ u_f
    out["fine"] = {"seconds": fine_s, "all_seconds": fine_all, "iterations": its,
                   "max_displacement": float(np.linalg.norm(us, axis=1).max())}
    out["models"] = {}
    for model in MODELS:
        sol, sec, all_s = _median_run(lambda: embedded_solve(tets, h.P, S, model=model, nu=nu, band=band),
                                          repeat)
        e = sol.u_points - us
        out["models"][model] = {
            "seconds": sec, "all_seconds": all_s, "stages": sol.info["seconds"],
            "unknowns": sol.info["unknowns"],
            "coarse_nodes": sol.info["coarse_nodes"], "coarse_tets": sol.info["coarse_tets"],
            "fixed_nodes": len(sol.fixed), "rel_l2": float(np.linalg.norm(e) / np.linalg.norm(us)),
            "rel_max": float(np.linalg.norm(e, axis=1).max() / np.linalg.norm(us, axis=1).max()),
            "speedup": fine_s / sec}
        out["models"][model]["_u"] = sol.u_points
    out["_u_fine"] = us
    print(f"  embedded: fine {fine_s:.2f} s ({its} it); " + "; ".join(
        f"{m} {r['seconds']:.3f} s err {r['rel_l2']:.3f}" for m, r in out["models"].items()), flush=True)
    return out


def run_harmonic(h, refine: int, repeat: int, chunk: int, solvers=("multigrid", "direct")) -> dict:
    """Harmonic coordinates by block MG-PCG and by one factorisation."""
    from exp_common import peak_rss_mb

    from nestmg.harmonic import hierarchy_harmonic_coordinates

    out = {"refine": refine, "cage_vertices": len(h.surfaces[-1][0]), "cage_faces": len(h.surfaces[-1][1]),
           "n_points": len(h.surfaces[0][0]), "solvers": {}}
    W = {}
    for solver in solvers:
        infos: list = []

        def one():
            hc = hierarchy_harmonic_coordinates(h, refine=refine, solver=solver, chunk=chunk)
            infos.append(dict(hc.info))
            return hc

        hc, sec, all_s = _median_run(one, repeat)
        its = hc.info.pop("iterations", None)
        stages = {k: [i[k] for i in infos] for k in ("seconds_mesh", "seconds_setup", "seconds_solve")}
        r = {"seconds": sec, "all_seconds": all_s, "all_stage_seconds": stages,
             "pu_error": hc.partition_of_unity_error(),
             "lp_error": hc.linear_precision_error(), "min_weight": float(hc.W.min()), **hc.info,
             "peak_rss_mb": peak_rss_mb()}
        if its:
            r["iterations_median"], r["iterations_max"] = float(np.median(its)), int(max(its))
        out["solvers"][solver] = r
        W[solver] = hc
        print(f"  harmonic ({solver}, refine {refine}): {sec:.2f} s, PU {r['pu_error']:.1e}, "
              f"LP {r['lp_error']:.1e}, {hc.info['unknowns']} unknowns", flush=True)
    if len(W) == 2:
        out["max_weight_difference"] = float(np.abs(W["multigrid"].W - W["direct"].W).max())
    out["_hc"] = W[solvers[0]]
    return out


def _placements(a, b, offsets, direction):
    """Object B's layers centred on A's centroid plus ``offset * direction``."""
    d = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    ca, cb = a[0][0].mean(axis=0), b[0][0].mean(axis=0)
    return [[(V - cb + ca + o * d, F) for V, F in b] for o in offsets]


def run_culling(h_a, h_b, offsets, direction, repeat: int) -> list:
    """Culling coarse to fine against the direct exact test on the inputs, per offset."""
    from cagegen import cull_collisions, solids_intersect

    a = h_a.surfaces_in("normalized")
    rows = []
    for off, b in zip(offsets, _placements(a, h_b.surfaces_in("normalized"), offsets, direction)):
        rep, cull_s, _ = _median_run(lambda: cull_collisions(a, b), repeat)
        direct, direct_s, _ = _median_run(lambda: solids_intersect(*a[0], *b[0]), repeat)
        if rep.separated == direct["intersect"]:
            raise SystemExit(f"culling and the direct test disagree at offset {off}")
        rows.append({"offset": off, "separated": rep.separated, "decided_at": list(rep.decided_at),
                     "tests": rep.tests, "cull_seconds": cull_s, "direct_seconds": direct_s,
                     "direct_faces": direct["faces"], "direct_crossing": direct["crossing"]})
        print(f"  culling offset {off:.2f}: separated={rep.separated} at {rep.decided_at}, "
              f"{cull_s * 1e3:.1f} ms vs direct {direct_s * 1e3:.1f} ms", flush=True)
    return rows


def twist(V: np.ndarray, degrees: float = 60.0) -> np.ndarray:
    """Twist about the axis of largest extent through the centroid, 0 to ``degrees`` along it."""
    k = int(np.argmax(np.ptp(V, axis=0)))
    c = V.mean(axis=0)
    t = (V[:, k] - V[:, k].min()) / np.ptp(V[:, k])
    a = np.radians(degrees) * t
    i, j = [m for m in range(3) if m != k]
    out = V.copy()
    x, y = V[:, i] - c[i], V[:, j] - c[j]
    out[:, i] = c[i] + np.cos(a) * x - np.sin(a) * y
    out[:, j] = c[j] + np.sin(a) * x + np.cos(a) * y
    return out


def _panels(path: Path, panels, clim=None) -> None:
    """Side-by-side off-screen panels: each ``(title, [(V, F, opts), ...])``."""
    import pyvista as pv

    from nestmg.render import _polydata, third_party_to_log

    with third_party_to_log():
        pl = pv.Plotter(off_screen=True, shape=(1, len(panels)), window_size=(600 * len(panels), 560),
                        border=False)
        for c, (title, meshes) in enumerate(panels):
            pl.subplot(0, c)
            for V, F, opts in meshes:
                pd = _polydata(V, F)
                if "scalars" in opts:
                    pd["|u|"] = opts.pop("scalars")
                    opts = dict(opts, scalars="|u|", clim=clim, cmap="viridis",
                                scalar_bar_args={"title": "|u| (fine max = 1)"})
                pl.add_mesh(pd, **opts)
            pl.add_text(title, font_size=10)
            pl.view_isometric()
        pl.link_views()
        path.parent.mkdir(parents=True, exist_ok=True)
        pl.screenshot(str(path))
        pl.close()


def picture_embedded(h, emb: dict, path: Path) -> None:
    """The input warped by the fine and the embedded displacements (scaled alike), coloured by |u|."""
    V, F = h.surfaces_in("normalized")[0]
    scale = 0.12 / emb["fine"]["max_displacement"]  # the fine solve's largest move = 12 % of the diagonal
    panels = [(f"fine MG-PCG ({emb['fine_tets']:,} tets)", emb["_u_fine"])]
    for m in ("filled", "galerkin"):
        r = emb["models"][m]
        title = f"embedded '{m}' ({r['coarse_tets']:,} tets), error {100 * r['rel_l2']:.0f} %"
        panels.append((title, r["_u"]))
    mx = emb["fine"]["max_displacement"]
    _panels(path, [(t, [(V + scale * u, F, {"scalars": np.linalg.norm(u, axis=1) / mx,
                                           "smooth_shading": True})]) for t, u in panels], clim=(0.0, 1.0))


def picture_harmonic(h, hc, path: Path) -> None:
    """The input and its cage, then both after a twist of the cage (harmonic-coordinate deformation)."""
    (V, F), (C, G) = h.surfaces[0], h.surfaces[-1]
    C2 = twist(C)
    cage = {"style": "wireframe", "color": "#c0392b", "line_width": 0.8}
    body = {"color": "#d9c9a8", "smooth_shading": True}
    _panels(path, [(f"input and cage ({len(C)} vertices)", [(V, F, dict(body)), (C, G, dict(cage))]),
                   ("cage twisted 60 deg, input deformed",
                    [(hc.deform(C2), F, dict(body)), (C2, G, dict(cage))])])


def _public(obj):
    """Drop the arrays kept for the pictures (keys starting with '_')."""
    if isinstance(obj, dict):
        return {k: _public(v) for k, v in obj.items() if not k.startswith("_")}
    if isinstance(obj, list):
        return [_public(v) for v in obj]
    return obj


def table_embedded(res: dict) -> str:
    rows = ["| mesh | fine tets | fine MG-PCG s (it) | model | cage tets | s | speedup | error L2 "
            "| error max |",
            "|---|---|---|---|---|---|---|---|---|"]
    for m in res["meshes"]:
        if "embedded" not in m:
            continue
        e = m["embedded"]
        for name, r in e["models"].items():
            fine = f"{e['fine']['seconds']:.2f} ({e['fine']['iterations']})"
            rows.append(f"| {m['mesh']} | {e['fine_tets']:,} | {fine} "
                        f"| {name} | {r['coarse_tets']:,} | {r['seconds']:.3f} | {r['speedup']:.1f}x | "
                        f"{100 * r['rel_l2']:.1f} % | {100 * r['rel_max']:.1f} % |")
    return "\n".join(rows)


def table_harmonic(*results: dict) -> str:
    """Rows of every result given (e.g. the main run and a larger refinement run)."""
    rows = ["| mesh | cage vertices | points | unknowns (tets) | solver | setup s (last run) "
            "| solve s (last run) | total s (median) | iterations | partition of unity | linear precision "
            "| min weight |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in (m for res in results for m in res["meshes"] if "harmonic" in m):
        hm = m["harmonic"]
        for name, r in hm["solvers"].items():
            it = "–"
            if "iterations_median" in r:
                it = f"{r['iterations_median']:.0f} (max {r['iterations_max']})"
            rows.append(f"| {m['mesh']} | {hm['cage_vertices']} | {hm['n_points']:,} | {r['unknowns']:,} "
                        f"({r['tets']:,}) | {r['backend']} | {r['seconds_setup']:.2f} "
                        f"| {r['seconds_solve']:.2f} "
                        f"| {r['seconds']:.2f} | {it} | {r['pu_error']:.1e} | {r['lp_error']:.1e} | "
                        f"{r['min_weight']:.3f} |")
    return "\n".join(rows)


def table_culling(res: dict) -> str:
    c = res.get("culling")
    if not c:
        return ""
    rows = ["| offset | answer | decided at layers | faces tested (A + B), coarse → fine | culled ms "
            "| faces tested directly | direct ms | direct / culled |",
            "|---|---|---|---|---|---|---|---|"]
    for r in c["rows"]:
        faces = " → ".join(str(sum(t["faces"])) for t in r["tests"])
        ans = "separated" if r["separated"] else "intersecting"
        rows.append(f"| {r['offset']:.2f} | {ans} | {tuple(r['decided_at'])} | {faces} "
                    f"| {1e3 * r['cull_seconds']:.1f} | {sum(r['direct_faces'])} "
                    f"| {1e3 * r['direct_seconds']:.1f} | {r['direct_seconds'] / r['cull_seconds']:.1f} |")
    return "\n".join(rows)


def _span(xs, fmt: str) -> str:
    lo, hi = format(min(xs), fmt), format(max(xs), fmt)
    return lo if lo == hi else f"{lo}–{hi}"


def summary_embedded(res: dict) -> str:
    """One sentence per model: speedup and L2 error ranges over the meshes."""
    parts = []
    for model in MODELS:
        rs = [m["embedded"]["models"][model] for m in res["meshes"] if "embedded" in m]
        parts.append(f"`{model}` {_span([r['speedup'] for r in rs], '.1f')}x faster at "
                     f"{_span([100 * r['rel_l2'] for r in rs], '.1f')} % error")
    return "; ".join(parts)


def summary_harmonic(res: dict) -> str:
    """Direct against multigrid total seconds, per mesh."""
    rows = [m["harmonic"]["solvers"] for m in res["meshes"] if "harmonic" in m]
    ratio = [s["multigrid"]["seconds"] / s["direct"]["seconds"] for s in rows if len(s) == 2]
    pu = [s["multigrid"]["pu_error"] for s in rows]
    return (f"the factorisation took {_span(ratio, '.1f')}x less time than block MG-PCG; partition of unity "
            f"held to {max(pu):.1e} with MG-PCG")


def summary_harmonic_scale(res: dict, larger: dict) -> str:
    """The larger refinement's MG-PCG run beside the main run's factor size."""
    big = [m for m in larger["meshes"] if "harmonic" in m][0]
    mg = big["harmonic"]["solvers"]["multigrid"]
    small = [m["harmonic"]["solvers"]["direct"] for m in res["meshes"]
             if m["mesh"] == big["mesh"] and "harmonic" in m][0]
    return (f"{big['mesh']} with {mg['unknowns']:,} unknowns ({mg['tets']:,} tets): block MG-PCG in "
            f"{mg['seconds']:.0f} s, {mg['iterations_median']:.0f} iterations (max {mg['iterations_max']}), "
            f"peak memory {mg['peak_rss_mb']:.0f} MB, partition of unity {mg['pu_error']:.1e}; "
            f"SuperLU's factor at {small['unknowns']:,} unknowns already held "
            f"{small['factor_nnz'] / 1e6:.1f}M nonzeros")


def summary_culling(res: dict) -> str:
    """Ratios direct / culled by outcome."""
    rows = res["culling"]["rows"]
    cage = [r for r in rows if r["separated"] and r["decided_at"] != [0, 0] and r["direct_faces"] != [0, 0]]
    inner = [r for r in rows if r["decided_at"] == [0, 0]]
    out = []
    if cage:
        out.append(f"separated by the cages while the inputs' boxes overlap: the direct test took "
                   f"{_span([r['direct_seconds'] / r['cull_seconds'] for r in cage], '.1f')}x "
                   "the culled time")
    if inner:
        out.append(f"decided on the inputs (the cages meet): the culled test took "
                   f"{_span([r['cull_seconds'] / r['direct_seconds'] for r in inner], '.1f')}x "
                   "the direct time")
    return "; ".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="*", help="closed surface files (the first two are the culling pair)")
    ap.add_argument("--table", type=Path, default=None, help="only print the Markdown tables of this JSON")
    ap.add_argument("--max-tets", type=int, default=300_000)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--nu", type=float, default=0.3)
    ap.add_argument("--band", type=float, default=0.15, help="clamped fraction of the x extent (embedded)")
    ap.add_argument("--refine", type=int, default=2, help="red refinements of the cage's tets (harmonic)")
    ap.add_argument("--chunk", type=int, default=32, help="right-hand sides per block (harmonic)")
    ap.add_argument("--repeat", type=int, default=3, help="repeats of the embedded and culling timings")
    ap.add_argument("--harmonic-repeat", type=int, default=1)
    ap.add_argument("--offsets", type=float, nargs="+",
                    default=[0.3, 0.45, 0.5, 0.51, 0.52, 0.53, 0.54, 0.55, 0.57, 0.6, 0.8])
    ap.add_argument("--direction", type=float, nargs=3, default=[1.0, 0.3, 0.2])
    ap.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    ap.add_argument("--harmonic-solvers", nargs="+", default=["multigrid", "direct"],
                    choices=["multigrid", "direct"])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--png", type=Path, default=None, help="folder for the pictures (first mesh)")
    a = ap.parse_args(argv)
    from exp_common import environment, git_commit, peak_rss_mb, write_json  # benchmarks/ is sys.path[0]

    if a.table is not None:
        res = json.loads(a.table.read_text())
        print(table_embedded(res), table_harmonic(res), table_culling(res), sep="\n\n")
        return 0
    if not a.meshes or a.out is None:
        ap.error("give at least one mesh and --out (or --table JSON)")
    res = {"params": {k: v for k, v in vars(a).items() if k not in ("meshes", "out", "png", "table")},
           "command": " ".join(["benchmarks/cage_uses.py"] + [Path(x).name if Path(x).exists() else x
                                                             for x in sys.argv[1:]]),
           "commit": git_commit(), "environment": environment(), "meshes": []}
    hs = []
    for k, path in enumerate(a.meshes):
        name = Path(path).name
        print(f"[{name}]", flush=True)
        h, build_s = _hierarchy(path, a.max_tets, a.levels)
        hs.append(h)
        m = {"mesh": name, "hierarchy": h.to_dict(), "hierarchy_seconds": build_s}
        stem = Path(path).stem
        if "embedded" in a.parts:
            emb = run_embedded(h, a.nu, a.band, a.repeat)
            if a.png is not None and k == 0:
                picture_embedded(h, emb, a.png / f"embedded_{stem}.png")
            m["embedded"] = _public(emb)
        if "harmonic" in a.parts:
            hm = run_harmonic(h, a.refine, a.harmonic_repeat, a.chunk, tuple(a.harmonic_solvers))
            if a.png is not None and k == 0:
                picture_harmonic(h, hm["_hc"], a.png / f"harmonic_{stem}.png")
            m["harmonic"] = _public(hm)
        res["meshes"].append(m)
        write_json(res, a.out)
    if len(hs) >= 2 and "culling" in a.parts:
        res["culling"] = {"objects": [Path(p).name for p in a.meshes[:2]], "direction": a.direction,
                          "rows": run_culling(hs[0], hs[1], a.offsets, a.direction, a.repeat)}
    res["peak_rss_mb"] = peak_rss_mb()
    res["environment_end"] = environment()
    write_json(res, a.out)
    print(table_embedded(res), table_harmonic(res), table_culling(res), sep="\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
