"""How much the V-cycle factors of one mesh vary between fresh default hierarchies.

Usage::

    python benchmarks/factor_spread.py ZOO_DIR --meshes decimated-knight.off angle_block.stl \\
        --runs 6 [--variants default nu2 W] --out OUT.json

``benchmarks/corpus.py`` shows one hierarchy per mesh. The nested cages are reproducible only to round-off
(ipctk's threaded reductions), TetWild's tets follow the cages, and the factors follow the tets: a mesh near
a goal can meet it in one corpus run and miss it in the next. Per mesh and run this builds the hierarchy of
``nestmg solve FILE --levels 3`` (defaults, no cache) and solves the three model problems with each solver
variant, as V-cycles (factor) and MG-PCG (iterations). Variants: ``default`` (the pipeline's cycle),
``nu2`` (V(2,2) on the fine level, ``SolverOptions(nu=2)``), ``W`` (``SolverOptions(cycle="W")``).
The JSON holds, per mesh, one record per run: tets per level, ``[factor, MG-PCG iterations]`` per
variant and problem, and the default cycle's subdomain solves (``local_solves``: ``[level, nodes]`` per
problem, :mod:`solvers.subdomain`). ``--slow-mode``: also the pure-Neumann problem's two-grid pair of the
two finest levels (exact coarse solve on level 1): its asymptotic energy-norm contraction after 40
error-propagation steps ``e <- e - M A e`` from a random start, and where that slowest error lives (the
share of its energy ``e_i (A e)_i`` on the 1% of nodes that carry most, their centroid and the share of
them on the boundary).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from dataclasses import replace
from pathlib import Path

from corpus import _cli_args
from nestmg.problems import PROBLEMS

VARIANTS = {"default": {}, "nu2": {"nu": 2}, "W": {"cycle": "W"}}


def neumann_two_grid(tets, P):
    """``(A, M)``: the pure-Neumann problem on the two finest levels and its default two-grid cycle (exact
    coarse solve on level 1) as a preconditioner."""
    from nestmg.options import SolverOptions
    from nestmg.problems import setup_problem

    prob = setup_problem(tets[:2], P[:1], "poisson-neumann")
    return prob.A, prob.multigrid(SolverOptions().resolved("poisson-neumann")).aspreconditioner()


def contraction(A, step, n_steps: int = 40) -> tuple[float, np.ndarray]:
    """Energy-norm contraction of the error propagation ``step`` (e.g. ``e -> e - M A e``) at its last of
    ``n_steps`` from a random start, every error normalised and made zero-mean; and that last error."""
    e = np.random.default_rng(0).standard_normal(A.shape[0])
    for _ in range(n_steps):
        e -= e.mean()
        e /= np.sqrt(e @ (A @ e))
        e = step(e)
    e -= e.mean()
    return float(np.sqrt(e @ (A @ e))), e


def slow_mode(tets, P, steps: int = 40) -> dict:
    """The Neumann two-grid pair of the two finest levels: asymptotic contraction and where its slowest
    error lives (see the module docstring)."""
    from solvers import boundary_nodes

    A, M = neumann_two_grid(tets, P)
    rate, e = contraction(A, lambda e: e - M @ (A @ e), steps)
    local = np.abs(e * (A @ e))
    top = np.argsort(-local)[: max(1, A.shape[0] // 100)]
    X, T = tets[0]
    boundary = np.zeros(len(X), dtype=bool)
    boundary[boundary_nodes(T)] = True
    return {"contraction": rate, "energy_share_top1pct": float(local[top].sum() / local.sum()),
            "top1pct_centroid": X[top].mean(axis=0).tolist(),
            "top1pct_extent": np.ptp(X[top], axis=0).tolist(),
            "top1pct_on_boundary": float(boundary[top].mean()), "on_boundary_all": float(boundary.mean())}


def one_run(mesh: Path, variants: list[str], modes: bool = False) -> dict:
    """A fresh default hierarchy of ``mesh`` and ``[factor, MG-PCG iterations]`` per variant and problem."""
    from nestmg.cli import _hierarchy, _load, _solve

    args = _cli_args("solve", mesh, [])
    V, F, _ = _load(str(mesh))
    h = _hierarchy(V, F, args)
    base, out, local = args.solver, {}, {}
    for name in variants:
        row = {}
        for problem in PROBLEMS:
            args.problem = problem
            args.solver = replace(base, accel=None, **VARIANTS[name])
            r = _solve(h, args)
            if name == "default":  # [level, nodes] of each subdomain solve the probe kept
                local[problem] = [[d["level"], d["local_solve"]["nodes"]] for d in r.get("deflation") or []
                                  if d.get("local_solve", {}).get("kept")]
            args.solver = replace(base, accel="cg", **VARIANTS[name])
            c = _solve(h, args)
            row[problem] = [r["factor"], c["iterations"]]
        out[name] = row
    rec = {"tets": [len(T) for _, T in h.tets], "certified": h.certified, "variants": out,
           "local_solves": local}
    if modes:
        rec["slow_mode"] = slow_mode(h.tets_in("normalized"), h.P)
    return rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[1],
                                 formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("folder", type=Path)
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--variants", nargs="+", default=["default", "nu2", "W"], choices=sorted(VARIANTS))
    ap.add_argument("--slow-mode", action="store_true",
                    help="also locate the Neumann two-grid pair's slowest error")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    flags = f" --variants {' '.join(args.variants)}" + (" --slow-mode" if args.slow_mode else "")
    doc = {"command": (f"python benchmarks/factor_spread.py ZOO_DIR --meshes {' '.join(args.meshes)} "
                       f"--runs {args.runs}{flags} --out OUT/{args.out.name}"),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "meshes": {}}
    for m in args.meshes:
        runs = doc["meshes"].setdefault(m, [])
        for i in range(args.runs):
            t = time.perf_counter()
            runs.append(one_run(args.folder / m, args.variants, args.slow_mode))
            d = runs[-1]["variants"]["default"] if "default" in args.variants else {}
            slow = f"; slow mode {runs[-1]['slow_mode']['contraction']:.3f}" if args.slow_mode else ""
            print(f"[spread] {m} run {i + 1}: {time.perf_counter() - t:.0f} s, default factors "
                  + ", ".join(f"{p} {v[0]:.3f}" for p, v in d.items()) + slow, flush=True)
            args.out.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
