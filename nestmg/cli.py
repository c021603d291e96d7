"""Command line: ``nestmg demo | cages | solve | compare``.

MESH arguments are a surface file (OBJ/OFF/PLY/STL), a tet-mesh file (``.msh``, ``.mesh``, ``.vtu``,
``.vtk`` through meshio: the file's tets become the fine level, :func:`nestmg.hierarchy_from_tets`) or
``shape:NAME`` for a built-in procedural shape (``sphere``, ``torus``, ``genus2``, ``neck_blobs``,
``thin_plate``). Inputs are normalised to a unit
bounding-box diagonal before any work; outputs are written atomically and never over the input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from cagegen.errors import NestmgError
from solvers.errors import SolverError

from .cache import atomic_write_bytes
from .io import json_default

__all__ = ["main"]


def _load(mesh: str) -> tuple[np.ndarray, np.ndarray, str]:
    """Normalised nodes, cells ((m,3) triangles, or (t,4) tets from a tet-mesh file) and a name."""
    from .io import TET_FORMATS, load_mesh, read_cells
    from .shapes import SHAPES

    if mesh.startswith("shape:"):
        name = mesh.split(":", 1)[1]
        if name not in SHAPES:
            raise NestmgError(f"unknown built-in shape {name!r}; choose from {sorted(SHAPES)}")
        V, F = SHAPES[name](res=24)
    elif Path(mesh).suffix.lower() in TET_FORMATS:  # tets if the file has them, else its triangles
        V, T, F = read_cells(mesh)
        if T is None and F is None:
            raise NestmgError(f"{mesh}: neither tetrahedra nor triangles in the file")
        F = T if T is not None else F
        name = Path(mesh).stem
    else:
        V, F = load_mesh(mesh)
        name = Path(mesh).stem
    # no normalisation here: build_hierarchy / build_cage_surfaces normalise inside and return (and the
    # commands write) everything in the input's coordinates
    return np.ascontiguousarray(V, dtype=np.float64), F, name


def _refuse_overwriting_input(mesh: str, outputs: list[Path]) -> None:
    """Raise :class:`NestmgError` if an output path is the input mesh file (checked before any work)."""
    if mesh.startswith("shape:"):
        return
    src = Path(mesh).resolve()
    for out in outputs:
        if Path(out).resolve() == src:
            raise NestmgError(f"refusing to write {out}: it is the input mesh {mesh}; choose another output")


def _write_json(path: str | Path, obj: Any) -> None:
    atomic_write_bytes(Path(path), json.dumps(obj, indent=1, default=json_default).encode())


def _cage_options(args, method: str):
    """The cage method's options (:func:`cagegen.options_class`) from ``--repair``, ``--min-gap`` and the
    method-specific :data:`CAGE_FLAGS` (``--cage-time-budget``, 0: no limit; ``--cage-threads``)."""
    import dataclasses

    from cagegen import options_class, registered_backends

    opts = {"repair": args.repair, "min_gap": args.min_gap}
    for flag, (_, field) in CAGE_FLAGS.items():
        value = getattr(args, field, None)
        if value is None:
            continue

        def takes(m: str) -> bool:
            return field in {f.name for f in dataclasses.fields(options_class(m))}

        if not takes(method):
            names = " and ".join(m for m in registered_backends() if takes(m))
            raise NestmgError(f"{flag} applies to --method {names} only, not {method!r}")
        opts[field] = (value if value > 0 else None) if field == "cage_time_budget" else value
    return options_class(method)(**opts)


def _hierarchy(V, F, args, method=None):
    from .hierarchy import build_hierarchy

    method = method or args.method
    kw = {"sizing": args.sizing, "meshing": args.meshing, "cages": _cage_options(args, method),
          "cache": not args.no_cache, "progress": None if args.quiet is False else False}
    if F.shape[1] == 4:  # a tet mesh: it is the fine level, cages of its boundary below it
        from .usermesh import hierarchy_from_tets

        return hierarchy_from_tets(V, F, args.levels, method, **kw)
    return build_hierarchy(V, F, args.levels, method, **kw)


def _p2_level(h) -> int:
    """The level that carries P2: 1 when level 0 is the red refinement of level 1 (same unknowns), else 0."""
    rep = h.prolongation_reports[0] if h.prolongation_reports else None
    return 1 if rep is not None and str(rep.extrapolation).startswith("none (refinement)") else 0


def _curve(h, base: int, quality: float | None = None, sj_floor: float | None = None,
           relax: float | None = None):
    """Level ``base`` of ``h`` curved onto the input surface (normalised frame), certified."""
    from .curved import curve_mesh, surface_projector

    Vs, Fs = h.surfaces_in("normalized")[0]
    return curve_mesh(*h.tets_in("normalized")[base], surface_projector(Vs, Fs), quality=quality,
                      sj_floor=sj_floor, relax=relax)


def _solve(h, args, solution: bool = False) -> dict:
    from .run import solve_on_hierarchy

    # the model problems are posed on the normalised shape (unit bounding-box diagonal), so --lam and
    # the right-hand side mean the same for every input scale
    tets, P, extra = h.tets_in("normalized"), h.P, {}
    if getattr(args, "element", "P1") == "P2":
        if args.problem.startswith("elasticity"):
            raise NestmgError("--element P2 supports the scalar problems only (not elasticity)")
        base = _p2_level(h)
        cm = _curve(h, base, getattr(args, "quality", None), getattr(args, "sj_floor", None),
                    getattr(args, "relax", None))
        tets, P, extra = tets[base:], P[base:], {"element": "P2", "curved": cm}
    r = solve_on_hierarchy(tets, P, args.problem, args.solver, return_solution=solution, **extra)
    if extra:
        r["curved"] = cm.report | {"level": base}
        r["p2_mesh"] = cm  # popped before the report is written
    return r


def _print_solve(label: str, h, r: dict) -> None:
    status = "DIVERGED" if r["diverged"] else ("converged" if r["converged"] else "not converged")
    fb = "".join(f" layer {d['layer']} by fallback {d['fallback']!r}" for d in h.fallbacks)
    print(f"{label:<10} levels={h.levels} tets={[len(T) for _, T in h.tets]} n_outside={h.n_outside} "
          f"certified={h.certified}{fb}")
    deflated = [f"level {d['level']}: {d['modes']}" for d in r.get("deflation") or [] if d["modes"]]
    local = [f"level {d['level']}: {d['local_solve']['nodes']} nodes" for d in r.get("deflation") or []
             if d.get("local_solve", {}).get("kept")]
    extra = (f", {r['coarse_nu']} coarse sweeps" if r.get("coarse_nu", r["nu"]) != r["nu"] else "") + (
        f", boundary layer +1 ({r['local_nodes']} nodes)" if r.get("local_nodes") else "") + (
        f", slow modes deflated ({', '.join(deflated)})" if deflated else "") + (
        f", local solves ({', '.join(local)})" if local else "")
    cyc = r.get("cycle") or "V"
    print(f"{'':<10} {r['problem']} ({r['coarse']}, {r['smoother']} {cyc}({r['nu']},{r['nu']}){extra}): factor "
          f"{r['factor']:.3f}, {r['iterations']} cycles, {status}, final residual {r['residuals'][-1]:.2e}")


def _png_layers(h, path, title):
    from .render import render_layers

    # same-domain levels (the refined fine level, same_domain_levels) share their surface: draw it once
    layers = [S for k, S in enumerate(h.surfaces) if k == 0 or S[0] is not h.surfaces[k - 1][0]]
    render_layers(layers, path, title=title)


def cmd_demo(args) -> int:
    from .render import plot_convergence

    V, F, _ = _load(f"shape:{args.shape}")
    out = Path(args.out)
    print(f"nestmg demo: {args.shape} ({len(F)} faces), {args.levels} levels, cages by {args.method!r}")
    h = _hierarchy(V, F, args)
    print(repr(h))
    results = {}
    for problem in ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann"):
        args.problem = problem
        r = _solve(h, args)
        results[problem] = r
        _print_solve(args.method, h, r)
    _write_json(out / "report.json", {"shape": args.shape, "hierarchy": h.to_dict(), "solves": results})
    if not args.no_png:
        _png_layers(h, out / "layers.png", f"{args.shape}: {args.method} cages")
        cyc = f"{r['cycle']}({r['nu']},{r['nu']})"  # the scalar problems' cycle (SolverOptions.resolved)
        plot_convergence({p: res["residuals"] for p, res in results.items()}, out / "convergence.png",
                         title=f"{args.shape}, {h.levels} levels, {args.method} cages, {cyc}")
    print(f"wrote {out / 'report.json'}" + ("" if args.no_png else f", {out / 'layers.png'}, {out / 'convergence.png'}"))
    return 0


def cmd_cages(args) -> int:
    from .hierarchy import build_cage_surfaces
    from .io import save_mesh

    out = Path(args.out)
    n_layers = args.levels if args.face_counts is None else len(args.face_counts) + 1
    _refuse_overwriting_input(args.mesh, [out / f"layer_{k}.obj" for k in range(n_layers)] + [out / "report.json"])
    V, F, name = _load(args.mesh)
    if F.shape[1] == 4:  # a tet mesh: cage its boundary surface
        from .usermesh import boundary_surface

        V, F, _ = boundary_surface(V, F)
    # the same function and clearance as `solve`, layers in the input's coordinates
    n_layers = args.levels if args.face_counts is None else len(args.face_counts) + 1
    V, F, bodies = _bodies(V, F, args.repair)
    if bodies:
        return _cages_bodies(bodies, n_layers, args, name, out)
    layers, info = build_cage_surfaces(
        V, F, n_layers, args.method, sizing=args.sizing, meshing=args.meshing,
        cages=_cage_options(args, args.method), cache=not args.no_cache,
        progress=None if args.quiet is False else False,
    )
    for k, (Vk, Fk) in enumerate(layers):
        save_mesh(out / f"layer_{k}.obj", Vk, Fk)
    _write_json(out / "report.json", {"mesh": args.mesh, "method": args.method,
                                      "faces": [len(Fk) for _, Fk in layers], **info})
    ver = info.get("verification", {})
    from cagegen.build import fallback_layers

    fb = [f"layer {d['layer']} by fallback {d['fallback']!r}" for d in fallback_layers(info)]
    print(f"{name}: {len(layers)} layers {[len(Fk) for _, Fk in layers]} faces; verifier ok={ver.get('ok')}"
          + (f"; {', '.join(fb)}" if fb else ""))
    if args.png:
        from .render import render_layers

        render_layers(layers, out / "layers.png", title=f"{name}: {args.method}")
    print(f"wrote {out}/layer_*.obj and report.json")
    return 0


def _body_cages(bodies, n_layers: int, args, name: str, method: str | None = None) -> tuple[list, list]:
    """Each body's cage layers and info (:func:`nestmg.hierarchy.build_cage_surfaces`: its own clearance and
    face counts, ``n_layers`` a ceiling)."""
    import time

    from .bodies import audit_bodies, naming_body
    from .hierarchy import build_cage_surfaces
    from .progress import stage_line

    method = method or args.method
    if args.face_counts is not None:
        raise NestmgError(f"--face-counts counts one solid's cage faces; {name} has {len(bodies)} disjoint "
                          "bodies: give --levels instead (each body gets the levels that fit it)")
    audit_bodies(bodies, repair=bool(args.repair))  # a bad last body fails in seconds
    t0 = time.perf_counter()
    per_body, infos = [], []
    for k, (Vb, Fb) in enumerate(bodies):
        stage_line(f"body {k + 1}/{len(bodies)}: {len(Fb):,} faces", t0)
        with naming_body(k, len(bodies)):
            layers, info = build_cage_surfaces(Vb, Fb, n_layers, method, sizing=args.sizing,
                                               meshing=args.meshing, cages=_cage_options(args, method),
                                               cache=not args.no_cache,
                                               progress=None if args.quiet is False else False)
        per_body.append(layers)
        infos.append({"faces": [len(Fk) for _, Fk in layers], **info})
    return per_body, infos


def _cages_bodies(bodies, n_layers: int, args, name: str, out: Path) -> int:
    """``nestmg cages`` on several disjoint bodies: layer ``k`` of every body that has it in ``layer_k.obj``."""
    from cagegen.build import fallback_layers

    from .io import save_mesh

    per_body, infos = _body_cages(bodies, n_layers, args, name)
    combined = _body_layers(per_body)
    for k, (Vk, Fk) in enumerate(combined):
        save_mesh(out / f"layer_{k}.obj", Vk, Fk)
    oks = [(i.get("verification") or {}).get("ok") for i in infos]
    ok = None if any(o is None for o in oks) else all(oks)
    _write_json(out / "report.json", {"mesh": args.mesh, "method": args.method,
                                      "faces": [len(Fk) for _, Fk in combined], "verification": {"ok": ok},
                                      "bodies": infos})
    fb = [f"body {b + 1} layer {d['layer']} by fallback {d['fallback']!r}"
          for b, i in enumerate(infos) for d in fallback_layers(i)]
    print(f"{name}: {len(bodies)} bodies, {len(combined)} layers {[len(Fk) for _, Fk in combined]} faces "
          f"(per body {[i['faces'] for i in infos]}); verifier ok={ok}" + (f"; {', '.join(fb)}" if fb else ""))
    if args.png:
        from .render import render_layers

        render_layers(combined, out / "layers.png", title=f"{name}: {args.method}, {len(bodies)} bodies")
    print(f"wrote {out}/layer_*.obj and report.json")
    return 0


def cmd_solve(args) -> int:
    from .render import plot_convergence

    vtu = [Path(args.out) / f"level_{k}.vtu" for k in range(args.levels)] if args.out else []
    _refuse_overwriting_input(args.mesh, [Path(p) for p in (args.json,) if p] + vtu)
    V, F, name = _load(args.mesh)
    V, F, bodies = _bodies(V, F, args.repair)
    if bodies:
        return _solve_bodies(V, F, bodies, args, name)
    h = _hierarchy(V, F, args)
    r = _solve(h, args, solution=bool(args.out))
    u = r.pop("solution", None)
    cm = r.pop("p2_mesh", None)
    _print_solve(args.method, h, r)
    if cm is not None:
        c = r["curved"]
        print(f"{'':<10} P2 on level {c['level']} ({len(cm.X):,} nodes): {c['curved_tets']:,} curved tets, "
              f"{c['invalid_after_projection']} invalid after projection, {c['straightened']} straightened, "
              f"certified={c['certified']}, scaled Jacobian min {c['scaled_jacobian']['min']:.3f}")
    if args.out and cm is not None:  # the curved P2 mesh with u (tetra10), then every level without u
        from .io import save_tet_mesh
        from .usermesh import write_vtu_levels

        p2 = Path(args.out) / "p2.vtu"
        save_tet_mesh(p2, h.to_user(cm.X), cm.T10, point_data={"u": u})
        files = [p2, *write_vtu_levels(args.out, h, {})]
        print(f"wrote {', '.join(str(f) for f in files)}")
    elif args.out:  # every level's tet mesh; the solution on level 0; in the input's coordinates
        from .problems import default_rhs
        from .usermesh import write_vtu_levels

        # elasticity: u is the (n, 3) displacement; the scalar source f is not its load
        fields = ({} if args.problem.startswith("elasticity") else  # the source the problem was given
                  {"f": default_rhs(h.tets_in("normalized")[0][0])}) | (
            {"u": u} if u is not None else {})
        files = write_vtu_levels(args.out, h, fields)  # h.tets are in the input's coordinates
        print(f"wrote {', '.join(str(f) for f in files)}")
    png = _write_report(args, {"mesh": args.mesh, "hierarchy": h.to_dict(), "solve": r})
    if png is not None:
        _png_layers(h, png / "layers.png", f"{name}: {args.method}")
        plot_convergence({args.method: r["residuals"]}, png / "convergence.png", title=f"{name}: {args.problem}")
    return 0


def _bodies(V, F, repair: bool = False):
    """``(V, F, bodies)``: the disjoint bodies of a surface input of several closed pieces
    (:func:`nestmg.bodies.disjoint_bodies`; specks refused, or dropped with ``--repair``), else None; ``V, F``
    the one body left when the others were specks."""
    from cagegen import MeshInputError

    from .bodies import disjoint_bodies, drop_specks

    why: list = []
    bodies = disjoint_bodies(V, F, why) if F.shape[1] == 3 else None
    if why and not repair:  # pieces that cross or nest: say so, not only "several connected components"
        import re

        nested = re.match(r"component (\d+) lies inside component (\d+)", why[0])
        if nested:  # a void facing outward (inward it would be a solid with a void: nestmg.cavities)
            raise MeshInputError(f"input: component {nested[1]} lies inside component {nested[2]} and faces "
                                 "outward: a void's surface must face the void (--repair reads a piece inside an "
                                 "odd number of others as a void)")
        raise MeshInputError(f"input: {why[0]} (--repair replaces crossing pieces by their union)")
    if why:  # --repair: clean parts that overlap become their exact union, maybe several bodies
        V, F, bodies = _union_bodies(V, F, bodies)
    if bodies:
        bodies = drop_specks(bodies, repair)
        if len(bodies) == 1:
            return (*bodies[0], None)
    return V, F, bodies


def _union_bodies(V, F, bodies):
    """``(V, F, bodies)`` after :func:`nestmg.solid.exact_union` of crossing or nesting clean parts when their
    union is several disjoint bodies (one stage line); unchanged when it is one solid (the pipeline's repair
    makes the same union and reports it) or when the union does not apply (the repair's TetWild solid)."""
    import time

    from .bodies import disjoint_bodies
    from .progress import stage_line
    from .solid import exact_union

    t0 = time.perf_counter()
    union = exact_union(V, F)
    if union is None or union[2]["bodies"] == 1:
        return V, F, bodies
    W, G, info = union
    stage_line(f"repair: crossing pieces -> their exact union: {len(F):,} -> {len(G):,} faces, "
               f"{info['bodies']} bodies, voids filled "
               f"{info['volume_filled'] / info['volume']:.2%} ({time.perf_counter() - t0:.1f} s)", t0)
    return W, G, disjoint_bodies(W, G)


def _body_hierarchies(V, F, bodies, args):
    from .bodies import build_body_hierarchies

    return build_body_hierarchies(V, F, args.levels, args.method, bodies=bodies, sizing=args.sizing,
                                  meshing=args.meshing, cages=_cage_options(args, args.method),
                                  cache=not args.no_cache, progress=None if args.quiet is False else False)


def _solve_bodies(V, F, bodies, args, name: str) -> int:
    """``nestmg solve`` on several disjoint bodies: one hierarchy and one solve per body, files with all."""
    from .bodies import file_frame, merge_meshes, solve_bodies
    from .problems import default_rhs
    from .render import plot_convergence

    if getattr(args, "element", "P1") == "P2":
        raise NestmgError(f"--element P2 takes one solid; {name} has {len(bodies)} disjoint bodies: split the file")
    hs = _body_hierarchies(V, F, bodies, args)
    frame = file_frame(V)
    r = solve_bodies(hs, frame, args.problem, args.solver, return_solution=bool(args.out))
    u = r.pop("solution", None)
    for k, (h, rk) in enumerate(zip(hs, r["bodies"])):
        _print_solve(f"body {k + 1}", h, rk)
    status = "DIVERGED" if r["diverged"] else ("converged" if r["converged"] else "not converged")
    print(f"{len(hs)} bodies: largest factor {r['factor']:.3f} (body {r['worst_body'] + 1}), most cycles "
          f"{r['iterations']}, {status}")
    if args.out:  # level k of every body that has it, one file per level; u and f on level_0.vtu
        from .io import save_tet_mesh

        files = []
        for k in range(max(h.levels for h in hs)):
            Vk, Tk, owner = merge_meshes([h.tets[k] for h in hs if k < h.levels])
            pdata = {}
            if k == 0 and not args.problem.startswith("elasticity"):
                pdata["f"] = default_rhs((Vk - frame[0]) / frame[1])  # the source the problems were given
            if k == 0 and u is not None:
                pdata["u"] = u
            body = np.flatnonzero([k < h.levels for h in hs]).astype(np.int32)[owner]
            files.append(Path(args.out) / f"level_{k}.vtu")
            save_tet_mesh(files[-1], Vk, Tk, point_data=pdata,
                          cell_data={"level": np.full(len(Tk), k, dtype=np.int32), "body": body})
        print(f"wrote {', '.join(str(f) for f in files)}")
    report = {"mesh": args.mesh, "bodies": [{"hierarchy": h.to_dict(), "solve": rk}
                                            for h, rk in zip(hs, r.pop("bodies"))], "solve": r}
    png = _write_report(args, report)
    if png is not None:
        from .render import render_layers

        layers = _body_layers([h.surfaces for h in hs])
        render_layers(layers, png / "layers.png", title=f"{name}: {args.method}, {len(hs)} bodies")
        plot_convergence({f"body {k + 1}": b["solve"]["residuals"] for k, b in enumerate(report["bodies"])},
                         png / "convergence.png", title=f"{name}: {args.problem}")
    return 0


def _write_report(args, report: dict) -> Path | None:
    """``--json`` (and, with ``--png`` but no ``--json``, ``report.json`` beside the pictures: pictures always
    travel with the report they illustrate); returns the ``--png`` folder or None."""
    if args.json:
        _write_json(args.json, report)
    if not args.png:
        return None
    png = Path(args.png)
    if not args.json:
        _write_json(png / "report.json", report)
    return png


def _body_layers(surfaces: list) -> list:
    """Layer ``k`` of every body that has it, as one surface per layer (distinct surfaces only)."""
    from .bodies import merge_meshes

    per_body = [[S for k, S in enumerate(ss) if k == 0 or S[0] is not ss[k - 1][0]] for ss in surfaces]
    out = []
    for k in range(max(len(ls) for ls in per_body)):
        V, Fk, _ = merge_meshes([ls[k] for ls in per_body if k < len(ls)])
        out.append((V, Fk))
    return out


def cmd_compare(args) -> int:
    from .render import plot_convergence

    _refuse_overwriting_input(args.mesh, [Path(p) for p in (args.json,) if p])
    V, F, name = _load(args.mesh)
    V, F, bodies = _bodies(V, F, args.repair)
    if bodies:
        raise NestmgError(f"compare takes one solid; {name} has {len(bodies)} disjoint bodies: split the file, "
                          "or run `nestmg solve` (one hierarchy per body) once per method")
    report: dict[str, Any] = {"mesh": args.mesh, "problem": args.problem, "methods": {}}
    hists = {}
    for m in args.methods:
        h = _hierarchy(V, F, args, method=m)
        r = _solve(h, args)
        _print_solve(m, h, r)
        report["methods"][m] = {"hierarchy": h.to_dict(), "solve": r}
        hists[f"{m} ({r['factor']:.2f}/cycle)"] = r["residuals"]
        if args.png:
            _png_layers(h, Path(args.png) / f"layers_{m}.png", f"{name}: {m}")
    if args.json:
        _write_json(args.json, report)
    elif args.png:  # pictures always travel with the report they illustrate
        _write_json(Path(args.png) / "report.json", report)
    if args.png:
        plot_convergence(hists, Path(args.png) / "convergence.png",
                         title=f"{name}: {args.problem}, {args.coarse} coarse operators")
    return 0


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (the usage of ``solve`` alone is 14 lines) and
    whose ``--help`` lists the everyday flags; ``--help-all`` lists every flag, the expert ones too (the
    actions with ``expert = True``: options fields marked ``expert``, :func:`nestmg.options.add_arguments`).
    """

    show_expert = False

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def expert_actions(self) -> list[argparse.Action]:
        """The flags ``--help`` leaves out."""
        return [a for a in self._actions if getattr(a, "expert", False)]

    def format_help(self) -> str:
        expert = self.expert_actions()
        if self.show_expert or not expert:
            return super().format_help()
        saved = [a.help for a in expert]
        for a in expert:  # argparse leaves SUPPRESSed actions out of the usage and the groups
            a.help = argparse.SUPPRESS
        try:
            text = super().format_help()
        finally:
            for a, h in zip(expert, saved, strict=True):
                a.help = h
        return text + f"\n{len(expert)} expert flags not shown: {self.prog} --help-all lists every flag.\n"


class _HelpAll(argparse.Action):
    """``--help-all``: print the help with the expert flags and exit."""

    def __init__(self, option_strings, dest="help_all", default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.show_expert = True
        parser.print_help()
        parser.exit()


def _expert(action: argparse.Action) -> argparse.Action:
    """Mark a flag that is not an options field as expert (``--help-all`` only)."""
    action.expert = True
    return action


def _number(kind, low, *, strict: bool = False, what: str = ""):
    """An argparse ``type``: ``kind`` (int or float) that is ``> low`` (``strict``) or ``>= low``, finite."""

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if not np.isfinite(v) or (v <= low if strict else v < low):
            raise argparse.ArgumentTypeError(f"must be {'>' if strict else '>='} {low:g}{what}, got {text}")
        return v

    return parse


#: cage flags that are not a field of :class:`cagegen.CageOptions`: flag -> (the options classes that have the
#: field, field); a method whose class lacks it refuses the flag
CAGE_FLAGS = {"--cage-time-budget": (("NestedOptions", "SdfOptions"), "cage_time_budget"),
              "--cage-threads": (("NestedOptions",), "cage_threads")}


def _common(p: argparse.ArgumentParser, *, levels: int = 3) -> None:
    """The hierarchy's flags, one group per stage: sizing (``--levels`` and :class:`nestmg.SizingOptions`),
    meshing (:class:`nestmg.MeshingOptions`), cages (:class:`cagegen.CageOptions`, :data:`CAGE_FLAGS`);
    ``--no-cache``, ``--quiet`` and ``--help-all`` beside the command's own flags."""
    from cagegen import CageOptions

    from .options import MeshingOptions, SizingOptions, add_arguments

    p.add_argument("--no-cache", action="store_true", help="ignore and do not fill the cache ($NESTMG_CACHE)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--help-all", action=_HelpAll, help="show every flag, the expert ones too, and exit")
    g = p.add_argument_group("sizing")
    g.add_argument("--levels", type=_number(int, 2), default=levels,
                   help="levels incl. the input, >= 2 (default %(default)s)")
    add_arguments(g, SizingOptions)
    add_arguments(p.add_argument_group("meshing"), MeshingOptions)
    g = p.add_argument_group("cages")
    add_arguments(g, CageOptions)
    _expert(g.add_argument(
        "--cage-time-budget", type=_number(float, 0), default=None,
        help="seconds the nested or sdf cage backend may take, estimated before any work; refused at once "
             "above it (default 900; 0: no limit)"))
    _expert(g.add_argument(
        "--cage-threads", type=_number(int, 1), default=None,
        help="threads of the nested backend's contact library (ipctk); 1: the same cages every run "
             "(default: all cores, faster)"))


def _solver_opts(p: argparse.ArgumentParser) -> None:
    """The solver's flags: one per field of :class:`nestmg.SolverOptions`."""
    from .options import SolverOptions, add_arguments

    add_arguments(p.add_argument_group("solver"), SolverOptions)


def _typed_options(args: argparse.Namespace) -> None:
    """``args.sizing`` / ``args.meshing`` / ``args.solver`` from the flags (raises :class:`OptionError`)."""
    from .options import MeshingOptions, SizingOptions, SolverOptions, from_arguments

    if hasattr(args, "mesh_time_budget"):
        if args.mesh_time_budget == 0:  # the command line's "no limit"
            args.mesh_time_budget = None
        args.sizing = from_arguments(SizingOptions, args)
        args.meshing = from_arguments(MeshingOptions, args)
    if hasattr(args, "tol"):
        args.solver = from_arguments(SolverOptions, args)


def build_parser() -> argparse.ArgumentParser:
    """The ``nestmg`` argument parser."""
    p = _Parser(prog="nestmg", description="Geometric multigrid on nested cages.")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="hierarchy + three solves on a built-in shape, with pictures")
    d.add_argument("--shape", default="torus", choices=["sphere", "torus", "genus2", "neck_blobs", "thin_plate"])
    d.add_argument("--method", default="nested")
    d.add_argument("--out", default="nestmg-demo")
    d.add_argument("--no-png", action="store_true")
    _common(d, levels=4)  # refined fine level, the input meshed, two nested cages
    _solver_opts(d)
    d.set_defaults(func=cmd_demo)

    c = sub.add_parser("cages", help="build and certify a cage hierarchy")
    c.add_argument("mesh")
    c.add_argument("--method", default="nested", help="cage backend (default %(default)s)")
    c.add_argument("--out", required=True, help="folder for layer_k.obj and report.json")
    c.add_argument("--png", action="store_true", help="render the layers to OUT/layers.png")
    _common(c)
    c.set_defaults(func=cmd_cages)

    s = sub.add_parser("solve", help="solve a model problem by multigrid on a hierarchy")
    s.add_argument("mesh")
    s.add_argument("--problem", default="poisson-dirichlet",
                   choices=["poisson-dirichlet", "poisson-neumann", "diffusion-neumann", "elasticity-clamped",
                            "elasticity-free"],
                   help="elasticity-*: linear elasticity (E = 1, --poisson-ratio), clamped at the lowest x "
                        "under gravity -z, or free under a balanced body force; u is the displacement")
    s.add_argument("--method", default="nested", help="cage backend (default %(default)s)")
    s.add_argument("--element", choices=["P1", "P2"], default="P1",
                   help="P2: quadratic tets curved onto the input surface (certified valid), on the level "
                        "refined into level 0 (the same unknowns) or on level 0; p-multigrid to the P1 levels; "
                        "--out writes p2.vtu (tetra10)")
    _expert(s.add_argument("--quality", type=float, default=None,
                           help="with --element P2: quality pass on the curved tets whose scaled Jacobian "
                                "(min / max det J) is below this, e.g. 0.96"))
    _expert(s.add_argument("--relax", type=float, default=None,
                           help="with --element P2: move the interior edge nodes of the curved tets whose "
                                "scaled Jacobian is below this (e.g. 0.97) to even out det J; the boundary "
                                "stays on the surface"))
    _expert(s.add_argument("--sj-floor", type=float, default=None,
                           help="with --element P2: back off the curving until every tet's certified scaled "
                                "Jacobian is at least this, e.g. 0.955 (costs accuracy: docs/curved.md)"))
    s.add_argument("--json", default=None, help="write the report here")
    s.add_argument("--png", default=None, help="folder for layers.png and convergence.png")
    s.add_argument("--out", default=None,
                   help="folder for VTU files (ParaView): level_k.vtu per level, level_0.vtu with f and the solution u")
    _common(s)
    _solver_opts(s)
    s.set_defaults(func=cmd_solve)

    m = sub.add_parser("compare", help="the same problem on hierarchies of several cage methods")
    m.add_argument("mesh")
    m.add_argument("--methods", nargs="+", default=["nested", "decimate"])
    m.add_argument("--problem", default="poisson-neumann",
                   choices=["poisson-dirichlet", "poisson-neumann", "diffusion-neumann"])
    m.add_argument("--json", default=None)
    m.add_argument("--png", default=None, help="folder for the pictures")
    _common(m)
    _solver_opts(m)
    m.set_defaults(func=cmd_compare)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``nestmg`` console script."""
    args = build_parser().parse_args(argv)
    if not sys.stderr.isatty() and not getattr(args, "quiet", False):
        from .progress import enable_stage_lines

        enable_stage_lines()  # a log or a pipe: one line per stage (in a terminal, rich bars instead)
    from cagegen.registry import registered_backends

    methods = [getattr(args, "method", None), *(getattr(args, "methods", None) or [])]
    unknown = [m for m in methods if m is not None and m not in registered_backends()]
    if unknown:  # before any work, without importing a backend
        print(f"nestmg: error: unknown --method {unknown[0]!r}; registered: {', '.join(registered_backends())}",
              file=sys.stderr)
        return 2
    from .options import OptionError, flag

    try:  # every field checked by its options class (a negative envelope would segfault TetWild)
        _typed_options(args)
    except OptionError as exc:
        print(f"nestmg {args.command}: error: argument {flag(exc.field)}: {exc.problem}", file=sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except SolverError as exc:  # first: under the common root NestmgError, with its own exit code
        print(f"nestmg: solver error: {_one_line(exc)}", file=sys.stderr)
        return 3
    except NestmgError as exc:
        print(f"nestmg: error: {_one_line(exc)}{_repair_hint(exc, args)}{_levels_hint(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that cannot be written, e.g. --out naming an existing file
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"nestmg: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


def _repair_hint(exc: BaseException, args) -> str:
    """The option that mends an input refused for overlapping bodies, self-intersections or pinches."""
    from cagegen import MeshInputError

    mendable = ("self-intersections", "non-manifold", "several connected components")
    if not isinstance(exc, MeshInputError) or getattr(args, "repair", True):
        return ""
    if "open boundary" in str(exc):
        return " (--repair closes small holes: a scan's, up to 5% of the surface's area)"
    if any(w in str(exc) for w in mendable):
        return " (--repair meshes the solid it encloses with TetWild and uses that boundary)"
    return ""


def _levels_hint(exc: BaseException) -> str:
    """The command line's name of the library's ``face_counts`` when a message asks for it."""
    from cagegen import LevelsError

    if isinstance(exc, LevelsError) and "asked for by face_counts" in str(exc):
        return "; on the command line: --face-counts (`nestmg solve` meshes an input this coarse without a cage)"
    return ""


def _one_line(exc: BaseException) -> str:
    """The exception's message on one line (a multi-line message is joined with "; ")."""
    return "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
