"""The command line and the README's example, end to end on procedural shapes."""

import json
import runpy
from pathlib import Path

import numpy as np

from nestmg.cli import main


def test_cli_solve_and_compare_on_builtin_shape(tmp_path, capsys):
    out = tmp_path / "solve.json"
    rc = main(["solve", "shape:sphere", "--method", "decimate", "--levels", "3", "--mesher", "tetgen",
               "--max-tets", "60000", "--problem", "poisson-dirichlet", "--json", str(out), "--quiet", "--png", str(tmp_path / "png")])
    assert rc == 0
    rep = json.loads(out.read_text())
    r = rep["solve"]
    assert r["converged"] and r["residuals"][-1] <= 1e-8 and r["factor"] < 0.5
    h = rep["hierarchy"]
    assert h["levels"] == 3 and len(h["n_outside"]) == 2
    assert h["tets"][0] > h["tets"][1] > h["tets"][2]
    assert set(r["seconds"]) == {"assembly", "setup", "solve"}
    assert (tmp_path / "png" / "convergence.png").stat().st_size > 5000
    assert (tmp_path / "png" / "layers.png").stat().st_size > 5000

    cmp_json = tmp_path / "cmp.json"
    rc = main(["compare", "shape:sphere", "--methods", "decimate", "--levels", "2", "--mesher", "tetgen",
               "--max-tets", "60000",
               "--problem", "poisson-neumann", "--json", str(cmp_json), "--quiet"])
    assert rc == 0
    rep = json.loads(cmp_json.read_text())
    assert rep["methods"]["decimate"]["solve"]["converged"]


def test_cli_cages_writes_layers_and_report(tmp_path):
    rc = main(["cages", "shape:torus", "--method", "decimate", "--levels", "3", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    from nestmg.io import load_mesh

    faces = [len(load_mesh(tmp_path / f"layer_{k}.obj")[1]) for k in range(3)]
    assert faces[0] > 3 * faces[1] > 9 * faces[2] / 1.5
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["faces"] == faces and "verification" in rep


def test_cli_reports_bad_input_cleanly(tmp_path, capsys):
    bad = tmp_path / "open.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    rc = main(["cages", str(bad), "--out", str(tmp_path / "o"), "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "error" in err and ("open" in err or "boundary" in err)
    assert main(["cages", str(tmp_path / "missing.off"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert bad.read_text().startswith("v 0 0 0")  # input untouched


def test_readme_example_runs():
    path = Path(__file__).resolve().parents[1] / "docs" / "examples" / "quickstart.py"
    ns = runpy.run_path(str(path))
    h, u, residuals = ns["main"](method="nested", mesher="tetwild")  # as in the README
    assert h.certified
    assert residuals[-1] <= 1e-8 and len(residuals) - 1 <= 40
    assert abs(u.mean()) < 1e-10 and np.isfinite(u).all()


def test_cli_cage_time_budget_refuses_at_once(tmp_path, capsys):
    """``--cage-time-budget`` reaches the nested and sdf backends: a budget below their estimate fails in
    well under a second with exit code 2 and a message naming the option; with another method it is
    refused."""
    import time

    for method in ("sdf", "nested"):
        t = time.perf_counter()
        rc = main(["cages", "shape:torus", "--method", method, "--cage-time-budget", "1", "--out", str(tmp_path),
                   "--quiet"])
        assert rc == 2 and time.perf_counter() - t < 5.0
        err = capsys.readouterr().err
        assert "exceeds cage_time_budget=1 s" in err and "--cage-time-budget" in err
        assert not (tmp_path / "layer_1.obj").exists()
    rc = main(["cages", "shape:torus", "--method", "decimate", "--cage-time-budget", "1", "--out", str(tmp_path),
               "--quiet"])
    assert rc == 2 and "applies to --method nested and sdf only" in capsys.readouterr().err


def test_cli_solve_writes_the_source_the_problem_was_given(tmp_path):
    """level_0.vtu's ``f`` is the model source at the normalised coordinates the problem is posed in (not
    at the input's coordinates), next to ``u``."""
    import meshio

    from nestmg.problems import default_rhs

    out, js = tmp_path / "o", tmp_path / "r.json"
    assert main(["solve", "shape:sphere", "--method", "decimate", "--max-tets", "20000", "--out", str(out),
                 "--json", str(js), "--quiet"]) == 0
    frame = json.loads(js.read_text())["hierarchy"]["frame"]
    m = meshio.read(out / "level_0.vtu")
    Vn = (m.points - np.asarray(frame["center"])) / frame["scale"]
    assert frame["scale"] > 2.0  # the input's frame is not the normalised one
    assert np.allclose(m.point_data["f"], default_rhs(Vn), rtol=1e-12, atol=1e-12)
    assert not np.allclose(m.point_data["f"], default_rhs(m.points), rtol=1e-3)
