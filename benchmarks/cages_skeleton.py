"""Skeleton cages (``cagegen.skeleton``, Casti et al. 2019): procedural shapes and the zoo's characters.

Cases:

* ``star`` / ``stick`` -- procedural articulated shapes (implicit unions of capsules, marching cubes)
  with their KNOWN skeletons and bending nodes; the ``nested`` cage with the same face count is built
  beside them for the tightness comparison;
* zoo meshes (``--zoo DIR``, default homer, cheburashka, elephant, spot) -- automatic skeleton
  (pygel3d) and automatic bending nodes.

Per case (each in a child process with ``--timeout``): certified or the error (its message names the
failing step), seconds per step, skeleton / cage sizes, tightness (max and mean distance of the cage
to the input over the input's diagonal, from cage vertices and area-uniform samples; volume ratio).
Prints one JSON object, writes it to ``--out`` and, with ``--png DIR``, one picture per case: the
skeleton with its bending nodes, the integral-line hits and quads of the cross-sections, the tight
cage, and the certified cage.

Usage::

    nice -n 10 python benchmarks/cages_skeleton.py --zoo ZOO_DIR \\
        --out benchmarks/results/skeleton/cages_skeleton.json --png docs/images/skeleton

``--opt KEY=VALUE`` (repeatable): extra :func:`cagegen.skeleton.skeleton_cage` keywords for every case,
e.g. ``--opt min_gap=0.0025 --opt containment='flow'`` (recorded under ``options``).

``--tighten``: per certified case, the cage after :func:`cagegen.skeleton.tighten.tighten_cage` (certified
or not, tightness), recorded under ``tighten``; the case's own figures stay those of the returned cage.

``--min-nested``: per certified case, the smallest ``nested`` face count whose max distance is at most
the skeleton cage's (:func:`smallest_nested`), instead of the one nested cage at equal face count.
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

ZOO = ("homer.obj", "cheburashka.obj", "elephant.obj", "spot.obj")
_OPTS: dict = {}  # extra skeleton_cage keywords (--opt KEY=VALUE), inherited by the forked children
_TIGHTEN = False  # --tighten: measure cagegen.skeleton.tighten on each certified cage (forked children)


# ----------------------------------------------------------------------------- one case
def _load(case: str, zoo: Path | None):
    import trimesh

    from cagegen import check_mesh
    from nestmg.shapes import star_of_capsules, stick_figure

    if case == "star":
        V, F, S = star_of_capsules()
        return V, F, S, "given"
    if case == "stick":
        V, F, S = stick_figure()
        return V, F, S, "given"
    m = trimesh.load(zoo / case, process=True, force="mesh")
    V, F = check_mesh(np.asarray(m.vertices, float), np.asarray(m.faces, np.int64), repair=True)
    return V, F, None, "auto"


def smallest_nested(V, F, k: int, d_skel: float, max_tries: int = 6, bisect: int = 2) -> dict:
    """The smallest ``nested`` face count (build_cages(method="nested"), one layer) whose max distance
    (``tightness``) is <= ``d_skel``, the skeleton cage's: start at the skeleton cage's face count k,
    go down (3k/4, k/2, k/4, ...) while the nested cage is as tight, else up (1.5k, 2k, 3k, 4k, 6k)
    until it is, then ``bisect`` bisection steps between the last failing and the first passing
    count (targets rounded to even numbers). Returns every try (target, faces, max / mean distance, seconds or error) and the answer
    (``None`` if no try reached ``d_skel``)."""
    from exp_common import tightness

    from cagegen import build_cages

    tries: list = []

    def run(n):
        t = time.perf_counter()
        try:
            layers = build_cages(V, F, face_counts=[int(n)], method="nested", fallback=None)
            tt = tightness(*layers[1], V, F, 20000)
            r = {"target": int(n), "faces": len(layers[1][1]), "max_dist_rel": tt["max_dist_rel"],
                 "mean_dist_rel": tt["mean_dist_rel"], "volume_ratio": tt["volume_ratio"],
                 "seconds": time.perf_counter() - t}
        except Exception as exc:  # noqa: BLE001 -- recorded
            r = {"target": int(n), "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t}
        tries.append(r)
        print(json.dumps({"nested_try": r}), file=sys.stderr, flush=True)
        return r.get("max_dist_rel", np.inf) <= d_skel

    def even(x):
        return max(8, 2 * int(round(x / 2)))

    best, fail = None, None
    if run(k):
        best = k
        for f in (0.75, 0.5, 0.25, 0.125)[:max_tries - 1]:
            if not run(even(f * k)):
                fail = even(f * k)
                break
            best = even(f * k)
    else:
        fail = k
        for f in (1.5, 2, 3, 4, 6)[:max_tries - 1]:
            if run(even(f * k)):
                best = even(f * k)
                break
            fail = even(f * k)
    for _ in range(bisect):  # narrow the bracket (fail, best]
        if best is None or fail is None or best - fail <= 2:
            break
        mid = even(0.5 * (best + fail))
        if mid in (best, fail):
            break
        if run(mid):
            best = mid
        else:
            fail = mid
    ok = [r for r in tries if r.get("max_dist_rel", np.inf) <= d_skel]
    smallest = min(ok, key=lambda r: r["faces"]) if ok else None
    return {"skeleton_faces": int(k), "skeleton_max_dist_rel": float(d_skel), "tries": tries,
            "smallest_target": best, "largest_failing_target": fail, "smallest_faces": smallest["faces"] if smallest else None,
            "face_ratio_nested_over_skeleton": (smallest["faces"] / k) if smallest else None}


def run_case(case: str, zoo: Path | None, png: Path | None, compare_nested: bool,
             min_nested: bool = False) -> dict:
    from exp_common import tightness

    from cagegen import build_cages, verify_nesting
    from cagegen.skeleton import skeleton_cage

    V, F, S, bending = _load(case, zoo)
    out: dict = {"case": case, "input_vertices": len(V), "input_faces": len(F),
                 "skeleton": "known" if S is not None else "automatic (pygel3d MSLS)", "bending": bending}
    log: list = []
    t0 = time.perf_counter()
    try:
        c = skeleton_cage(V, F, S, bending=bending, **_OPTS,
                          progress=lambda msg: log.append((round(time.perf_counter() - t0, 2), msg)))
    except Exception as exc:  # noqa: BLE001 -- a failure is a result: the message names the step
        out.update({"certified": False, "error": f"{type(exc).__name__}: {exc}", "progress": log,
                    "seconds_total": time.perf_counter() - t0})
        cause = exc.__cause__  # nest_pair's failure (stage, flow summary) behind a skeleton CageError
        if cause is not None and isinstance(getattr(cause, "info", None), dict):
            out["failure"] = {"stage": getattr(cause, "stage", None), "flow": cause.info.get("flow"),
                              "seconds": cause.info.get("seconds")}
        part = getattr(exc, "partial", None)  # what was built before the failing step (not certified)
        if part is not None:
            out["seconds"] = part.info.get("seconds")
            out["sections"] = len(part.sections)
            if png is not None:
                png.mkdir(parents=True, exist_ok=True)
                step = str(exc).split(":")[0].removeprefix("skeleton cage, ")
                picture(V, F, part, png / f"skeleton_{Path(case).stem}.png", title=f"{case} ({step} failed)")
                out["png"] = str(png / f"skeleton_{Path(case).stem}.png")
        return out
    gap = float(_OPTS.get("min_gap", 0.0))
    rep = verify_nesting([(V, F), (c.V, c.F)], min_gap=gap)
    out.update({
        "min_gap": gap, "gap_rel": float(rep.pairs[0].min_gap_rel),
        "quad_share": 2 * len(c.quads) / len(c.F),
        "tight_cage_quads": c.info["tight_cage"]["n_quads"],
        "certified": bool(rep.ok),
        "cage_vertices": len(c.V), "cage_faces": len(c.F), "cage_quads": len(c.quads),
        "cage_junction_triangles": len(c.tris), "sections": len(c.sections),
        "skeleton_info": c.info["skeleton"], "seconds": c.info["seconds"],
        "field": c.info["field"], "pre_inflation": c.info["pre_inflation"],
        "tightness": tightness(c.V, c.F, V, F, 20000),
        "tight_cage_tightness": tightness(c.tight_V, c.F, V, F, 20000),
        "progress": log,
    })
    import hashlib

    out["cage_digest"] = hashlib.sha256(np.ascontiguousarray(c.V).tobytes()
                                        + np.ascontiguousarray(c.F).tobytes()).hexdigest()
    out["sections_flattened"] = c.info.get("sections_flattened")
    out["containment"] = (c.info.get("containment")
                          or {k: c.info["inflation"].get(k) for k in ("flow", "seconds")})
    if "extraction" in c.info:
        out["extraction"] = c.info["extraction"]
    if compare_nested:
        t = time.perf_counter()
        try:
            layers = build_cages(V, F, face_counts=[len(c.F)], method="nested", fallback=None)
            out["nested_same_faces"] = {"faces": len(layers[1][1]), "seconds": time.perf_counter() - t,
                                        "tightness": tightness(*layers[1], V, F, 20000)}
        except Exception as exc:  # noqa: BLE001 -- recorded
            out["nested_same_faces"] = {"error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t}
    if min_nested:
        out["smallest_nested_at_same_distance"] = smallest_nested(V, F, len(c.F),
                                                                  out["tightness"]["max_dist_rel"])
    if _TIGHTEN:
        out["tighten"] = tighten_measure(V, F, c, gap)
    if png is not None:
        png.mkdir(parents=True, exist_ok=True)
        picture(V, F, c, png / f"skeleton_{Path(case).stem}.png", title=case)
        out["png"] = str(png / f"skeleton_{Path(case).stem}.png")
    return out


def tighten_measure(V, F, c, gap: float) -> dict:
    """:func:`cagegen.skeleton.tighten.tighten_cage` applied to the certified cage ``c`` (CCD
    ``min_distance`` 1.05 x the clearance): its record, the verifier at the clearance, and the tightness
    after (the cage in the result is the untightened one)."""
    from exp_common import tightness

    from cagegen import verify_nesting
    from cagegen.skeleton.tighten import tighten_cage

    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    C2, info = tighten_cage(c.V, c.F, V, F, 1.05 * max(gap, 1e-4) * diag)
    rep = verify_nesting([(V, F), (C2, c.F)], min_gap=gap)
    return {"info": info, "certified": bool(rep.ok), "gap_rel": float(rep.pairs[0].min_gap_rel),
            "tightness": tightness(C2, c.F, V, F, 20000)}


def picture(V, F, c, path: Path, title: str) -> None:
    """Three panels: skeleton + sections, tight cage, certified cage (pyvista, off screen).

    ``c`` may be a failed run's ``CageError.partial`` (``certified=False``): the third panel is then the
    pre-inflated cage, labelled as not certified."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    p = pv.Plotter(off_screen=True, window_size=(1500, 520), shape=(1, 3))
    mesh = pv.PolyData(V, np.c_[np.full(len(F), 3), F].ravel())
    S = c.skeleton
    bones = pv.PolyData(S.nodes, lines=np.c_[np.full(len(S.edges), 2), S.edges].ravel())

    def cage_mesh(VV):
        faces = [np.r_[4, q] for q in c.quads] + [np.r_[3, t] for t in c.tris]
        return pv.PolyData(VV, np.concatenate(faces))

    if c.V is None:  # an assembly failure before any tight cage: skeleton and sections only
        panels = [("skeleton, bending nodes, sections", None), ("no tight cage", None), ("no cage", None)]
    elif "assembly_crossing_pairs" in c.info:
        # an assembly failure: the partial's cage is the self-intersecting tight cage
        panels = [("skeleton, bending nodes, sections", None),
                  (f"tight cage, self-intersecting ({len(c.F)} triangles)", c.tight_V), ("no cage", None)]
    else:
        panels = [("skeleton, bending nodes, sections", None), ("tight cage", c.tight_V),
                  (f"certified cage ({len(c.F)} triangles)" if getattr(c, "certified", True)
                   else f"start cage, NOT certified ({len(c.F)} triangles)", c.V)]
    for k, (name, VV) in enumerate(panels):
        p.subplot(0, k)
        p.add_mesh(mesh, color="tan", opacity=0.35 if k else 0.25)
        p.add_mesh(bones, color="red", line_width=4)
        if k == 0:
            p.add_points(S.nodes[S.bending], color="black", point_size=12, render_points_as_spheres=True)
            for s in c.sections:
                p.add_points(s["hits"], color="green", point_size=5, render_points_as_spheres=True)
                q = np.vstack([s["quad"], s["quad"][:1]])
                p.add_mesh(pv.lines_from_points(q), color="blue", line_width=3)
        elif VV is not None:
            p.add_mesh(cage_mesh(VV), style="wireframe", color="navy", line_width=2)
        p.add_text(f"{title}: {name}", font_size=9)
        p.view_isometric()
    p.screenshot(str(path))
    p.close()


def hierarchy_case(case: str = "stick", zoo: Path | None = None, face_counts=(1200, 76),
                   problems=("poisson-dirichlet", "poisson-neumann")) -> dict:
    """3-layer hierarchies (input, ``nested`` cage of ``face_counts[0]`` faces, coarsest cage) whose coarsest
    layer is the skeleton cage, beside the ``nested``-only one with the same face counts (a zoo mesh: the
    skeleton cage's own face count as the last); TetWild layers (nestmg defaults, automatic clearance),
    V(1,1) cycles (``MultigridSolver`` defaults), mean residual reduction per cycle to 1e-8. ``case``:
    ``"stick"`` (known skeleton) or a zoo file name (automatic skeleton)."""
    from cagegen import NestedOptions, SkeletonOptions
    from nestmg import SizingOptions, build_hierarchy, setup_problem
    from nestmg.io import normalize
    from solvers import MultigridSolver

    V, F, S, bending = _load(case, zoo)
    if S is not None:
        _, center, scale = normalize(V)
        S = S.transformed(1.0 / scale, center)  # nestmg works on a unit-diagonal copy: so must the skeleton
    out: dict = {"shape": Path(case).stem, "input_faces": len(F), "face_counts": list(face_counts)}
    cases = (("skeleton", SkeletonOptions(skeleton=S, bending=bending)), ("nested", NestedOptions()))
    for name, opts in cases:
        t = time.perf_counter()
        counts = list(out["face_counts"])
        try:
            h = build_hierarchy(V, F, len(counts) + 1, name, sizing=SizingOptions(face_counts=counts),
                                cages=opts, cache=False)
            res: dict = {"build_seconds": time.perf_counter() - t, "certified": bool(h.certified),
                         "tets": [len(T) for _, T in h.tets], "n_outside": [int(x) for x in h.n_outside],
                         "cage_faces": [len(Fk) for _, Fk in h.surfaces[1:]]}
            if name == "skeleton" and res["cage_faces"]:
                out["face_counts"] = counts[:-1] + [res["cage_faces"][-1]]  # nested-only: the same counts
            for pname in problems:
                prob = setup_problem(h.tets, h.P, pname)
                ml = MultigridSolver(prob.A, prob.P, nullspace=prob.nullspace)
                r: list = []
                ml.solve(prob.b, tol=1e-8, residuals=r, maxiter=60)
                r = np.asarray(r, float)
                res[pname] = {"cycles": len(r) - 1, "mean_factor": float((r[-1] / r[0]) ** (1 / max(len(r) - 1, 1)))}
        except Exception as exc:  # noqa: BLE001 -- recorded
            res = {"error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t}
        out[name] = res
        print(json.dumps({name: res}), file=sys.stderr, flush=True)
    return out


def _child(q, case, zoo, png, compare, min_nested=False):
    try:
        q.put(run_case(case, zoo, png, compare, min_nested))
    except Exception:  # noqa: BLE001 -- recorded as the result
        q.put({"case": case, "certified": False, "error": traceback.format_exc(limit=3)})


def _command(args) -> str:
    """The command line, the zoo folder written ``ZOO_DIR`` (no path of this machine in the JSON)."""
    cmd = " ".join(sys.argv)
    return cmd.replace(str(args.zoo), "ZOO_DIR") if args.zoo else cmd


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--zoo", type=Path, default=None, help="folder of the dev zoo meshes")
    ap.add_argument("--cases", nargs="*", default=None, help="star, stick and/or zoo file names")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/skeleton/cages_skeleton.json"))
    ap.add_argument("--png", type=Path, default=None)
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--min-nested", action="store_true",
                    help="per certified case, the smallest nested face count at the skeleton cage's max distance")
    ap.add_argument("--hierarchy", nargs="*", default=None, metavar="CASE",
                    help="only hierarchies (skeleton cage coarsest) beside nested-only, V-cycles: the stick "
                         "figure (no CASE) or zoo file names (with --zoo)")
    ap.add_argument("--tighten", action="store_true",
                    help="per certified case, measure the tightening post-step (cagegen.skeleton.tighten)")
    ap.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                    help="extra skeleton_cage keyword (Python literal value), e.g. --opt min_gap=0.0025")
    args = ap.parse_args(argv)
    import ast

    _OPTS.update({k: ast.literal_eval(v) for k, v in (o.split("=", 1) for o in args.opt)})
    global _TIGHTEN
    _TIGHTEN = args.tighten
    if args.hierarchy is not None:
        from nestmg.io import json_default

        res = [hierarchy_case(c, args.zoo) for c in (args.hierarchy or ["stick"])]
        out = {"benchmark": "cages_skeleton --hierarchy", "command": _command(args),
               **({"result": res[0]} if not args.hierarchy else {"results": res})}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1, default=json_default))
        print(json.dumps(out, default=json_default))
        return out
    cases = args.cases or (["star", "stick"] + (list(ZOO) if args.zoo else []))
    ctx = mp.get_context("fork")
    results = []
    for case in cases:
        q = ctx.Queue()
        t = time.perf_counter()
        p = ctx.Process(target=_child, args=(q, case, args.zoo, args.png,
                                             case in ("star", "stick") and not args.min_nested, args.min_nested))
        p.start()
        p.join(args.timeout)
        if p.is_alive():
            p.terminate()
            p.join()
            res = {"case": case, "certified": False, "error": f"timeout after {args.timeout:.0f} s"}
        else:
            res = q.get() if not q.empty() else {"case": case, "certified": False, "error": "child died"}
        res["wall_seconds"] = time.perf_counter() - t
        results.append(res)
        print(json.dumps({k: res.get(k) for k in ("case", "certified", "cage_faces", "error", "wall_seconds")}),
              file=sys.stderr, flush=True)
    from nestmg.io import json_default

    out = {"benchmark": "cages_skeleton", "command": _command(args), "options": _OPTS, "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1, default=json_default))
    print(json.dumps(out, default=json_default))
    return out


if __name__ == "__main__":
    main()
