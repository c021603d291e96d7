"""Markdown tables of ``benchmarks/coarse_operators.py`` JSON files (docs/coarse.md).

    python benchmarks/coarse_operators_table.py benchmarks/results/coarse_operators/coarse_operators_tetgen.json

One row per mesh / cage method / problem: Galerkin, re-discretised + α, weighted + α, sparsified and
sparsified + α as ``factor / MG-PCG iterations (operator complexity)``, and Δ = sparsified + α minus
Galerkin; then how many cases each of weighted + α and sparsified + α meets the issue-15 target on
(within 0.05 of Galerkin's factor at operator complexity <= 1.3).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


def _cell(r: dict) -> str:
    f = "diverges" if r.get("diverged") else f"{r['factor']:.3f}"
    return f"{f} / {r['pcg_iterations']} ({r['operator_complexity']:.2f})"


def _meets(r: dict, g: dict) -> bool:
    return (not r.get("diverged")) and r["factor"] - g["factor"] <= 0.05 and r["operator_complexity"] <= 1.3


def table(doc: dict) -> list[str]:
    lines = ["| mesh / method | problem | Galerkin | re-discretised + α | weighted + α | sparsified | sparsified + α "
             "| Δ (sparsified + α − Galerkin) |", "|---|---|---|---|---|---|---|---|"]
    n = met_s = met_w = 0
    for res in doc["results"]:
        for m, rec in res["methods"].items():
            if "runs" not in rec:
                lines.append(f"| {res['mesh'].split('.')[0]} / {m} | error: {rec.get('error')} | | | | | | |")
                continue
            for prob in PROBLEMS:
                R = {(x["coarse"], x["coarse_scaling"]): x for x in rec["runs"] if x["problem"] == prob}
                g, s = R[("galerkin", None)], R[("sparsified", "energy")]
                d = math.nan if s.get("diverged") else s["factor"] - g["factor"]
                n += 1
                met_s += _meets(s, g)
                met_w += _meets(R[("weighted", "energy")], g)
                short = prob.replace("poisson-", "").replace("-neumann", "")
                lines.append(f"| {res['mesh'].split('.')[0]} / {m} | {short} | {_cell(g)} | "
                             f"{_cell(R[('rediscretized', 'energy')])} | {_cell(R[('weighted', 'energy')])} | "
                             f"{_cell(R[('sparsified', None)])} | {_cell(s)} | {d:+.3f} |")
    lines.append("")
    lines.append(f"Target met (within 0.05 of Galerkin, operator complexity <= 1.3): sparsified + α {met_s} of {n}, "
                 f"weighted + α {met_w} of {n}.")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json", type=Path, nargs="+")
    args = ap.parse_args(argv)
    for path in args.json:
        print(f"<!-- {path} -->")
        print("\n".join(table(json.loads(path.read_text()))))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
