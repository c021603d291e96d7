"""Per-contact cost of the re-inflation's barrier Newton matrices on real collision sets.

Issue 27, item 2: is a compiled copy of ipctk's PSD-projected barrier Hessian worth writing? Runs
``nestmg cages MESH --levels 3`` (the corpus's ``case_cages`` call) with ``_Problem.barrier_hessian``
wrapped: at the first ``--sets`` Newton iterations with more than ``--min-contacts`` contacts it times, on
that collision set, ipctk's barrier gradient, its Hessian unprojected and projected by clamping (the
default), and the numpy Gauss-Newton matrix (contact arrays read from ipctk's collision objects, then the
matrix), and the hybrid matrix of large sets (``_Problem._hybrid_hessian``, where the checkout has it),
each ``--repeats`` times, in CPU and wall microseconds per contact (ipctk runs on its own TBB threads: CPU
over wall is its parallelism), and the contacts' distances over ``dhat`` (10th, 50th, 90th percentile,
fraction below 0.5). Also the cost of numpy's batched ``eigh`` of random symmetric
12x12 and 9x9 matrices, the floor of any PSD projection by eigendecomposition from Python. One OpenMP
thread::

    PYTHONPATH=CHECKOUT OMP_NUM_THREADS=1 python benchmarks/archive/contact_hessian_cost.py ZOO_DIR \\
        --meshes pepper.ply homer.obj --out OUT.json
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import sys
import time
from pathlib import Path

import ipctk
import numpy as np


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _per_contact(f, n: int, repeats: int) -> dict:
    """CPU and wall microseconds per contact of ``f()``, the median over ``repeats`` calls."""
    cpu, wall = [], []
    for _ in range(repeats):
        c, w = _cpu(), time.perf_counter()
        f()
        cpu.append(_cpu() - c)
        wall.append(time.perf_counter() - w)
    return {"cpu_us": 1e6 * float(np.median(cpu)) / n, "wall_us": 1e6 * float(np.median(wall)) / n}


def measure_set(prob, col, X: np.ndarray, fine_moves: bool, repeats: int) -> dict:
    """The four costs on one collision set of the re-inflation problem ``prob``."""
    from cagegen.nested.contact_hessian import contact_arrays, contact_gradients, gauss_newton_hessian

    mesh, n, nc = prob.pair.mesh, len(col), prob.nc
    idx = np.arange(3 * nc)

    def gn():
        ca = contact_arrays(col, mesh)
        gauss_newton_hessian(X, ca, prob.rest, prob.dhat, prob.kappa, dofs=idx)

    row = {"contacts": n, "fine_moves": fine_moves,
           "kinds": {k: len(getattr(col, f"{k}_collisions")) for k in ("fv", "ee", "ev", "vv")}}
    row["ipctk_gradient"] = _per_contact(lambda: prob.barrier.gradient(col, mesh, X), n, repeats)
    for name, proj in (("ipctk_hessian_none", ipctk.PSDProjectionMethod.NONE),
                       ("ipctk_hessian_clamp", ipctk.PSDProjectionMethod.CLAMP)):
        row[name] = _per_contact(lambda: prob.barrier.hessian(col, mesh, X, proj), n, repeats)
    row["contact_arrays"] = _per_contact(lambda: contact_arrays(col, mesh), n, repeats)
    row["gauss_newton_with_arrays"] = _per_contact(gn, n, repeats)
    if hasattr(prob, "_hybrid_hessian"):  # the default matrix of large sets since 36a31a7
        row["hybrid"] = _per_contact(lambda: prob._hybrid_hessian(col, X, fine_moves), n, repeats)
    d = contact_gradients(X, contact_arrays(col, mesh), prob.rest)[0] / prob.dhat
    row["distance_over_dhat"] = {"p10": float(np.quantile(d, 0.1)), "p50": float(np.median(d)),
                                 "p90": float(np.quantile(d, 0.9)), "below_half": float(np.mean(d < 0.5))}
    return row


def eigh_floor(n_mats: int = 50_000) -> dict:
    """Microseconds per matrix of numpy's batched ``eigh`` (random symmetric 12x12 and 9x9)."""
    rng = np.random.default_rng(0)
    out = {}
    for k in (12, 9):
        A = rng.random((n_mats, k, k))
        A = A + A.transpose(0, 2, 1)
        c = _cpu()
        np.linalg.eigh(A)
        out[f"eigh_{k}x{k}_cpu_us"] = 1e6 * (_cpu() - c) / n_mats
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--sets", type=int, default=4, help="collision sets measured per mesh")
    ap.add_argument("--min-contacts", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--label", help="the commit measured")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rf = importlib.import_module("cagegen.nested.reinflate")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from corpus import case_cages

    out = {"command": "python benchmarks/archive/contact_hessian_cost.py ZOO_DIR --meshes "
                      + " ".join(args.meshes), "commit": args.label, "load_before": os.getloadavg()[0],
           "eigh": eigh_floor(), "meshes": {}}
    original = rf._Problem.barrier_hessian
    for name in args.meshes:
        rows: list = []

        def wrapped(self, col, X, fine_moves, rows=rows):
            if len(rows) < args.sets and len(col) > args.min_contacts:
                rows.append(measure_set(self, col, X, fine_moves, args.repeats))
            return original(self, col, X, fine_moves)

        rf._Problem.barrier_hessian = wrapped
        try:
            case_cages(args.folder / name, "nested")
        finally:
            rf._Problem.barrier_hessian = original
        out["meshes"][name] = rows
        print(name, [(r["contacts"], round(r["ipctk_hessian_clamp"]["wall_us"], 1),
                      round(r.get("hybrid", {}).get("wall_us", float("nan")), 1)) for r in rows], flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
