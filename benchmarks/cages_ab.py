"""Before / after of a change to a cage backend: ``nestmg cages`` with the defaults, from two source trees.

Usage::

    python benchmarks/cages_ab.py MESH_DIR --trees BEFORE_DIR AFTER_DIR --out OUT.json
                                  [--meshes a.off b.obj ...] [--levels 3] [--method nested]
                                  [--labels COMMIT_BEFORE COMMIT_AFTER]

Each tree is a checkout (e.g. ``git worktree add --detach BEFORE_DIR <commit>``) imported through
``PYTHONPATH``. Per mesh the two trees run one after the other (so both meet about the same load), each
``nestmg cages MESH --levels L --no-cache --quiet`` in a single-threaded subprocess. The JSON records per
tree and mesh: CPU seconds (user + system of the process), wall seconds, the SHA-1 of every layer file
(the same digests: the change left the cages bit for bit as they were), and per layer the target source,
face count, volume ratio, wall seconds and the failed attempts (stage, reason, seconds); the 1-minute
load average before each run. Temporary folders are removed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _layers(report: dict) -> list:
    rows = []
    for L in report.get("backend", {}).get("layers", []):
        rows.append({
            "layer": L.get("layer"), "n_faces": L.get("n_faces"),
            "source": L.get("decimation", {}).get("source"), "offset": L.get("decimation", {}).get("offset"),
            "volume_ratio": L.get("volume_ratio"), "seconds": L.get("seconds", {}).get("total"),
            "dhat": L.get("reinflate", {}).get("dhat"),  # the reverse steps' (None before 6a00d76)
            "failed_attempts": [{k: f.get(k) for k in ("action", "stage", "reason", "seconds")}
                                for f in L.get("failed_attempts", [])],
        })
    return rows


def run_one(tree: Path, mesh: Path, levels: int, method: str, repair: bool = False) -> dict:
    """``nestmg cages`` from ``tree`` on ``mesh``: CPU and wall seconds, layer digests, per-layer record."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    with tempfile.TemporaryDirectory(prefix="cages-ab-") as tmp:
        cmd = [sys.executable, "-c", "import sys; from nestmg.cli import main; sys.exit(main())", "cages",
               str(mesh), "--levels", str(levels), "--method", method, "--out", tmp, "--no-cache", "--quiet"]
        cmd += ["--repair"] if repair else []
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        # run in the temporary folder: ``python -c`` puts the working directory first on sys.path, where
        # a checkout's own packages would shadow the tree's
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tmp)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        row = {"ok": proc.returncode == 0, "wall_seconds": wall, "load_before": load,
               "cpu_seconds": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)}
        if proc.returncode != 0:
            row["error"] = (proc.stderr.strip().splitlines() or [""])[-1]
            return row
        files = sorted(Path(tmp).glob("layer_*.obj"))
        row["layer_sha1"] = [hashlib.sha1(f.read_bytes()).hexdigest() for f in files]
        row["layers"] = _layers(json.loads((Path(tmp) / "report.json").read_text()))
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--trees", nargs=2, type=Path, required=True, metavar=("BEFORE", "AFTER"))
    ap.add_argument("--meshes", nargs="+", help="only these file names (default: every file of the folder)")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--method", default="nested")
    ap.add_argument("--repair", action="store_true", help="pass --repair (e.g. CAD STL caps)")
    ap.add_argument("--labels", nargs=2, metavar=("BEFORE", "AFTER"), help="e.g. the two commits")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    names = args.meshes or sorted(p.name for p in args.folder.iterdir() if p.is_file())
    words = ["MESH_DIR", "--trees", "BEFORE", "AFTER", "--levels", str(args.levels), "--method", args.method,
             *(["--repair"] if args.repair else []), "--meshes", *names]
    out = {"command": "python benchmarks/cages_ab.py " + " ".join(words),
           "trees": dict(zip(("before", "after"), args.labels or [t.name for t in args.trees])), "meshes": {}}
    for name in names:
        rows = {tag: run_one(tree, args.folder / name, args.levels, args.method, args.repair)
                for tag, tree in zip(("before", "after"), args.trees)}
        b, a = rows["before"], rows["after"]
        rows["same_cages"] = bool(b.get("layer_sha1")) and b.get("layer_sha1") == a.get("layer_sha1")
        if b["ok"] and a["ok"]:
            rows["cpu_ratio"] = b["cpu_seconds"] / max(a["cpu_seconds"], 1e-9)
        out["meshes"][name] = rows
        print(f"{name}: cpu {b['cpu_seconds']:.1f} -> {a['cpu_seconds']:.1f} s, same cages {rows['same_cages']}",
              flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
