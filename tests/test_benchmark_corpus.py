"""``benchmarks/corpus.py`` builds its cases as ``nestmg`` does (typed options), on a procedural mesh file."""

from __future__ import annotations

import sys
from pathlib import Path

import igl
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import corpus  # noqa: E402

from nestmg import MeshingOptions, SizingOptions, SolverOptions, shapes  # noqa: E402


@pytest.fixture(scope="module")
def torus_file(tmp_path_factory):
    V, F = shapes.torus(res=24)
    path = tmp_path_factory.mktemp("corpus") / "torus.off"
    igl.write_triangle_mesh(str(path), V, F)
    return path


def test_solve_case_arguments_carry_the_typed_options(torus_file):
    args = corpus._cli_args("solve", torus_file, [])
    assert isinstance(args.sizing, SizingOptions) and args.sizing == SizingOptions()
    assert isinstance(args.meshing, MeshingOptions) and args.meshing == MeshingOptions()
    assert isinstance(args.solver, SolverOptions) and args.solver.accel is None
    assert args.levels == 3 and args.no_cache


def test_cages_case_runs_and_certifies(torus_file):
    rec = corpus.case_cages(torus_file, "decimate")  # the fast backend: the same code path as nested
    assert rec["faces"][0] == len(shapes.torus(res=24)[1]) and len(rec["faces"]) == 3
    assert rec["faces"][1] < rec["faces"][0] and rec["seconds"] > 0
