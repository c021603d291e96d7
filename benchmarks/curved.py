"""Curved P2 on real inputs: fit, certified validity, accuracy vs P1 at equal unknowns, MG-PCG iterations.

For every MESH (a closed surface): the pipeline's hierarchy (``build_hierarchy``: TetWild at 2 h_0, the
fine level its red refinement, then nested cages); level 1 curved onto the input surface
(:func:`nestmg.curved.curve_mesh` with libigl's closest points), so that P2 on level 1 has exactly the
unknowns of P1 on level 0. Recorded per mesh:

* the curving: boundary edge nodes, tets invalid after projection, fitted by the energy, straightened,
  certified, min / mean scaled Jacobian (``min det J / max det J`` per curved tet, sampled and its
  certified Bernstein lower bound) before and after the quality pass, the straight tets' own (linear)
  scaled Jacobian, largest and mean distance of the boundary facets to the input surface (straight
  and curved), seconds per stage;
* a manufactured solution ``u = sin(6x) e^{2y} cos(4z)`` (``-Δu = 48u``) on the normalised shape
  (unit bounding-box diagonal), Dirichlet data ``u`` and Neumann flux ``∇u·n`` taken at the closest
  point of the *input surface* (``n``: the smooth normal of :func:`nestmg.curved.surface_projector`,
  corner normals interpolated on the closest triangle; ``neumann_face``: the closest triangle's own
  normal, discontinuous across the input's edges): L2 errors against ``u`` by quadrature over each
  discrete domain of P1 on level 0 (boundary vertices projected onto the input), straight P2 and
  curved P2 on level 1 (with and without the quality pass, and partially curved up to the
  scaled-Jacobian floor ``--sj-floor`` without quality pass); MG-PCG iterations to 1e-8 (default
  cycle), seconds.

Run from the repository root::

    OMP_NUM_THREADS=1 python benchmarks/curved.py ZOO_DIR/bunny.off ZOO_DIR/gargo.off ZOO_DIR/fandisk.obj \\
        --edge-length 0.015 --quality 0.96 --quality-lam 1.0 --sj-floor 0.955 0.7 \\
        --json benchmarks/results/curved/curved.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from nestmg import build_hierarchy, load_mesh, setup_problem
from nestmg.curved import curve_mesh, p2_nodes, p2_prolongation, surface_projector
from nestmg.io import json_default
from exp_common import git_commit, write_json  # benchmarks/ is sys.path[0]
from nestmg.tetmesh import orient_tets, tet_volumes
from solvers import stiffness_matrix
from solvers.fem_p2 import p2_boundary_facets, p2_l2_error, p2_load, p2_neumann_load
from nestmg import SizingOptions

A, B, C = 6.0, 2.0, 4.0  # u = sin(A x) e^{B y} cos(C z), Δu = (B² - A² - C²) u


def exact(x):
    return np.sin(A * x[:, 0]) * np.exp(B * x[:, 1]) * np.cos(C * x[:, 2])


def grad(x):
    s, c = np.sin(A * x[:, 0]), np.cos(A * x[:, 0])
    e, cz, sz = np.exp(B * x[:, 1]), np.cos(C * x[:, 2]), np.sin(C * x[:, 2])
    return np.c_[A * c * e * cz, B * s * e * cz, -C * s * e * sz]


def source(x):
    return (A**2 + C**2 - B**2) * exact(x)


def _data(proj):
    """Dirichlet values and Neumann flux given on the input surface (at the closest point)."""
    return (lambda x: exact(proj(x)[0]),
            lambda x, n: np.einsum("ij,ij->i", grad(proj(x)[0]), proj(x)[1]))


def _solve(prob, tol):
    ml = prob.multigrid()
    t0 = time.perf_counter()
    x, info = ml.solve(prob.b, tol=tol, accel="cg", return_info=True)
    return prob.expand(x), int(info["iterations"]), time.perf_counter() - t0


def p1_case(h, Vp, name, proj, tol):
    """P1 on level 0 (boundary vertices ``Vp``), loads by quadrature, the pipeline's P1 multigrid."""
    V0, T0 = h.tets_in("normalized")[0]
    T0 = orient_tets(Vp, T0)
    t0 = time.perf_counter()
    X, T10, E = p2_nodes(Vp, T0)  # straight P2 nodes: exact P1 quadrature through the P1 -> P2 map
    Pp = p2_prolongation(len(Vp), E)
    prob = setup_problem([(Vp, T0), *h.tets_in("normalized")[1:]], h.P, name)
    b = Pp.T @ p2_load(X, T10, source)
    g, flux = _data(proj)
    F6 = p2_boundary_facets(T10)[0]
    if name == "poisson-dirichlet":
        free = prob.free[0]
        bnd = np.setdiff1d(np.arange(len(Vp)), free)
        fixed = np.zeros(len(Vp))
        fixed[bnd] = g(Vp[bnd])
        K = stiffness_matrix(Vp, T0)
        prob.b = b[free] - K[free][:, bnd] @ fixed[bnd]
        prob.fixed_values = fixed
    else:
        b = b + Pp.T @ p2_neumann_load(X, F6, flux)
        m = Pp.T @ p2_load(X, T10, lambda x: np.ones(len(x)))
        prob.b = b - b.sum() * m / m.sum()
    t_setup = time.perf_counter() - t0
    u, its, t_solve = _solve(prob, tol)
    err = p2_l2_error(X, T10, Pp @ u, exact, remove_mean=name != "poisson-dirichlet")
    return {"unknowns": int(len(prob.b)), "nodes": int(len(Vp)), "l2_error": err, "iterations": its,
            "seconds": {"setup": t_setup, "solve": t_solve}}


def p2_case(h, cm, name, proj, tol):
    """Straight (``cm=None``) or curved P2 on level 1 with p-multigrid onto the P1 levels 1, 2, ..."""
    g, flux = _data(proj)
    kw = {"boundary_values": g} if name == "poisson-dirichlet" else {"flux": flux}
    t0 = time.perf_counter()
    prob = setup_problem(h.tets_in("normalized")[1:], h.P[1:], name, element="P2", curved=cm, f=source, **kw)
    t_setup = time.perf_counter() - t0
    u, its, t_solve = _solve(prob, tol)
    err = p2_l2_error(prob.mesh.X, prob.mesh.T10, u, exact, remove_mean=name != "poisson-dirichlet")
    return {"unknowns": int(len(prob.b)), "nodes": int(len(u)), "l2_error": err, "iterations": its,
            "seconds": {"setup": t_setup, "solve": t_solve}}


def _hierarchy(path: str, args):
    V, F = load_mesh(path)
    t0 = time.perf_counter()
    h = build_hierarchy(V, F, args.levels, args.method, sizing=SizingOptions(edge_length=args.edge_length),
                        progress=False)
    t_h = time.perf_counter() - t0
    if not str(h.prolongation_reports[0].extrapolation).startswith("none (refinement)"):
        raise SystemExit(f"{path}: level 0 is not the refinement of level 1 (use TetWild and >= 3 levels)")
    return h, len(F), t_h


def _curve(h, proj, args, quality, sj_floor=None):
    t0 = time.perf_counter()
    cm = curve_mesh(*h.tets_in("normalized")[1], proj, lam=args.lam, quality=quality,
                    quality_lam=args.quality_lam, sj_floor=sj_floor)
    return cm, cm.report | {"seconds_total": time.perf_counter() - t0}


def _problem_row(h, Vp, cms, name, proj, tol) -> dict:
    """P1, straight P2 and curved P2 (each curving of ``cms``) on one problem; errors and iterations."""
    r = {"P1": p1_case(h, Vp, name, proj, tol), "P2_straight": p2_case(h, None, name, proj, tol)}
    for key, cm in cms.items():
        r[key] = p2_case(h, cm, name, proj, tol)
    r["p1_over_curved"] = r["P1"]["l2_error"] / r["P2_curved"]["l2_error"]
    r["straight_over_curved"] = r["P2_straight"]["l2_error"] / r["P2_curved"]["l2_error"]
    for key in [k for k in r if k.startswith("P2_curved_floor_")]:
        r["p1_over_" + key[3:]] = r["P1"]["l2_error"] / r[key]["l2_error"]
    return r


def run_mesh(path: str, args) -> dict:
    h, n_faces, t_h = _hierarchy(path, args)
    Vs, Fs = h.surfaces_in("normalized")[0]
    proj = surface_projector(Vs, Fs, normals="smooth")
    cm, rep = _curve(h, proj, args, args.quality)
    cm0, rep0 = _curve(h, proj, args, None)  # the same without the quality pass
    floors = {}  # partial curving up to each floor instead of the quality pass
    for fl in args.sj_floor:
        cmf, repf = _curve(h, proj, args, None, fl)
        floors[f"{fl:g}"] = (cmf, repf)
        print(f"{Path(path).name}: scaled Jacobian min / mean {rep0['scaled_jacobian']['min']:.3f} / "
              f"{rep0['scaled_jacobian']['mean_all']:.3f} -> floor {fl:g}: "
              f"{repf['scaled_jacobian']['min']:.3f} / {repf['scaled_jacobian']['mean_all']:.3f}, "
              f"{repf['sj_floor']['backed_off']} of {repf['sj_floor']['curved_edge_nodes']} edge nodes "
              "backed off", flush=True)
    # P1 on level 0 with its boundary vertices on the input: the nodes of the curving without quality pass
    V0 = h.tets_in("normalized")[0][0]
    assert len(V0) == len(cm0.X)
    Vp = cm0.X.copy()
    if np.any(tet_volumes(Vp, orient_tets(V0, h.tets[0][1])) <= 0):
        Vp = V0  # a projected vertex would invert a P1 tet: keep TetWild's boundary
    out = {"mesh": Path(path).name, "input_faces": n_faces, "hierarchy": {
        "tets": [len(T) for _, T in h.tets], "nodes": [len(Vk) for Vk, _ in h.tets], "certified": h.certified,
        "seconds": t_h}, "curving": rep, "curving_no_quality": rep0,
        "curving_floor": {k: rep_f for k, (_, rep_f) in floors.items()},
        "p1_vertices_projected": Vp is not V0,
        "problems": {}}
    cms = {"P2_curved": cm, "P2_curved_no_quality": cm0} | {f"P2_curved_floor_{k}": c for k, (c, _) in
                                                             floors.items()}
    face = surface_projector(Vs, Fs, normals="face")
    for name, pr, key in (("poisson-dirichlet", proj, "poisson-dirichlet"),
                          ("poisson-neumann", proj, "poisson-neumann"),
                          ("poisson-neumann", face, "neumann_face")):
        r = _problem_row(h, Vp, cms if key != "neumann_face" else {"P2_curved": cm}, name, pr, args.tol)
        out["problems"][key] = r
        print(f"{out['mesh']} {key}: L2 P1 {r['P1']['l2_error']:.3e} ({r['P1']['iterations']} it), "
              f"P2 straight {r['P2_straight']['l2_error']:.3e} ({r['P2_straight']['iterations']} it), "
              f"P2 curved {r['P2_curved']['l2_error']:.3e} ({r['P2_curved']['iterations']} it)"
              + "".join(f", {k[3:]} {v['l2_error']:.3e} ({v['iterations']} it)" for k, v in r.items()
                        if k.startswith("P2_curved_floor_")), flush=True)
    return out


def picture(path: str, png: str, edge: float) -> dict:
    """A coarse TetWild mesh of ``path`` curved onto it, drawn beside its straight version."""
    from nestmg import tetrahedralize
    from nestmg.io import normalize
    from nestmg.render import render_curved

    if path == "shape:torus":  # the procedural solid torus and its exact closest points
        from nestmg.curved import torus_projector
        from nestmg.shapes import torus_tets

        (Vt, Tt), proj = torus_tets(0, segments=12)[0][0], torus_projector()
    else:
        V, F = load_mesh(path)
        Vn = normalize(V)[0]
        Vt, Tt = tetrahedralize(Vn, F, edge_length=edge, coarsen=True)
        proj = surface_projector(Vn, F, normals="smooth")
    cm = curve_mesh(Vt, Tt, proj)
    rep = cm.report
    render_curved(cm.X, cm.boundary_facets(), cm.straight().X, png, titles=(
        f"straight: {len(Tt):,} tets, surface distance <= {rep['surface_distance']['straight_max']:.4f}",
        f"curved P2: certified={rep['certified']}, scaled Jacobian >= {rep['scaled_jacobian']['min']:.3f}, "
        f"distance <= {rep['surface_distance']['curved_max']:.4f}"))
    return {"mesh": Path(path).name, "edge_length": edge, "png": png, "curving": rep}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("meshes", nargs="+", help="closed surface meshes (e.g. ZOO_DIR/bunny.off)")
    p.add_argument("--json", required=True, help="output JSON")
    p.add_argument("--levels", type=int, default=4)
    p.add_argument("--method", default="nested")
    p.add_argument("--edge-length", type=float, default=0.015,
                   help="fine edge / bbox diagonal (level 1: twice)")
    p.add_argument("--lam", type=float, default=0.05, help="λ of the fitting energy")
    p.add_argument("--quality", type=float, default=0.96,
                   help="scaled-Jacobian threshold of the quality pass")
    p.add_argument("--quality-lam", type=float, default=1.0, help="λ of the quality pass")
    p.add_argument("--sj-floor", type=float, nargs="+", default=[0.955, 0.7],
                   help="scaled-Jacobian floors of the partial curving (a curving each, no quality pass)")
    p.add_argument("--tol", type=float, default=1e-8)
    p.add_argument("--png", default=None, help="also draw a coarse curved mesh of --png-mesh here")
    p.add_argument("--png-mesh", default=None, help="surface for the picture (default: the first MESH; "
                                                      "shape:torus: the procedural solid torus)")
    p.add_argument("--png-edge", type=float, default=0.08,
                   help="TetWild edge / bbox diagonal of the picture's mesh")
    p.add_argument("--png-only", action="store_true", help="only the picture (no hierarchy, no solves)")
    args = p.parse_args(argv)
    if args.png:
        pic = picture(args.png_mesh or args.meshes[0], args.png, args.png_edge)
        print(f"wrote {args.png}: {pic['curving']['tets']} tets, certified {pic['curving']['certified']}")
        if args.png_only:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps({"picture": pic | {"png": Path(pic["png"]).name}}, indent=1,
                                                  default=json_default))
            return 0
    commit = git_commit()
    zoo = " ".join(f"ZOO_DIR/{Path(m).name}" for m in args.meshes)
    res = {"command": f"python benchmarks/curved.py {zoo} --levels {args.levels} --method {args.method}"
           + f" --edge-length {args.edge_length} --lam {args.lam}"
           + f" --quality {args.quality} --quality-lam {args.quality_lam} --sj-floor "
           + " ".join(f"{f:g}" for f in args.sj_floor),
           "commit": commit, "machine": platform.machine(), "solution": "sin(6x) exp(2y) cos(4z)",
           "results": [run_mesh(m, args) for m in args.meshes], "picture": pic if args.png else None}
    write_json(res, Path(args.json))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
