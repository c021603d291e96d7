"""nestmg.usermesh: the user's tet mesh as the fine level, meshio formats, save/load, scikit-fem matrices,
license-safe defaults and the CLI's unknown-method exit code."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cagegen
from cagegen.errors import BackendUnavailableError, MeshInputError, NestmgError
from nestmg import (
    NestmgInputError,
    hierarchy_from_tets,
    load_hierarchy,
    load_tet_mesh,
    save_hierarchy,
    save_tet_mesh,
    shapes,
    tetrahedralize,
    write_vtu_levels,
)
from nestmg.usermesh import boundary_surface, p1_to_p2_prolongation

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def user_mesh(tmp_path_factory):
    """A TetWild tet mesh of a procedural sphere (the 'user's mesh') and its hierarchy."""
    with pytest.MonkeyPatch.context() as mp:  # the session's cache folder (conftest), not the user's
        mp.setenv("NESTMG_CACHE", str(tmp_path_factory.getbasetemp() / "nestmg-cache"))
        Vs, Fs = shapes.sphere(res=16)
        V, T = tetrahedralize(Vs, Fs, edge_length=0.06)
        H = hierarchy_from_tets(V, T, levels=3, progress=False)
    return V, T, H


def test_fine_level_is_the_user_mesh_and_certified(user_mesh):
    V, T, H = user_mesh
    assert H.levels == 3
    assert np.array_equal(H.tets[0][0], V) and np.array_equal(H.tets[0][1], T)
    assert H.certified and H.n_outside == [0, 0] and H.fallbacks == []
    assert H.options["fine_level"] == "user" and H.method == "nested"
    # the surface that was caged is the boundary of the user's tets
    Vs, Fs, _ = boundary_surface(V, T)
    assert np.array_equal(H.surfaces[0][0], Vs) and np.array_equal(H.surfaces[0][1], Fs)
    assert len(H.surfaces[1][1]) < len(Fs) and len(H.tets[1][0]) < len(V)
    for P in H.P:  # barycentric: rows sum to 1, no negative weights (no extrapolation)
        assert np.allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0, atol=1e-12) and P.data.min() >= -1e-12
    # P reproduces linear functions on the user's nodes (they all lie inside the coarse tets)
    g = np.array([0.3, -1.2, 0.7])
    assert np.abs(H.P[0] @ (1.0 + H.tets[1][0] @ g) - (1.0 + V @ g)).max() < 1e-10
    assert "fallbacks" in H.to_dict() and "Hierarchy(method='nested', levels=3, certified=True)" in repr(H)


@pytest.mark.parametrize("fmt", [("gmsh22", ".msh"), ("medit", ".mesh"), ("vtu", ".vtu"), ("vtk", ".vtk")])
def test_meshio_formats_come_back_node_for_node(user_mesh, tmp_path, fmt):
    import meshio

    V, T, _ = user_mesh
    fmt_name, ext = fmt
    path = tmp_path / f"part{ext}"
    cells = [("triangle", boundary_surface(V, T)[1]), ("tetra", T)] if ext == ".msh" else [("tetra", T)]
    meshio.write(str(path), meshio.Mesh(V, cells), file_format=fmt_name)
    V2, T2 = load_tet_mesh(path)
    assert np.array_equal(T2, T)
    assert np.abs(V2 - V).max() <= 1e-15 * np.abs(V).max()  # ASCII Medit: round-trip to the last bit or so
    if ext in (".msh", ".vtu"):  # two formats through the whole pipeline (cages and tets from the cache)
        H2 = hierarchy_from_tets(V2, T2, levels=3, progress=False)
        assert np.array_equal(H2.tets[0][0], V2) and np.array_equal(H2.tets[0][1], T)
        assert H2.certified and H2.P[0].shape == (len(V), len(H2.tets[1][0]))


def test_bad_user_meshes_are_refused(tmp_path):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(MeshInputError, match="used by no tet"):
        hierarchy_from_tets(np.vstack([V, [[3.0, 3, 3]]]), [[0, 1, 2, 3]])
    with pytest.raises(MeshInputError, match="flat|zero volume"):
        hierarchy_from_tets(np.vstack([V, [[0.5, 0.5, 0]]]), [[0, 1, 2, 3], [0, 1, 2, 4]])
    with pytest.raises(MeshInputError, match="out of range|indices"):
        hierarchy_from_tets(V, [[0, 1, 2, 9]])
    # a hollow ball is accepted (tests/test_nestmg_cavities.py), disjoint bodies too (test_nestmg_bodies.py)
    # a file with triangles only is not a tet mesh
    Vs, Fs = shapes.sphere(res=12)
    import meshio

    meshio.write(str(tmp_path / "s.vtu"), meshio.Mesh(Vs, [("triangle", Fs)]))
    with pytest.raises(MeshInputError, match="no tetrahedra"):
        load_tet_mesh(tmp_path / "s.vtu")


def test_save_load_round_trip_and_vtu(user_mesh, tmp_path):
    import meshio

    _, _, H = user_mesh
    save_hierarchy(tmp_path / "h", H)
    H2 = load_hierarchy(tmp_path / "h")
    assert H2.levels == H.levels and H2.to_dict() == H.to_dict()
    for (a, b), (c, d) in zip(H.tets + H.surfaces, H2.tets + H2.surfaces):
        assert np.array_equal(a, c) and np.array_equal(b, d)
    for P, Q in zip(H.P, H2.P):
        assert P.shape == Q.shape and abs(P - Q).max() == 0
    # an altered file is refused, not silently used
    npz = tmp_path / "h" / "hierarchy.npz"
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["tets0_V"] = arrays["tets0_V"] + 1e-9
    np.savez_compressed(npz, **arrays)
    with pytest.raises(NestmgError, match="SHA-256"):
        load_hierarchy(tmp_path / "h")
    with pytest.raises(NestmgError, match="no saved hierarchy"):
        load_hierarchy(tmp_path / "nothing")
    # one pair, the path first (as save_mesh): the 0.1 order (H, directory) is refused before any write
    with pytest.raises(NestmgInputError, match=r"save_hierarchy\(directory, H\)"):
        save_hierarchy(H, tmp_path / "swapped")
    assert not (tmp_path / "swapped").exists()
    assert not hasattr(H, "save") and not hasattr(type(H), "load")
    # VTU per level, fields on level 0, in the given frame
    u = np.arange(len(H.tets[0][0]), dtype=float)
    files = write_vtu_levels(tmp_path / "vtu", H, {"u": u}, frame=(np.array([1.0, 2.0, 3.0]), 2.0))
    assert [f.name for f in files] == ["level_0.vtu", "level_1.vtu", "level_2.vtu"]
    m0 = meshio.read(files[0])
    assert np.allclose(m0.points, H.tets[0][0] * 2.0 + [1.0, 2.0, 3.0], rtol=0, atol=1e-14)
    assert np.array_equal(m0.point_data["u"], u) and np.array_equal(m0.cells_dict["tetra"], H.tets[0][1])
    assert len(meshio.read(files[2]).cells_dict["tetra"]) == len(H.tets[2][1])
    with pytest.raises(NestmgInputError, match="values"):
        write_vtu_levels(tmp_path / "vtu", H, {"u": u[:-1]})
    # the tet-mesh pair: save_tet_mesh writes what load_tet_mesh reads, node for node
    V0, T0 = H.tets[0]
    for ext in (".vtu", ".msh"):
        save_tet_mesh(tmp_path / f"fine{ext}", V0, T0)
        V1, T1 = load_tet_mesh(tmp_path / f"fine{ext}")
        assert np.array_equal(V1, V0) and np.array_equal(T1, T0)


def test_skfem_example_matches_nestmg_assembly(user_mesh):
    """scikit-fem's matrices on the user's mesh converge like nestmg's own assembly (iterations +-1)."""
    pytest.importorskip("skfem")
    from nestmg import setup_problem
    from solvers import MultigridSolver

    spec = importlib.util.spec_from_file_location("skfem_poisson", ROOT / "docs" / "examples" / "skfem_poisson.py")
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    V, T, H = user_mesh
    out = ex.main(V, T, verbose=False)
    assert np.array_equal(out["hierarchy"].tets[0][1], T)
    own = {}
    for name in ("poisson-dirichlet", "poisson-neumann"):
        prob = setup_problem(H.tets, H.P, name)
        ml = MultigridSolver(prob.A, prob.P, nullspace=prob.nullspace)
        own[name] = ml.solve(prob.b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"]
    assert abs(out["dirichlet_mgpcg"] - own["poisson-dirichlet"]) <= 1, (out, own)
    assert abs(out["neumann_mgpcg"] - own["poisson-neumann"]) <= 1, (out, own)
    assert out["dirichlet_mgpcg"] <= 12 and out["dirichlet_residual"] < 1e-8 and out["neumann_residual"] < 1e-8
    # scipy's cg with the V-cycle as M= takes the same number of steps and finds the same solution
    assert abs(out["dirichlet_scipy_cg"] - out["dirichlet_mgpcg"]) <= 1 and out["scipy_vs_mg"] < 1e-6
    # P2 on the same tets through the exact P1 -> P2 level: still a handful of iterations
    assert out["p2_mgpcg"] <= 15 and out["p2_residual"] < 1e-8


def test_p1_to_p2_prolongation_reproduces_linear_functions():
    skfem = pytest.importorskip("skfem")
    m = skfem.MeshTet().refined(2)
    basis = skfem.Basis(m, skfem.ElementTetP2())
    P = p1_to_p2_prolongation(m.nvertices, m.edges.T)
    def lin(x):
        return 2.0 + x[0] - 3 * x[1] + 0.5 * x[2]

    assert np.abs(P @ lin(m.p) - basis.project(lin)).max() < 1e-12


def test_volumetric_arap_names_tetgen_when_absent(monkeypatch):
    from cagegen.nested.energies import check_energy_available, make_energy

    monkeypatch.setitem(sys.modules, "tetgen", None)
    with pytest.raises(BackendUnavailableError, match=r"TetGen \(AGPL-3.0\).*nestmg\[tetgen\]"):
        check_energy_available("volumetric_arap")
    V, F = shapes.sphere(res=8)
    with pytest.raises(BackendUnavailableError, match="copyleft"):
        make_energy("volumetric_arap", V, F)
    check_energy_available("volume")  # permissive energies need nothing


_LICENSE_PROBE = r"""
import sys
import numpy as np
import cagegen.nested.backend as nb
from cagegen import CageError
from nestmg import SizingOptions, build_hierarchy, shapes
V, F = shapes.sphere(res=12)
h = build_hierarchy(V, F, levels=2, sizing=SizingOptions(edge_length=0.15), cache=False, progress=False)
assert h.certified and h.fallbacks == [], h
# the default nested backend, forced to fail: its default fallback is the MIT sdf cage, never the GPL
# lazy one; without a fallback it raises
from cagegen.nested.flow import FlowResult
nb.flow_inside = lambda Vf, *a, **kw: FlowResult([Vf], False, 0, "forced failure (test)", 1.0)
layers, info = nb.nested_backend(V, F, [300], max_recovery_depth=0)
assert info["layers"][0]["fallback"] == "sdf", info["layers"][0].get("fallback")
try:
    nb.nested_backend(V, F, [300], max_recovery_depth=0, fallback=None)
    raise SystemExit("no CageError")
except CageError:
    pass
print(sorted(m for m in sys.modules if m.split(".")[0] in ("gpytoolbox", "tetgen") or "copyleft" in m))
"""


def test_default_nested_run_loads_no_copyleft_module():
    r = subprocess.run([sys.executable, "-c", _LICENSE_PROBE], check=False, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout


def test_unknown_method_exits_with_code_2(capsys):
    from nestmg.cli import main

    names = cagegen.registered_backends()
    for bad in ["bogus"] + ([] if "sdf" in names else ["sdf"]):
        assert main(["solve", "shape:torus", "--method", bad]) == 2
        err = capsys.readouterr().err
        assert f"unknown --method {bad!r}" in err and "nested" in err and "Traceback" not in err
    assert main(["compare", "shape:torus", "--methods", "nested", "bogus"]) == 2
    with pytest.raises(cagegen.UnknownMethodError, match="registered"):
        cagegen.build_cages(*shapes.sphere(res=8), 2, method="bogus")


def test_cli_solve_on_a_tet_mesh_file_writes_vtu(user_mesh, tmp_path, capsys):
    import meshio

    from nestmg.cli import main

    V, T, _ = user_mesh
    Vu = V * 40.0 + [5.0, -2.0, 1.0]  # the user's own units: the VTU files must come back in them
    src = tmp_path / "part.msh"
    meshio.write(str(src), meshio.Mesh(Vu, [("tetra", T)]), file_format="gmsh")
    out = tmp_path / "out"
    rc = main(["solve", str(src), "--levels", "3", "--problem", "poisson-neumann", "--accel", "cg", "--quiet",
               "--out", str(out), "--json", str(tmp_path / "r.json")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "certified=True" in text and "level_2.vtu" in text
    m0 = meshio.read(out / "level_0.vtu")
    assert np.array_equal(m0.cells_dict["tetra"], T) and np.abs(m0.points - Vu).max() < 1e-12 * 40
    u = m0.point_data["u"]
    assert u.shape == (len(V),) and np.isfinite(u).all() and np.std(u) > 0
    assert (out / "level_1.vtu").is_file() and (out / "level_2.vtu").is_file()


def test_fallback_layers_are_reported(user_mesh):
    import dataclasses

    _, _, H = user_mesh
    info = dict(H.cage_info, backend={"layers": [{"layer": 1}, {"layer": 2, "fallback": "lazy"}]})
    Hf = dataclasses.replace(H, cage_info=info)
    assert Hf.fallbacks == [{"layer": 2, "fallback": "lazy"}]
    assert "layer 2 by fallback 'lazy'" in repr(Hf).splitlines()[0]
    assert Hf.to_dict()["fallbacks"] == [{"layer": 2, "fallback": "lazy"}]


def test_cli_cages_on_a_tet_mesh_file_cages_its_boundary(user_mesh, tmp_path, capsys):
    import meshio

    from nestmg.cli import main

    V, T, _ = user_mesh
    src = tmp_path / "part.vtu"
    meshio.write(str(src), meshio.Mesh(V, [("tetra", T)]))
    assert main(["cages", str(src), "--levels", "3", "--out", str(tmp_path / "c"), "--quiet"]) == 0
    n_bnd = len(boundary_surface(V, T)[1])
    assert f"3 layers [{n_bnd}," in capsys.readouterr().out and (tmp_path / "c" / "layer_2.obj").is_file()
