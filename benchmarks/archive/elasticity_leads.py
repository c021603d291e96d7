"""The three leads of issue 32 item 2 (≤ 20 MG-PCG iterations at ν = 0.45), measured on one process
(docs/history/elasticity.md).

On a cached nested hierarchy (``benchmarks/elasticity.py``'s: 3 levels, defaults, ``--max-tets``), the
clamped (and free) elasticity problem at ``--nu``:

``prune``     the clamped problem's coarse-node pruning (``min_column_sum`` 0 ... 1) with the default
              cycle: coarse sizes, coarsest null vectors and factor, set-up CPU seconds, iterations.
``coarse``    (clamped problem, prune ``--coarse-prune``, default 0.2: a singular coarsest level) the
              coarsest solve of a given cycle replaced by: the eigen pseudo-inverse dropping
              eigenvalues below ``rtol λ_max`` (several ``rtol``), the default factor ("auto": the
              pivoted Cholesky there) and it plus one step of iterative refinement, the regularised
              SuperLU of ``A + 1e-9 diag A`` and it plus one refinement step; the iteration at which
              CG's residual first reaches 1e-6, 1e-7, 3e-8 and 1e-8, and the true final residual. Also
              the coarsest operator's smallest eigenvalues.
``cycles``    cycles and smoothers (symmetric / forward Gauss–Seidel, SSOR, "k / m" sweeps on the fine /
              coarser levels, V / F): iterations and CPU seconds of set-up and solve, two interleaved
              repeats (median).

Every MG-PCG run goes from zero to 1e-8 (500 iterations at most). Run from ``benchmarks/``'s parent::

    OMP_NUM_THREADS=1 python benchmarks/archive/elasticity_leads.py ZOO_DIR/fandisk.obj --max-tets 150000 \\
        --parts prune cycles --out benchmarks/results/elasticity/leads_fandisk_173k.json
    OMP_NUM_THREADS=1 python benchmarks/archive/elasticity_leads.py ZOO_DIR/spot.obj --max-tets 300000 \\
        --parts prune coarse --out benchmarks/results/elasticity/leads_spot_349k.json
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

_SGS, _GS = "symmetric_gauss_seidel", "gauss_seidel"


def _specs(name: str, fine: int, coarse: int, omega: float = 1.0) -> list:
    opts = {} if omega == 1.0 else {"omega": omega}
    return [(name, {"iterations": fine, **opts}), (name, {"iterations": coarse, **opts})]


#: label -> (presmoother specs, cycle)
CYCLES = {"V sgs 1/2": (_specs(_SGS, 1, 2), "V"), "V sgs 1/4": (_specs(_SGS, 1, 4), "V"),
          "V sgs 1/8": (_specs(_SGS, 1, 8), "V"), "F sgs 1/2": (_specs(_SGS, 1, 2), "F"),
          "V sgs 2/4": (_specs(_SGS, 2, 4), "V"), "W sgs 2/4": (_specs(_SGS, 2, 4), "W"),
          "V ssor1.2 1/2": (_specs(_SGS, 1, 2, 1.2), "V"), "V ssor1.4 1/2": (_specs(_SGS, 1, 2, 1.4), "V"),
          "V gs 2/4": (_specs(_GS, 2, 4), "V"), "V gs 2/8": (_specs(_GS, 2, 8), "V"),
          "V gs 3/6": (_specs(_GS, 3, 6), "V"), "F gs 2/2": (_specs(_GS, 2, 2), "F"),
          "F gs 2/4": (_specs(_GS, 2, 4), "F"), "F gs 2/8": (_specs(_GS, 2, 8), "F"),
          "F gs 3/4": (_specs(_GS, 3, 4), "F"), "F gs 3/6": (_specs(_GS, 3, 6), "F")}
PRUNES = (0.0, 0.2, 0.35, 0.5, 1.0)
THRESHOLDS = (1e-6, 1e-7, 3e-8, 1e-8)


def _problem(h, name: str, nu: float, prune: float | None = None):
    from nestmg.elasticity import setup_elasticity

    return setup_elasticity(h.tets_in("normalized"), h.P, name, nu=nu, prune=prune)


def _solve(pr, ml, cycle) -> dict:
    """MG-PCG to 1e-8 (CPU seconds, iterations, first iterations below :data:`THRESHOLDS`, true residual)."""
    from exp_common import relres

    c0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        x, info = ml.solve(pr.b, tol=1e-8, maxiter=500, cycle=cycle, accel="cg", return_info=True)
    sec = time.process_time() - c0
    r = np.asarray(info["residuals"])
    first = {f"{t:g}": (int(np.argmax(r <= t)) if np.any(r <= t) else None) for t in THRESHOLDS}
    return {"solve_cpu": sec, "iterations": int(info["iterations"]), "first_below": first,
            "final_residual": relres(pr.A, pr.b, x)}


def part_prune(h, nu: float) -> list[dict]:
    out = []
    for prune in PRUNES:
        pr = _problem(h, "elasticity-clamped", nu, prune)
        c0 = time.process_time()
        ml = pr.multigrid()
        setup = time.process_time() - c0
        cs = ml._coarse_solver
        out.append({"prune": prune, "levels": [L.A.shape[0] for L in ml.levels], "coarse_solver": cs.method,
                    "coarse_nullity": int(cs.nullity), "setup_cpu": setup, **_solve(pr, ml, ml.cycle)})
        print(f"  prune {prune}: {out[-1]}", file=sys.stderr, flush=True)
    return out


class _Pinv:
    """Eigen pseudo-inverse of the dense symmetric ``w, Q`` over eigenvalues above ``rtol λ_max``."""

    def __init__(self, w, Q, rtol):
        keep = w > rtol * w.max()
        self.Q, self.winv, self.dropped = Q[:, keep], 1.0 / w[keep], int(np.count_nonzero(~keep))

    def __call__(self, b):
        return self.Q @ (self.winv * (self.Q.T @ b))


class _Refined:
    """One step of iterative refinement of a coarse solve: ``x + S(b - A x)``, ``x = S b``."""

    def __init__(self, solve, A):
        self.solve, self.A = solve, A

    def __call__(self, b):
        x = self.solve(b)
        return x + self.solve(b - self.A @ x)


def part_coarse(h, nu: float, cycles: list[str], prune: float) -> dict:
    from solvers.coarse import _CoarseSolver

    pr = _problem(h, "elasticity-clamped", nu, prune)
    out: dict = {"prune": prune, "runs": {}}
    for label in cycles:
        spec, cycle = CYCLES[label]
        ml = pr.multigrid(presmoother=spec)
        Ac = sp.csr_matrix(ml.levels[-1].A)
        if "eigenvalues" not in out:
            w, Q = sla.eigh(Ac.toarray())
            out["coarsest_n"], out["eigenvalues_over_max"] = Ac.shape[0], (w[:12] / w.max()).tolist()
        pivoted = ml._coarse_solver
        regular = _CoarseSolver(Ac, None, len(ml.levels) - 1, "regularized", symmetric=True)
        solves = {f"default ({pivoted.method})": pivoted,
                  f"{pivoted.method} + refinement": _Refined(pivoted, Ac),
                  "regularized": regular, "regularized + refinement": _Refined(regular, Ac)}
        solves.update({f"pinv rtol {rt:g}": _Pinv(w, Q, rt) for rt in (1e-10, 1e-8, 1e-7, 1e-6)})
        for name, solve in solves.items():
            ml._coarse_solver = solve
            out["runs"][f"{label}: {name}"] = rec = _solve(pr, ml, cycle)
            print(f"  {label}: {name}: {rec}", file=sys.stderr, flush=True)
    return out


def part_cycles(h, nu: float, problems: list[str], repeat: int = 2) -> list[dict]:
    out = []
    for name in problems:
        pr = _problem(h, name, nu)
        runs: dict = {label: [] for label in CYCLES}
        for _ in range(repeat):
            for label, (spec, cycle) in CYCLES.items():
                c0 = time.process_time()
                ml = pr.multigrid(presmoother=spec)
                setup = time.process_time() - c0
                runs[label].append({"setup_cpu": setup, **_solve(pr, ml, cycle)})
        for label, rs in runs.items():
            rec = {"problem": name, "nu": nu, "variant": label, "iterations": rs[-1]["iterations"],
                   "first_below": rs[-1]["first_below"], "final_residual": rs[-1]["final_residual"],
                   "median_setup_cpu": float(np.median([r["setup_cpu"] for r in rs])),
                   "median_solve_cpu": float(np.median([r["solve_cpu"] for r in rs]))}
            out.append(rec)
            print(f"  {name} {label}: {rec['iterations']} it, solve {rec['median_solve_cpu']:.2f} s",
                  file=sys.stderr, flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--max-tets", type=int, default=300_000)
    ap.add_argument("--nu", type=float, default=0.45)
    ap.add_argument("--parts", nargs="+", default=["prune", "coarse", "cycles"],
                    choices=["prune", "coarse", "cycles"])
    ap.add_argument("--coarse-cycles", nargs="+", default=["W sgs 2/4", "F gs 3/4"], choices=list(CYCLES))
    ap.add_argument("--coarse-prune", type=float, default=0.2,
                    help="the clamped problem's prune in the coarse part (0.2: the default before item 2)")
    ap.add_argument("--problems", nargs="+", default=["elasticity-clamped", "elasticity-free"])
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    import nestmg
    from elasticity import load_surface
    from exp_common import environment, git_commit, write_json

    V, F = load_surface(str(a.mesh))
    h = nestmg.build_hierarchy(V, F, 3, "nested", sizing=nestmg.SizingOptions(max_tets=a.max_tets),
                               cache=True, progress=False)
    res = {"command": " ".join(["benchmarks/archive/elasticity_leads.py", a.mesh.name]
                               + [x for x in sys.argv[2:]]),
           "commit": git_commit(), "environment": environment(), "mesh": a.mesh.name, "nu": a.nu,
           "tets": [len(T) for _, T in h.tets_in("normalized")]}
    if "prune" in a.parts:
        res["prune"] = part_prune(h, a.nu)
    if "coarse" in a.parts:
        res["coarse"] = part_coarse(h, a.nu, a.coarse_cycles, a.coarse_prune)
    if "cycles" in a.parts:
        res["cycles"] = part_cycles(h, a.nu, a.problems)
    write_json(res, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
