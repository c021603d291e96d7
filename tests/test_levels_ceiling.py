"""``--levels`` is a ceiling: a small input gets the levels that fit, with one line saying so; explicit
``--face-counts`` that cannot be met fail at once, naming the option (issue 27, item 5)."""

from __future__ import annotations

import json
import logging
import time

import numpy as np
import pytest

from cagegen.errors import LevelsError, MeshInputError
from cagegen.sizes import MIN_FACES, default_face_counts, fitting_levels
from nestmg import SizingOptions, build_hierarchy, hierarchy_from_tets, shapes, tetrahedralize
from nestmg.sizing import plan_hierarchy, plan_levels
from nestmg.usermesh import boundary_surface


@pytest.fixture
def stage_lines():
    """The ``nestmg`` logger's INFO lines, whatever handlers an earlier CLI test installed."""
    lines: list[str] = []

    class _Keep(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage())

    log = logging.getLogger("nestmg")
    h, level = _Keep(level=logging.INFO), log.level
    log.addHandler(h)
    log.setLevel(logging.INFO)
    yield lines
    log.removeHandler(h)
    log.setLevel(level)


@pytest.fixture(scope="module")
def small_sphere():
    V, F = shapes.sphere(res=10)  # 776 faces: one cage of 194 faces fits at ratio 4, two do not
    assert 4 * MIN_FACES <= len(F) < 16 * MIN_FACES
    return V, F


@pytest.fixture(scope="module")
def small_tets():
    """A TetWild tet mesh of a coarse procedural sphere: 780 boundary faces (the 'user's Medit mesh')."""
    V, T = tetrahedralize(*shapes.sphere(res=10), edge_length=0.12)
    nb = len(boundary_surface(V, T)[1])
    assert 4 * MIN_FACES <= nb < 16 * MIN_FACES, nb
    return V, T, nb


def test_fitting_levels_agrees_with_default_face_counts():
    for n in (400, 670, 1599, 1600, 6400, 20000, 100000):
        for levels in (2, 3, 4, 6):
            fit = fitting_levels(n, levels)
            assert 1 <= fit <= levels
            if fit >= 2:  # the granted levels are buildable, one more is not
                assert min(default_face_counts(n, fit)) >= MIN_FACES
            if fit < levels:
                with pytest.raises(LevelsError, match=f"at most {fit} levels fit"):
                    default_face_counts(n, fit + 1)
    assert fitting_levels(670, 3) == 2 and fitting_levels(390, 3) == 1 and fitting_levels(1600, 3) == 3


def test_plan_levels_is_a_ceiling_with_one_line():
    lp = plan_levels(670, 3)
    assert (lp.requested, lp.levels, lp.n_faces) == (3, 2, 670)
    assert lp.note == "levels: 2 of the 3 asked fit 670 faces at ratio 4 (smallest cage >= 100 faces)"
    assert plan_levels(20000, 3).levels == 3 and plan_levels(20000, 3).note == ""
    # a refined fine level is not a cage level: 4 asked, input + 2 cages do not fit 670 faces, 1 does
    lp4 = plan_levels(670, 4, fixed_levels=1)
    assert lp4.levels == 3 and "3 of the 4 asked" in lp4.note
    json.dumps(lp.to_dict())
    # not even one cage fits: one cage level is kept (no note); cagegen.build_cages refuses it after its audit
    assert plan_levels(300, 3).levels == 2 and plan_levels(300, 3).note == ""
    assert plan_levels(2, 3).levels == 2  # not a closed surface: the audit says so, not the level planning
    with pytest.raises(LevelsError, match="leaves no cage level"):
        plan_levels(5000, 2, fixed_levels=1)


def test_too_small_input_is_audited_first_then_refused():
    import trimesh

    from nestmg.hierarchy import build_cage_surfaces

    s = trimesh.creation.icosphere(subdivisions=2)  # 320 faces: a cage of 80 < 100 faces
    V, F = np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int64)
    # "lower levels" cannot help there: the message says what can
    with pytest.raises(LevelsError, match=r"^no cage fits a 320-face input at ratio 4: its first cage would have "
                                          r"80 < min_faces=100 faces; .*face_counts \(e\.g\. \[160\]\)$"):
        build_cage_surfaces(V, F, 3, cache=False, progress=False)
    with pytest.raises(MeshInputError):  # a broken small input is named as broken, not as too small
        build_cage_surfaces(V, F[:-1], 3, cache=False, progress=False)
    # an explicit small cage is the user's choice
    layers, info = build_cage_surfaces(V, F, 2, "decimate", sizing=SizingOptions(face_counts=[80]),
                                       cache=False,
                                       progress=False)
    assert len(layers) == 2 and info["levels"]["face_counts"] == [80]


def test_impossible_face_counts_fail_in_milliseconds_naming_the_option(small_sphere):
    V, F = small_sphere
    t = time.perf_counter()
    with pytest.raises(LevelsError, match=r"^--face-counts 5000 100 cannot be met on an input of 776 faces"):
        build_hierarchy(V, F, levels=3, sizing=SizingOptions(face_counts=[5000, 100]), cache=False,
                        progress=False)
    with pytest.raises(LevelsError, match=r"--face-counts 300 100 gives 2 cage face counts, but --levels 2"):
        plan_levels(776, 2, face_counts=[300, 100])
    with pytest.raises(LevelsError, match=r"--face-counts 100 300 .*face_counts\[1\] = 300 >= 100"):
        plan_levels(776, 3, face_counts=[100, 300])
    assert time.perf_counter() - t < 1.0
    # explicit counts below the default minimum are the user's choice: kept, not reduced
    assert plan_levels(776, 3, face_counts=[190, 48]).levels == 3


def test_plan_hierarchy_gets_the_levels_that_fit(small_sphere):
    V, F = small_sphere
    p = plan_hierarchy(V, F, 4, fixed_levels=1)
    assert p.n_levels == 3 and len(p.expected_tets) == 3
    assert p.levels["requested"] == 4 and p.levels["levels"] == 3 and "3 of the 4 asked" in p.levels["note"]
    assert plan_hierarchy(V, F, 2).levels["note"] == ""


def test_small_surface_with_four_levels_gets_three_and_the_line(small_sphere, stage_lines):
    V, F = small_sphere
    h = build_hierarchy(V, F, levels=4, cache=False, progress=False)
    # refined fine level + the input meshed + the one cage that fits (194 faces)
    assert h.levels == 3 and len(h.surfaces[-1][1]) == pytest.approx(len(F) / 4, abs=4)
    assert h.certified
    note = f"levels: 3 of the 4 asked fit {len(F)} faces at ratio 4 (smallest cage >= 100 faces)"
    assert sum(note in line for line in stage_lines) == 1, stage_lines
    assert h.options["levels_requested"] == 4 and h.options["levels"] == 3
    assert h.options["plan"]["levels"]["note"] == note
    json.dumps(h.to_dict())


def test_tet_mesh_with_few_boundary_faces(small_tets, stage_lines):
    V, T, nb = small_tets
    t = time.perf_counter()
    with pytest.raises(LevelsError, match="--face-counts 2000 cannot be met"):
        hierarchy_from_tets(V, T, levels=2, sizing=SizingOptions(face_counts=[2000]), cache=False,
                            progress=False)
    assert time.perf_counter() - t < 1.0
    H = hierarchy_from_tets(V, T, levels=3, cache=False, progress=False)
    assert H.levels == 2 and H.certified and np.array_equal(H.tets[0][1], T)
    note = f"levels: 2 of the 3 asked fit {nb} faces at ratio 4 (smallest cage >= 100 faces)"
    assert sum(note in line for line in stage_lines) == 1, stage_lines
    assert H.options["levels_requested"] == 3 and H.options["levels_plan"]["note"] == note
    assert H.cage_info["levels"]["levels"] == 2


def test_cli_on_a_small_medit_tet_mesh_with_three_levels(small_tets, tmp_path, capsys):
    import meshio

    from nestmg.cli import main

    V, T, _ = small_tets
    src = tmp_path / "part.mesh"
    meshio.write(str(src), meshio.Mesh(V * 25.0, [("tetra", T)]), file_format="medit")
    rc = main(["solve", str(src), "--levels", "3", "--problem", "poisson-neumann", "--quiet", "--no-cache",
               "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "levels=2" in out.out and "certified=True" in out.out
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["hierarchy"]["levels"] == 2 and rep["hierarchy"]["options"]["levels_requested"] == 3
    # an explicit count that cannot be met: one line, exit code 2, no traceback, before any work
    t = time.perf_counter()
    rc = main(["cages", str(src), "--face-counts", "5000", "--out", str(tmp_path / "c"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and time.perf_counter() - t < 1.0
    assert err.startswith("nestmg: error: --face-counts 5000 cannot be met") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_cli_cages_of_an_input_too_coarse_for_any_cage(tmp_path, capsys):
    """A 12-face box: no cage of 100 faces fits under it. ``nestmg cages`` says so in one line naming
    ``--face-counts`` (exit code 2, before any cage work), and builds the cage that option asks for."""
    import trimesh

    from nestmg.cli import main

    src = tmp_path / "box.stl"
    trimesh.creation.box(extents=(30.0, 20.0, 10.0)).export(src)
    t = time.perf_counter()
    rc = main(["cages", str(src), "--levels", "3", "--out", str(tmp_path / "c"), "--quiet", "--no-cache"])
    err = capsys.readouterr().err
    assert rc == 2 and time.perf_counter() - t < 5.0
    assert err.startswith("nestmg: error: no cage fits a 12-face input at ratio 4") and "Traceback" not in err
    assert "(e.g. [6]); on the command line: --face-counts" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()
    rc = main(["cages", str(src), "--face-counts", "6", "--out", str(tmp_path / "c"), "--quiet", "--no-cache"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "[12, 6] faces; verifier ok=True" in out.out
