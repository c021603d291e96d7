"""Solids with voids (a hollow part: an outer surface and inward-facing surfaces inside it), nestmg.cavities:
cages of the outer surface, the voids kept in the levels meshed from the input."""

import json

import numpy as np
import pytest

from cagegen import MeshInputError
from nestmg import MeshingOptions, NestmgInputError, SizingOptions, build_hierarchy, setup_problem
from nestmg.bodies import disjoint_bodies
from nestmg.cavities import hollow_solid, solid_groups
from nestmg.cli import _bodies, main
from nestmg.io import save_mesh
from nestmg.memory import signed_volume
from nestmg.shapes import SHAPES
from nestmg.tetmesh import tet_volumes


def _hollow_ball(inner: float = 0.5, res: int = 16, shift=(0.0, 0.0, 0.0)):
    """A unit ball with a ball-shaped void of radius ``inner`` (its surface facing the void)."""
    V, F = SHAPES["sphere"](res=res)
    return (np.vstack([V, inner * V + [0.1, 0.0, 0.0]]) + shift,
            np.vstack([F, F[:, ::-1] + len(V)]))


def test_voids_are_inward_pieces_inside_one_outward_piece():
    import cagegen

    V, F = _hollow_ball()
    outer, voids, count = hollow_solid(V, F)
    assert count == 1 and signed_volume(*outer) > 0 and signed_volume(*voids) < 0
    assert signed_volume(*outer) + signed_volume(*voids) == pytest.approx(signed_volume(V, F), rel=1e-12)
    Vs, Fs = SHAPES["sphere"](res=16)
    assert hollow_solid(Vs, Fs) is None  # one piece
    # an outward piece inside another is no void (a body inside a hollow one, or a wrong orientation)
    assert hollow_solid(np.vstack([Vs, 0.3 * Vs]), np.vstack([Fs, Fs + len(Vs)])) is None
    # an inward piece crossing the outer surface, or outside it, is no void either
    pieces = cagegen.split_components(*_hollow_ball(0.5, shift=(0, 0, 0)))
    crossing = [pieces[0], (pieces[1][0] + [0.6, 0.0, 0.0], pieces[1][1])]
    assert solid_groups(crossing) is None
    apart = [pieces[0], (pieces[1][0] + [5.0, 0.0, 0.0], pieces[1][1])]
    assert solid_groups(apart) is None


def test_a_hollow_ball_keeps_its_void_on_the_fine_levels_and_is_certified():
    V, F = _hollow_ball()
    V = 30.0 * V + [100.0, -5.0, 2.0]  # the user's units
    H = build_hierarchy(V, F, levels=3, sizing=SizingOptions(max_tets=60_000), progress=False)
    assert H.certified and H.n_outside == [0, 0] and H.cage_info["voids"]["count"] == 1
    assert hollow_solid(*H.surfaces[0])[2] == 1  # level 0's surface: the (predecimated) outer and the void
    assert len(H.surfaces[-1][1]) < len(F) // 2  # a cage of the outer surface only
    for Vt, T in H.tets[:2]:  # the levels meshed from the input: solid volume, the void left out
        vol = float(np.abs(tet_volumes(Vt, T)).sum())
        assert vol == pytest.approx(signed_volume(V, F), rel=0.01)
    Vt, T = H.tets[2]  # the cage level fills the void (it contains the whole solid)
    assert float(np.abs(tet_volumes(Vt, T)).sum()) > signed_volume(V, F) * 1.1
    # nodes on the void's wall are boundary nodes: Dirichlet fixes them; Neumann converges as usual
    c = np.array([100.0 + 3.0, -5.0, 2.0])  # the void's centre (radius 15)
    Vf = H.tets[0][0]
    dirichlet = setup_problem(H.tets, H.P, "poisson-dirichlet")
    free = dirichlet.free[0]
    on_void = np.flatnonzero(np.abs(np.linalg.norm(Vf - c, axis=1) - 15.0) < 0.2)
    assert on_void.size > 100 and not np.isin(on_void, free).any()
    for name in ("poisson-dirichlet", "poisson-neumann"):
        pr = setup_problem(H.tets, H.P, name)
        _, info = pr.multigrid().solve(pr.b, tol=1e-8, accel="cg", return_info=True)
        assert info["converged"] and info["iterations"] <= 10, (name, info["iterations"])
    with pytest.raises(NestmgInputError, match="void.*TetWild"):
        build_hierarchy(V, F, levels=3, meshing=MeshingOptions(mesher="tetgen"), progress=False)


def test_cli_solves_a_hollow_part_and_two_hollow_bodies(tmp_path, capsys):
    V, F = _hollow_ball(res=12)
    src = tmp_path / "hollow.obj"
    save_mesh(src, V, F)
    assert _bodies(V, F)[2] is None  # one solid with a void: no error, no split into bodies
    rc = main(["cages", str(src), "--levels", "2", "--out", str(tmp_path / "c"), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads((tmp_path / "c" / "report.json").read_text())
    assert rep["verification"]["ok"] and rep["voids"]["count"] == 1 and rep["faces"][0] == len(F)
    # two hollow balls apart: two bodies, each with its void
    V2, F2 = _hollow_ball(res=12, shift=(4.0, 0.0, 0.0))
    Vb, Fb = np.vstack([V, V2]), np.vstack([F, F2 + len(V)])
    bodies = disjoint_bodies(Vb, Fb)
    assert len(bodies) == 2 and all(len(Fk) == len(F) for _, Fk in bodies)
    assert [signed_volume(*b) for b in bodies] == pytest.approx([signed_volume(V, F)] * 2, rel=1e-12)
    with pytest.raises(MeshInputError, match=r"(?s)void 1 of 1.*self-intersections"):
        Vbad = V.copy()
        k = len(V) // 2 + np.argmax(V[len(V) // 2:, 0])  # a void vertex pushed through the void
        Vbad[k] = 2 * np.array([0.1, 0, 0]) - (Vbad[k] - [0.1, 0, 0]) * 1.5
        build_hierarchy(Vbad, F, levels=2, progress=False)


def test_a_users_hollow_tet_mesh_keeps_its_nodes_and_void():
    from nestmg import hierarchy_from_tets
    from nestmg.tetmesh import tetrahedralize
    from nestmg.usermesh import boundary_surface

    V1, T1 = tetrahedralize(*_hollow_ball(res=12), mesher="tetwild", edge_length=0.1)
    assert hollow_solid(*boundary_surface(V1, T1)[:2]) is not None  # the tet mesh has the void
    H = hierarchy_from_tets(V1, T1, levels=2, progress=False)
    assert H.certified and H.n_outside == [0] and H.options["levels"] == len(H.tets) == 2
    assert np.array_equal(H.tets[0][0], V1) and np.array_equal(H.tets[0][1], T1)
    pr = setup_problem(H.tets, H.P, "poisson-neumann")
    _, info = pr.multigrid().solve(pr.b, tol=1e-8, accel="cg", return_info=True)
    assert info["converged"] and info["iterations"] <= 12


def test_a_small_hollow_cad_part_gets_refined_levels_with_its_void():
    """A tank exported as STL (outer cylinder, inner cylinder facing the void; too few faces for a cage):
    one coarse mesh of the whole solid, red refinements, the wall's volume on every level."""
    import trimesh

    a = trimesh.creation.cylinder(radius=40.0, height=120.0, sections=32)
    b = trimesh.creation.cylinder(radius=30.0, height=100.0, sections=32)
    V = np.vstack([a.vertices, b.vertices])
    F = np.vstack([a.faces, b.faces[:, ::-1] + len(a.vertices)]).astype(np.int64)
    H = build_hierarchy(V, F, levels=3, sizing=SizingOptions(max_tets=40_000), progress=False)
    assert H.certified and H.options["coarse_levels"] == "refinement"
    wall = signed_volume(V, F)
    assert wall == pytest.approx(float(a.volume - b.volume), rel=1e-9)
    for Vt, T in H.tets:
        assert float(np.abs(tet_volumes(Vt, T)).sum()) == pytest.approx(wall, rel=1e-3)
