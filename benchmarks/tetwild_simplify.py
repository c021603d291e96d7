"""fTetWild's own input simplification against meshing the pipeline's surface as given.

nestmg already predecimates an input much finer than its tets (``nestmg.hierarchy.predecimate``), so the
surface fTetWild gets is near its target edge; fTetWild then still simplifies it within its envelope. For
each mesh this script takes the surface and edge of the default pipeline's fine TetWild call (as
``tetwild_outside.py`` does) and meshes it twice in one process, one thread, no time limit, uniform outside:
``simplify=True`` (fTetWild's default) and ``simplify=False``. CPU seconds, tets and the smallest dihedral
angle go to the JSON (``benchmarks/results/tetwild/``).

    python benchmarks/tetwild_simplify.py ZOO_DIR/cheburashka.obj ZOO_DIR/elephant.obj ... --out OUT.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from exp_common import environment, git_commit, write_json
from tetwild_outside import _cpu, _meshed_surface


def measure(path: Path) -> dict:
    from nestmg.tetmesh import tet_quality, tetrahedralize

    S, G, h, row = _meshed_surface(path)
    row["mesh"] = path.name
    for simplify in (True, False):
        c, t = _cpu(), time.perf_counter()
        Vt, T = tetrahedralize(S, G, edge_length_abs=h, threads=1, time_limit=None, outer_edge_factor=1.0,
                               simplify=simplify)
        q = tet_quality(Vt, T)
        key = "simplify" if simplify else "as_given"
        row[key] = {"cpu_seconds": _cpu() - c, "wall_seconds": time.perf_counter() - t, "tets": int(len(T)),
                    "min_dihedral_deg": float(q.get("min_dihedral_deg", np.nan))}
        print(f"{path.name}: {key} {row[key]['cpu_seconds']:.1f} CPU s, {len(T):,} tets", flush=True)
    row["cpu_ratio_as_given_over_simplify"] = row["as_given"]["cpu_seconds"] / row["simplify"]["cpu_seconds"]
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="+", type=Path, help="closed surface files")
    ap.add_argument("--out", type=Path, required=True, help="JSON to write (rewritten after each mesh)")
    a = ap.parse_args(argv)
    out = {"command": "python benchmarks/tetwild_simplify.py MESHES...",
           "meshes_given": [p.name for p in a.meshes], "commit": git_commit(), "environment": environment(),
           "rows": []}
    for p in a.meshes:
        out["rows"].append(measure(p))
        write_json(out, a.out)


if __name__ == "__main__":
    sys.exit(main())
