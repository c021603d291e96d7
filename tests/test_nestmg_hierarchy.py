"""build_hierarchy options (nestmg.hierarchy): same-domain levels below the cages."""

import numpy as np
import pytest

from nestmg import MeshingOptions, SizingOptions, shapes
from nestmg.hierarchy import build_hierarchy


@pytest.fixture(scope="module")
def sphere_surface():
    return shapes.sphere(20)


def test_same_domain_levels(sphere_surface):
    pytest.importorskip("tetgen")
    V, F = sphere_surface
    V0, F0 = V.copy(), F.copy()
    h = build_hierarchy(V, F, 3, "decimate", sizing=SizingOptions(edge_length=0.03, same_domain_levels=1),
                        meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    np.testing.assert_array_equal(V, V0)
    np.testing.assert_array_equal(F, F0)
    assert h.levels == 3 and len(h.P) == 2
    # level 1 re-meshes the input surface itself; level 2 is the (decimated) cage with 4x fewer faces
    np.testing.assert_array_equal(h.surfaces[1][0], h.surfaces[0][0])
    np.testing.assert_array_equal(h.surfaces[1][1], h.surfaces[0][1])
    assert len(h.surfaces[2][1]) < len(F) / 3
    ntets = [len(T) for _, T in h.tets]
    assert ntets[0] > 3 * ntets[1] > 0, ntets  # 2x the edge length: several times fewer tets
    # TetGen keeps the boundary: every fine node lies in the same-domain coarse mesh (up to location
    # round-off on the shared boundary), so P reproduces linear functions at the fine nodes
    assert h.prolongation_reports[0].max_distance_rel < 1e-9
    a = np.array([0.7, -0.2, 1.3])
    Vf, Vc = h.tets[0][0], h.tets[1][0]
    assert np.abs(h.P[0] @ (Vc @ a) - Vf @ a).max() < 1e-8
    assert h.options["sizing"]["same_domain_levels"] == 1
    # the cage pair itself is not nested (decimation): extrapolated nodes only on the coarse level
    assert h.n_outside[1] > 0


@pytest.mark.parametrize("bad", [-1, 2, 5, 1.0, "1"])
def test_same_domain_levels_validated(sphere_surface, bad):
    V, F = sphere_surface
    with pytest.raises(ValueError, match="same_domain_levels"):
        build_hierarchy(V, F, 3, "decimate", sizing=SizingOptions(same_domain_levels=bad),
                        meshing=MeshingOptions(mesher="tetgen"), cache=False)


def test_cage_surfaces_take_the_callers_audit(sphere_surface, monkeypatch):
    """build_cage_surfaces hands a passed audit of an already-normalised input to build_cages (not audited
    again); an input in other coordinates is audited (its normalised copy is other arrays)."""
    import cagegen
    import cagegen.build
    from nestmg.hierarchy import _normalize, build_cage_surfaces

    V, F = sphere_surface
    Vn = _normalize(np.ascontiguousarray(V, dtype=np.float64))[0]
    _, _, audit = cagegen.check_mesh(Vn, F, return_audit=True)
    real, calls = cagegen.build.check_mesh, []
    monkeypatch.setattr(cagegen.build, "check_mesh", lambda *a, **k: calls.append(1) or real(*a, **k))
    kw = {"sizing": SizingOptions(face_counts=[len(F) // 4]), "cache": False, "progress": False}
    S, info = build_cage_surfaces(Vn, F, 2, "decimate", audit=audit, **kw)
    assert not calls and info["audit"] == audit.to_dict() and len(S[1][1]) <= len(F) // 4
    S2, _ = build_cage_surfaces(3.0 * Vn + 1.0, F, 2, "decimate", audit=audit, **kw)
    assert calls == [1] and np.allclose(S2[1][0], 3.0 * S[1][0] + 1.0)


def test_one_bounding_box_normalisation():
    """nestmg's normalisations are cagegen.normalize, bit for bit: centred box, unit diagonal."""
    import cagegen
    from nestmg.hierarchy import _normalize
    from nestmg.io import normalize

    V = np.random.default_rng(3).normal(size=(200, 3)) * [3.0, 0.5, 1.0] + [10.0, -4.0, 0.25]
    Vc, c, s = cagegen.normalize(V)
    for Vn, cn, sn in (normalize(V), _normalize(V)):
        assert np.array_equal(Vn, Vc) and np.array_equal(cn, c) and sn == s
    assert np.allclose(Vc.max(0) + Vc.min(0), 0.0, atol=1e-15)
    assert np.linalg.norm(Vc.max(0) - Vc.min(0)) == pytest.approx(1.0, abs=1e-15)
    assert np.allclose(Vc * s + c, V, rtol=0, atol=1e-13)


def test_cage_levels_bound_tetwild_passes(monkeypatch):
    """The cage levels get at most ``coarse_max_opt_iter`` TetWild passes (a runaway sizing-field loop on a
    cage's thin triangles can be cut there), the input's level keeps ``max_opt_iter``; the smaller one wins."""
    import nestmg.hierarchy as hh
    from nestmg.hierarchy import tet_hierarchy

    seen = []
    real = hh.tetrahedralize
    monkeypatch.setattr(hh, "tetrahedralize", lambda V, F, **kw: seen.append(kw) or real(V, F, **kw))
    S = shapes.nested_isosurfaces("torus", [0.0, 0.15, 0.35], [20, 12, 8])
    sizing = SizingOptions(edge_length=0.08, coarsening=None)
    tets, P, _, _ = tet_hierarchy(S, sizing=sizing, meshing=MeshingOptions(coarse_max_opt_iter=20), cache=False,
                                  progress=False)
    assert [kw["max_opt_iter"] for kw in seen] == [80, 20, 20]
    assert [kw.get("coarsen") for kw in seen][1:] == [True] * 2
    assert all(len(T) > 0 for _, T in tets) and len(P) == 2
    seen.clear()
    tet_hierarchy(S[:2], sizing=sizing, meshing=MeshingOptions(max_opt_iter=12, coarse_max_opt_iter=30),
                  cache=False, progress=False)
    assert [kw["max_opt_iter"] for kw in seen] == [12, 12]
    seen.clear()
    tet_hierarchy(S[:2], sizing=sizing, cache=False, progress=False)
    assert [kw["max_opt_iter"] for kw in seen] == [80, 80]  # the default: fTetWild's own on every level
