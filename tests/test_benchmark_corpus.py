"""``benchmarks/corpus.py`` builds its cases as ``nestmg`` does (typed options), on a procedural mesh file."""

from __future__ import annotations

import sys
from pathlib import Path

import igl
import numpy as np
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


def test_a_case_run_on_another_tree_than_the_runs_is_recorded(monkeypatch, capsys):
    """Each case process imports the source tree anew: a case that ran while the tree was edited, or after a
    commit made during the run, records both states and warns; a clean case records nothing."""
    doc, entry = {"commit": "aaa1111"}, {"mesh": "m.off", "solve": {"ok": True}}
    states = iter([{"commit": "aaa1111", "dirty": True}])
    monkeypatch.setattr(corpus, "_tree_state", lambda: next(states))
    corpus._note_tree(doc, entry, "solve", {"commit": "aaa1111", "dirty": False})
    assert entry["solve"]["tree"] == {"before": {"commit": "aaa1111", "dirty": False},
                                      "after": {"commit": "aaa1111", "dirty": True}}
    assert "run benchmarks from a clone" in capsys.readouterr().err
    clean = {"mesh": "m.off", "solve": {"ok": True}}
    monkeypatch.setattr(corpus, "_tree_state", lambda: {"commit": "aaa1111", "dirty": False})
    corpus._note_tree(doc, clean, "solve", {"commit": "aaa1111", "dirty": False})
    assert "tree" not in clean["solve"]
    monkeypatch.undo()
    real = corpus._tree_state()
    assert set(real) == {"commit", "dirty"} and isinstance(real["dirty"], bool)


def test_merge_replaces_columns_not_rows(tmp_path):
    """A later run of one column (solve) keeps the earlier run's other columns and says which commit made each."""
    old = {"command": "run A", "commit": "aaa", "date": "d1", "timeout": 600, "backends": ["nested", "decimate"],
           "goals": corpus.GOALS,
           "meshes": [{"mesh": "m.off", "faces": 10, "closed": True, "skipped": None, "solve": {"ok": True, "x": 1},
                       "cages:nested": {"ok": True, "seconds": 5.0}, "cages:decimate": {"ok": True, "seconds": 1.0}},
                      {"mesh": "n.off", "faces": 20, "closed": True, "skipped": None, "solve": {"ok": False}}]}
    new = dict(old, command="run B", commit="bbb", date="d2",
               meshes=[{"mesh": "m.off", "faces": 10, "closed": True, "skipped": None, "solve": {"ok": True, "x": 2},
                        "cages:nested": {"ok": True, "seconds": 4.0}}])
    doc = corpus.merge_runs([old, new])
    m, n = doc["meshes"]
    assert m["solve"]["x"] == 2 and m["cages:nested"]["seconds"] == 4.0 and m["cages:decimate"]["seconds"] == 1.0
    assert m["commits"] == {"solve": "bbb", "cages:nested": "bbb", "cages:decimate": "aaa"} and m["commit"] is None
    assert n["commits"] == {"solve": "aaa"} and n["commit"] == "aaa"
    assert doc["commit"] == "bbb / aaa" and doc["command"] == "run A ; run B"
    # the merge is dated by its latest run, also when an older run is merged last (a column put back)
    assert doc["date"] == "d2" and corpus.merge_runs([new, old])["date"] == "d2"
    # merging the merged document again keeps the per-column commits
    assert corpus.merge_runs([doc])["meshes"][0]["commits"] == m["commits"]
    # the table marks only the columns run elsewhere than the first commit
    assert corpus._at(m, ["solve"], "bbb")["mesh"] == "m.off"
    assert corpus._at(m, ["cages:nested", "cages:decimate"], "bbb")["mesh"] == "m.off (at aaa)"
    # the page names each shown column's run once; a merged run is listed through the JSON's ``runs``
    assert [r["command"] for r in corpus.merge_runs([doc, new])["runs"]] == ["run A", "run B"]
    lines = corpus._provenance(doc)
    assert [ln for ln in lines if ln.startswith("- ")] == ["- `run A` at aaa, d1", "- `run B` at bbb, d2"]
    assert "600 s per case" not in lines[0] and "`--timeout`" in lines[0]  # runs had their own limits
    older = {k: v for k, v in doc.items() if k != "runs"}  # a merge from before ``runs`` existed
    older.update(command="run 0 ; run A", commit="aaa / zzz")
    lines = corpus._provenance(corpus.merge_runs([older, new]))
    assert [ln for ln in lines if ln.startswith("- ")] == ["- `run B` at bbb, d2"]
    assert "from 2 earlier runs" in lines[-1]


def test_derived_inputs_recipe():
    """benchmarks/derived_inputs.py: loop subdivision multiplies the faces by 4 per round; the noise moves
    vertices along their normals by at most the given fraction of the mean edge, reproducibly (seed)."""
    import derived_inputs

    V, F = shapes.sphere(8)
    V1, F1 = derived_inputs.derive(V, F, 2, 0.0)
    assert len(F1) == 16 * len(F)
    Vn, Fn = derived_inputs.derive(V, F, 1, 0.25)
    Vs, _ = derived_inputs.derive(V, F, 1, 0.0)
    E = Vs[Fn[:, [1, 2, 0]]] - Vs[Fn]
    mean_edge = float(np.linalg.norm(E, axis=2).mean())
    move = np.linalg.norm(Vn - Vs, axis=1)
    assert 0.1 * mean_edge < move.max() <= 0.25 * mean_edge + 1e-12
    assert np.array_equal(Vn, derived_inputs.derive(V, F, 1, 0.25)[0])
    Vf, Ff = derived_inputs.derive(V, F, 1, 0.0, scheme="flat")  # each face in four in its own plane
    assert len(Ff) == 4 * len(F) and np.allclose(Vf[: len(V)], V)
    r = np.linalg.norm(Vf - V.mean(axis=0), axis=1)
    assert r[len(V):].max() < r[: len(V)].min()  # new vertices on the chords, inside the sphere (not smoothed)
    assert set(derived_inputs.DERIVED) == {"gargo_21k.obj", "gargo_342k.obj", "bunny_111k.obj", "homer_192k.obj",
                                           "gargo_86k_noisy.obj", "fandisk_207k_flat.obj"}


def test_constructor_record_and_its_table_cell():
    """The corpus records ``MultigridSolver(A, P)``'s MG-PCG with its defaults (the coarse probe on a nested
    hierarchy) and without the probe, and the solve table shows both iteration counts (the bracket only where
    they differ), from a record of either layout (the default was ``deflate=0`` when the older ones ran)."""
    from types import SimpleNamespace

    from solvers.gallery import kuhn_cube_hierarchy

    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    h = SimpleNamespace(tets_in=lambda frame: meshes, P=Ps)
    rec = corpus.constructor_pcg(h, "poisson-neumann", SolverOptions())
    d, n = rec["default"], rec["no_probe"]
    assert d["converged"] and n["converged"] and 3 <= d["pcg_iterations"] <= 12
    assert d["deflate"] == 8 and [p["level"] for p in d["probe"]] == [1]  # nested: cheap coarse levels probed
    assert n["deflate"] == 0 and n["probe"] == [] and d["operator_complexity"] < 1.5
    assert corpus._ctor_iterations(rec) == (d["pcg_iterations"], n["pcg_iterations"])
    older = {"default": {"pcg_iterations": 14, "deflate": 0}, "coarse_probe": {"pcg_iterations": 10, "deflate": 8},
             "layer": {"pcg_iterations": 13, "deflate": 0}}
    assert corpus._ctor_iterations(older) == (10, 14)
    unprobed = {"default": {"pcg_iterations": 9, "deflate": 0}, "no_probe": {"pcg_iterations": 9, "deflate": 0}}
    assert corpus._ctor_iterations(unprobed) == (9, 9)  # "auto" skipped the probe: no crash, one count
    probs = {p: {"factor": 0.1, "pcg_iterations": 7, "operator_complexity": 1.2,
                 "constructor": {"default": {"pcg_iterations": 10, "deflate": 8},
                                 "no_probe": {"pcg_iterations": k, "deflate": 0}}}
             for p, k in zip(corpus.PROBLEMS, (10, 14, 10))}
    entry = {"mesh": "m.off", "faces": 100, "solve": {"ok": True, "stages": {"cages": 1, "tets": 2}, "problems": probs,
                                                     "tets": [8000, 1000], "certified": True, "wall_seconds": 3,
                                                     "peak_mb": 100}}
    row = corpus.solve_row(entry)
    assert "| 10 / 10 (14) / 10 |" in row and row.count("|") == 12
