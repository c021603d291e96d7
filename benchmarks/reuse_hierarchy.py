"""Build (or load from the cache) the hierarchies of the reuse benchmarks and print their sizes and stage times.

    nice -n 10 python benchmarks/reuse_hierarchy.py ZOO_DIR/bunny.off --edge-length 0.0075

On a cache hit the stage times are those of the cached entries, not a build: clear ``$NESTMG_CACHE`` to
measure a build (docs/reuse.md quotes the uncached builds).
"""

from __future__ import annotations

import argparse
import json
import sys

from exp_common import add_hierarchy_arguments, cached_hierarchy, environment, hierarchies_from_args


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hierarchy_arguments(ap)
    a = ap.parse_args(argv)
    out = []
    for p, edge in hierarchies_from_args(a):
        h, s = cached_hierarchy(p, edge_length=edge)
        out.append({"mesh": p.name, "edge_length": edge, "seconds": s, "tets": [len(T) for _, T in h.tets],
                    "nodes": [len(V) for V, _ in h.tets], "timings": h.timings, "environment": environment()})
    print(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
