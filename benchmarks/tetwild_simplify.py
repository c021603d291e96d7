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
from pathlib import Path

from exp_common import environment, git_commit, write_json
from tetwild_outside import _meshed_surface, timed_mesh


def measure(path: Path) -> dict:
    S, G, h, row = _meshed_surface(path)
    row["mesh"] = path.name
    for simplify in (True, False):
        key = "simplify" if simplify else "as_given"
        row[key] = timed_mesh(S, G, h, f"{path.name}: {key}", outer_edge_factor=1.0, simplify=simplify)
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
