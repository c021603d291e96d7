"""The pipeline's deflation probe under MG-PCG: at set-up (``probe_at="setup"``, the behaviour before) or
deferred to the first stationary solve (``probe_at="stationary"``, the default of ``Problem.multigrid()``).

For each mesh: the default hierarchy (``build_hierarchy(V, F, levels=3)``, cached), then for the three model
problems ``Problem.multigrid(probe_at=...)`` + ``solve(b, tol=1e-8, accel="cg")``, alternating, twice each;
CPU seconds of set-up and solve, CG iterations, modes deflated per level.

    OMP_NUM_THREADS=1 python benchmarks/archive/probe_under_cg.py ZOO_DIR/homer.obj --out FILE.json
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from exp_common import mesh_study_main, model_problems, timed_pcg  # noqa: E402


def measure(mesh: Path) -> dict:
    """Set-up / solve CPU seconds and CG iterations of both probe placements on one mesh."""
    out, problems = model_problems(mesh)
    for name, pr in problems:
        for at in ("setup", "stationary", "setup", "stationary"):
            ml, setup, solve, info = timed_pcg(lambda at=at: pr.multigrid(probe_at=at), pr.b)
            out["rows"].append({"problem": name, "probe_at": at, "setup": setup, "solve": solve,
                                "it": info["iterations"], "modes": [d["vectors"] for d in ml.deflation]})
    return out


def main(argv=None) -> None:
    mesh_study_main("benchmarks/archive/probe_under_cg.py", __doc__.splitlines()[0], measure, argv)


if __name__ == "__main__":
    main()
