"""Plot what the ``sdf`` tightening pass did on a zoo run of ``benchmarks/cages_sdf.py`` (issue 17).

For every mesh and layer of the run, two bars: the largest input-to-cage distance of the optimised cage
(before the pass) and of the returned cage (after), over the input's bounding-box diagonal, with the
issue's 1.5% line. Read from each layer's ``tighten`` record (``max_before`` / ``max_after``).

Usage::

    python benchmarks/archive/sdf_tighten_plot.py benchmarks/results/sdf/zoo_sdf_tighten_hug01_d89697c.json \\
        --out benchmarks/results/sdf/zoo_sdf_tighten_hug01_d89697c.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--goal", type=float, default=1.5, help="line at this distance (%% of the diagonal)")
    a = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = []
    for r in json.loads(a.run.read_text())["results"]:
        s = r.get("sdf") or {}
        for k, li in enumerate(s.get("per_layer") or []):
            t = li.get("tighten") or {}
            if "max_before" in t:
                rows.append((f"{Path(r['mesh']).stem} L{k + 1}", 100 * t["max_before"], 100 * t["max_after"]))
    if not rows:
        raise SystemExit(f"{a.run}: no layer has a tighten record")
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(8, 0.45 * len(rows)), 4.2))
    ax.bar(x - 0.2, [r[1] for r in rows], 0.4, label="optimised cage (before the pass)", color="0.7")
    ax.bar(x + 0.2, [r[2] for r in rows], 0.4, label="returned cage", color="tab:blue")
    ax.axhline(a.goal, color="tab:red", lw=1, ls="--", label=f"{a.goal:g}% goal (4x level = L1)")
    ax.set_xticks(x, [r[0] for r in rows], rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("largest input-to-cage distance, % of diagonal")
    ax.set_title(f"sdf tightening pass: {a.run.name}", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=120)
    print(json.dumps({"png": str(a.out), "layers": len(rows)}))


if __name__ == "__main__":
    main()
