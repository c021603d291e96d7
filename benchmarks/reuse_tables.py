"""Markdown tables of docs/reuse.md from the reuse benchmarks' JSON files (issue 15 item 5).

    python benchmarks/reuse_tables.py benchmarks/results/reuse/*/reuse_*.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _f(x: float, nd: int = 2) -> str:
    return f"{x:.{nd}f}"


def table_a(res: dict) -> list[str]:
    out = []
    for rec in res["meshes"]:
        s = rec["summary"]
        n_steps = len(rec["dts"])
        n = s["nestmg"]["cpu_all_steps"]
        out += [(f"**{rec['mesh']}**, {rec['tets'][0]:,} / {rec['tets'][1]:,} / {rec['tets'][2]:,} tets, "
                 f"{rec['nodes'][0]:,} unknowns, {n_steps} steps, Δt/diag² in "
                 f"[{min(rec['dts']) / rec['diag'] ** 2:.1e}, {max(rec['dts']) / rec['diag'] ** 2:.1e}]"), "",
                ("| method | steps measured | once | setup per step | solve per step | CPU s per step | "
                 f"CPU s for {n_steps} steps | vs nestmg | iterations per step | max rel. residual | "
                 "max state diff vs reference |"),
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for m, r in s.items():
            k = r["steps_measured"]
            its = r["iterations"]
            it = "direct" if max(its) == 0 else f"{min(its)}–{max(its)}"
            tot = f"**{_f(r['cpu_all_steps'], 1)}**" + (" (extrapolated)" if r["extrapolated"] else "")
            out.append(f"| {m} | {k} | {_f(r['once_cpu'])} | {_f(r['setup_cpu'] / k)} | {_f(r['solve_cpu'] / k)} | "
                       f"{_f(r['cpu_per_step'])} | {tot} | {_f(r['cpu_all_steps'] / n)}x | {it} | "
                       f"{r['max_final_residual']:.1e} | {r['max_diff_vs_ref_rel']:.1e} |")
        out += ["", (f"Best re-setup alternative by CPU: {rec.get('best_resetup_alternative_cpu')}, nestmg speed-up "
                     f"{_f(rec.get('speedup_vs_best_resetup_cpu', float('nan')))}x; against GAMG reusing its "
                     f"interpolation: {_f(rec.get('speedup_vs_gamg_reuse_cpu', float('nan')))}x. Reference state: "
                     f"{rec.get('reference')}."), ""]
    return out


def table_b(res: dict) -> list[str]:
    out = []
    for rec in res["meshes"]:
        s = rec["summary"]
        out += [(f"**{rec['mesh']}**, {rec['tets'][0]:,} tets, {rec['nodes'][0]:,} unknowns, "
                f"{len(rec['sources'])} sources, t = {rec['t']:.3g}"), "",
                ("| method | setup CPU s (both matrices) | per source CPU s (median) | total CPU s | "
                "iterations heat / Poisson (median) | break-even vs CHOLMOD (sources) | "
                "distance vs CHOLMOD: median / p99 / max (of max distance) |"),
                "|---|---|---|---|---|---|---|"]
        for m, r in s.items():
            it = "direct" if m == "cholmod" else " / ".join(f"{x:g}" for x in r["iterations_median"])
            be = r.get("break_even_sources_vs_cholmod")
            be = "—" if be is None else ("never" if be == float("inf") else f"{be:.0f}")
            out.append(f"| {m} | {_f(r['setup_cpu'])} | {_f(r['per_source_median_cpu'], 3)} | **{_f(r['cpu'], 1)}** | "
                       f"{it} | {be} | {r['median_diff_vs_ref_rel_median']:.1e} / "
                       f"{r['p99_diff_vs_ref_rel_median']:.1e} / {r['max_diff_vs_ref_rel']:.1e} |")
        out.append("")
    return out


def table_c(res: dict) -> list[str]:
    out = []
    for rec in res["meshes"]:
        out += [(f"**{rec['mesh']}**, {rec['tets'][0]:,} / {rec['tets'][1]:,} / {rec['tets'][2]:,} tets "
                f"(hierarchy reused from the cache, loaded in {rec['hierarchy_load_seconds']:.0f} s wall; not counted)"), "",
                ("| problem | method | assembly | setup | solve | total CPU s | nestmg speed-up (total / setup+solve) "
                "| nestmg_fast speed-up (total / setup+solve) | iterations | wall total s |"),
                "|---|---|---|---|---|---|---|---|---|---|"]
        for name, pr in rec["problems"].items():
            for m, r in pr["runs"].items():
                cols = []
                for key in ("ratio_vs_nestmg", "ratio_vs_nestmg_fast"):
                    rat = pr.get(key, {}).get(m)
                    cols.append("—" if rat is None else f"{_f(rat['total_cpu'])}x / {_f(rat['solver_cpu'])}x")
                it = "direct" if r["iterations"] == 0 else str(r["iterations"])
                out.append(f"| {name} ({pr['unknowns']:,}) | {m} | {_f(r['assembly'][1])} | {_f(r['setup'][1])} | "
                           f"{_f(r['solve'][1])} | **{_f(r['total'][1])}** | {cols[0]} | {cols[1]} | {it} | "
                           f"{_f(r['total'][0], 1)} |")
        out.append("")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", type=Path, nargs="+")
    a = ap.parse_args(argv)
    for p in a.json:
        res = json.loads(p.read_text())
        case = res["case"][0]
        print(f"<!-- {p}: {res['params']['command']} ({res['environment']['date_utc']}, load average "
              f"{', '.join(f'{x:.1f}' for x in res['environment']['load_avg'])}) -->")
        print("\n".join({"a": table_a, "b": table_b, "c": table_c}[case](res)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
