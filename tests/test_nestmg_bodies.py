"""Inputs of several disjoint bodies (an assembly in one file): one hierarchy and one solve per body."""

import json
import time

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from nestmg import NestmgInputError, SizingOptions, setup_problem
from nestmg.bodies import body_sizings, build_body_hierarchies, disjoint_bodies, file_frame, solve_bodies
from nestmg.cli import main
from nestmg.io import load_mesh, load_tet_mesh, save_mesh
from nestmg.shapes import SHAPES


def _sphere_and_torus(shift: float = 3.0):
    """A unit sphere (2,312 faces) and a torus (1,344 faces) ``shift`` apart along x: apart for 3."""
    V1, F1 = SHAPES["sphere"](res=16)
    V2, F2 = SHAPES["torus"](res=16)
    return np.vstack([V1, V2 + [shift, 0.0, 0.0]]), np.vstack([F1, F2 + len(V1)])


def test_disjoint_bodies_are_pieces_that_neither_cross_nor_nest():
    V, F = _sphere_and_torus()
    bodies = disjoint_bodies(V, F)
    assert [len(Fb) for _, Fb in bodies] == [2312, 1344]
    assert disjoint_bodies(*SHAPES["sphere"](res=16)) is None  # one piece
    assert disjoint_bodies(*_sphere_and_torus(2.0)) is None  # the torus crosses the sphere: one solid's job
    V1, F1 = SHAPES["sphere"](res=16)
    assert disjoint_bodies(np.vstack([V1, 0.3 * V1]), np.vstack([F1, F1 + len(V1)])) is None  # a cavity


def test_body_sizings_give_every_body_the_whole_inputs_edge_and_budget():
    V, F = _sphere_and_torus()
    bodies = disjoint_bodies(V, F)
    sizings, plan = body_sizings(V, F, bodies, 3, SizingOptions(max_tets=30_000))
    _, scale = file_frame(V)
    diags = [float(np.linalg.norm(np.ptp(Vb, axis=0))) for Vb, _ in bodies]
    absolute = [s.edge_length * d for s, d in zip(sizings, diags)]
    assert absolute == pytest.approx([plan["edge_length"] * scale] * 2, rel=1e-12)
    assert plan["rule"] == "max_tets" and plan["expected_tets"][0] <= 30_000  # all bodies' tets in one cap
    with pytest.raises(NestmgInputError, match="2 disjoint bodies"):
        body_sizings(V, F, bodies, 3, SizingOptions(face_counts=(400,)))


def test_each_body_is_solved_in_the_files_frame():
    """The combined solution is every body's own problem solved: checked against a direct solve."""
    V, F = _sphere_and_torus()
    hs = build_body_hierarchies(V, F, 3, "decimate", sizing=SizingOptions(max_tets=20_000), cache=False,
                                progress=False)
    assert len(hs) == 2 and all(h.levels == 3 for h in hs)
    center, scale = frame = file_frame(V)
    r = solve_bodies(hs, frame, "poisson-dirichlet", return_solution=True)
    assert r["converged"] and len(r["bodies"]) == 2
    assert r["iterations"] == max(b["iterations"] for b in r["bodies"])
    u, start = r["solution"], 0
    for h in hs:
        tets = [((Vt - center) / scale, T) for Vt, T in h.tets]
        p = setup_problem(tets, h.P, "poisson-dirichlet")
        ref = p.expand(spla.spsolve(p.A.tocsc(), p.b))
        ub = u[start:start + len(ref)]
        assert np.abs(ub - ref).max() <= 1e-6 * np.abs(ref).max()
        start += len(ref)
    assert start == len(u)


def test_cli_solve_and_cages_on_two_bodies(tmp_path, capsys):
    V, F = _sphere_and_torus()
    mesh = tmp_path / "two.obj"
    save_mesh(mesh, V, F)
    out, js = tmp_path / "out", tmp_path / "r.json"
    rc = main(["solve", str(mesh), "--method", "decimate", "--levels", "3", "--max-tets", "20000",
               "--problem", "poisson-neumann", "--out", str(out), "--json", str(js), "--quiet"])
    assert rc == 0
    rep = json.loads(js.read_text())
    assert len(rep["bodies"]) == 2 and rep["solve"]["converged"]
    assert all(b["solve"]["residuals"][-1] <= 1e-8 * b["solve"]["residuals"][0] for b in rep["bodies"])
    Vt, T = load_tet_mesh(out / "level_0.vtu")
    assert len(Vt) == sum(b["hierarchy"]["nodes"][0] for b in rep["bodies"])
    import meshio

    m = meshio.read(out / "level_0.vtu")
    assert m.point_data["u"].shape == (len(Vt),) and set(np.unique(m.cell_data["body"][0])) == {0, 1}
    assert Vt[:, 0].max() > 3.5 and Vt[:, 0].min() < -0.9  # both bodies, in the input's coordinates
    for k in range(2):  # Neumann: each body's solution has zero mean on its own (its own nullspace)
        nodes = np.unique(T[m.cell_data["body"][0] == k])
        assert abs(m.point_data["u"][nodes].mean()) < 0.05 * np.abs(m.point_data["u"][nodes]).max()
    assert "2 bodies: largest factor" in capsys.readouterr().out

    cages = tmp_path / "cages"
    assert main(["cages", str(mesh), "--method", "decimate", "--levels", "3", "--out", str(cages), "--quiet"]) == 0
    rep = json.loads((cages / "report.json").read_text())
    assert [b["faces"] for b in rep["bodies"]] == [[2312, 578, 144], [1344, 336]]  # levels: a ceiling per body
    assert rep["faces"] == [3656, 914, 144]
    assert [len(load_mesh(cages / f"layer_{k}.obj")[1]) for k in range(3)] == rep["faces"]
    t = time.perf_counter()
    assert main(["cages", str(mesh), "--face-counts", "500", "--out", str(tmp_path / "c2"), "--quiet"]) == 2
    assert "2 disjoint bodies" in capsys.readouterr().err and time.perf_counter() - t < 5.0


def test_tet_mesh_of_two_bodies_gets_one_stacked_hierarchy():
    """A user's tet mesh of two bodies: level 0 node for node, no prolongation couples the bodies, the
    body with fewer levels repeats its coarsest one, and a pure Neumann problem (one constant per body in
    the kernel) is consistent and solved."""
    from nestmg import hierarchy_from_tets
    from nestmg.bodies import tet_bodies
    from solvers.gallery import kuhn_cube_mesh

    VA, TA = kuhn_cube_mesh(12)  # 1,728 boundary faces: 3 levels
    VB, TB = kuhn_cube_mesh(8)  # 768: 2 levels (a 192-face cage; a third would have 48 faces)
    V = np.vstack([0.7 * VB + [2.0, 0.0, 0.0], VA])  # the smaller body first ...
    T = np.vstack([TA + len(VB), TB])
    perm = np.random.default_rng(3).permutation(len(V))  # ... its nodes scattered among the other's
    inv = np.argsort(perm)
    V, T, inB = V[perm], inv[T], perm < len(VB)
    assert [len(b) for b in tet_bodies(T, len(V))] == [len(VB), len(VA)][:: 1 if inB[0] else -1]
    H = hierarchy_from_tets(V, T, 3, cache=False, progress=False)
    assert H.levels == 3 and sorted(H.options["bodies"]) == [2, 3] and H.certified
    assert np.array_equal(H.tets[0][0], V) and np.array_equal(H.tets[0][1], T)
    for P in H.P:
        assert np.allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0)
    P0 = H.P[0].tocsr()
    assert not set(P0[inB].indices) & set(P0[~inB].indices)  # each body prolonged from its own nodes
    # the prolongation reproduces linear functions body by body: P0 maps coarse nodes to the user's nodes
    Vc = H.tets[1][0]
    assert np.abs(P0 @ Vc - V).max() < 1e-9
    first = 0 if inB[0] else 1  # the smaller body's coarse nodes come first when its nodes do
    nB1 = len(set(P0[inB].indices))
    P1 = H.P[1].tocsr()
    rows = slice(0, nB1) if first == 0 else slice(P1.shape[0] - nB1, None)
    D = P1[rows].toarray()  # the smaller body's coarsest level, repeated: the identity
    cols = slice(0, nB1) if first == 0 else slice(P1.shape[1] - nB1, None)
    assert np.array_equal(D[:, cols], np.eye(nB1)) and np.abs(D).sum() == nB1
    p = setup_problem(H.tets_in("normalized"), H.P, "poisson-neumann")
    assert max(abs(p.b[inB].sum()), abs(p.b[~inB].sum())) < 1e-12 * np.abs(p.b).sum()  # consistent per body
    x, info = p.multigrid().solve(p.b, tol=1e-8, accel="cg", return_info=True)
    assert info["converged"] and info["iterations"] <= 15
    assert np.linalg.norm(p.A @ x - p.b) <= 1e-7 * np.linalg.norm(p.b)


def test_a_bad_last_body_fails_in_seconds_naming_it(tmp_path, capsys):
    """Every body is audited before any hierarchy is built: an open last body stops the run at once."""
    V, F = _sphere_and_torus()
    mesh = tmp_path / "two.obj"
    save_mesh(mesh, V, F[:-1])  # the torus (second body) loses a face: open
    save_mesh(tmp_path / "ok.obj", V, F)
    assert main(["compare", str(tmp_path / "ok.obj"), "--methods", "decimate", "--quiet"]) == 2
    assert "compare takes one solid; ok has 2 disjoint bodies" in capsys.readouterr().err
    for cmd in (["solve", str(mesh)], ["cages", str(mesh), "--out", str(tmp_path / "c")]):
        t = time.perf_counter()
        assert main([*cmd, "--levels", "3", "--quiet", "--no-cache"]) == 2
        assert time.perf_counter() - t < 5.0
        assert "body 2 of 2 is not a usable closed surface" in capsys.readouterr().err


def test_specks_are_refused_or_dropped_with_repair(tmp_path, capsys):
    """Scan debris: a body under SPECK_FRACTION of the volume is not meshed as a body of its own."""
    V1, F1 = SHAPES["sphere"](res=16)
    V = np.vstack([V1, 0.05 * V1 + [3.0, 0.0, 0.0]])  # a speck: 1.25e-4 of the sphere's volume
    F = np.vstack([F1, F1 + len(V1)])
    mesh, js = tmp_path / "speck.obj", tmp_path / "r.json"
    save_mesh(mesh, V, F)
    assert main(["solve", str(mesh), "--quiet", "--no-cache"]) == 2
    err = capsys.readouterr().err
    assert "2 disjoint bodies, 1 of them specks" in err and "first: body 2); --repair drops them" in err
    assert main(["solve", str(mesh), "--repair", "--method", "decimate", "--max-tets", "20000", "--quiet",
                 "--no-cache", "--json", str(js)]) == 0
    rep = json.loads(js.read_text())
    assert "bodies" not in rep and rep["hierarchy"]["surface_faces"][0] == len(F1)  # the sphere alone
