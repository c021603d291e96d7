"""cagegen.copyleft.lazy: the ``lazy`` backend (gpytoolbox, GPL) and its use as the nested backend's fallback."""

from __future__ import annotations

import importlib
import json
import sys

import numpy as np
import pytest
import trimesh

import cagegen
from cagegen import registry
from cagegen.errors import BackendUnavailableError, CageError

pytest.importorskip("gpytoolbox", reason="the lazy backend needs the optional 'lazy' extra (gpytoolbox, GPL)")

from cagegen.copyleft.lazy import genus, lazy_cage_layer
from nestmg import shapes

FAST = {"grid_size": 20, "max_iter": 5}


@pytest.fixture(scope="module")
def neck():
    return shapes.neck_blobs(res=28)  # 2364 faces, genus 0


@pytest.fixture(scope="module")
def neck_lazy(neck):
    V, F = neck
    return cagegen.build_cages(V, F, face_counts=[600, 150], method="lazy", return_info=True, **FAST)


def test_lazy_layers_certified(neck_lazy):
    layers, info = neck_lazy
    assert info["certified"] is True and info["method"] == "lazy"
    assert [p["ok"] for p in info["verification"]["pairs"]] == [True, True]
    # an independent re-verification of the returned layers (fresh call, exact winding numbers)
    rep = cagegen.verify_nesting(layers)
    assert rep.ok
    for p in rep.pairs:
        assert p.min_winding == pytest.approx(1.0, abs=1e-9)
        assert p.n_outside_vertices == 0 and p.n_intersecting_pairs == 0
        assert p.min_gap_rel > 1e-4  # a loose cage: clearly separated
    achieved = info["achieved_face_counts"]
    assert abs(achieved[0] - 600) <= 30 and abs(achieved[1] - 150) <= 15
    be = info["backend"]
    assert be["nested_by_construction"] is True and len(be["layers"]) == 2
    for k, li in enumerate(be["layers"], start=1):
        assert li["layer"] == k and li["n_faces"] == achieved[k - 1]
        assert 1.0 < li["volume_ratio"] < 3.0 and 0 < li["offset_relative"] < 0.5
        # the binary search keeps the smallest accepted offset
        acc = [s["d_relative"] for s in li["iterations"] if s["accepted"]]
        assert li["offset_relative"] == pytest.approx(min(acc), rel=1e-12)
        assert any(not s["accepted"] for s in li["iterations"])  # the search did get close enough to fail
    assert be["layers"][1]["volume_ratio_to_input"] > be["layers"][0]["volume_ratio_to_input"] > 1.0
    json.dumps(info)


def test_lazy_tet_layers_have_no_fine_node_outside(neck_lazy):
    """Tet-level certification: TetGen keeps each cage's boundary, so no fine node falls outside."""
    pytest.importorskip("tetgen")
    from nestmg import MeshingOptions, SizingOptions
    from nestmg.hierarchy import tet_hierarchy

    layers, _ = neck_lazy
    tets, P, reps, _ = tet_hierarchy(layers, sizing=SizingOptions(edge_length=0.06, coarsening=None),
                                     meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    assert [r.n_outside for r in reps] == [0, 0]
    for k, Pk in enumerate(P):
        assert Pk.shape == (len(tets[k][0]), len(tets[k + 1][0]))
        # barycentric rows reproduce linear functions (no extrapolation anywhere)
        Vc = tets[k + 1][0]
        assert np.allclose(Pk @ Vc, tets[k][0], atol=1e-9)


def test_genus_change_is_reported():
    """A fat torus (hole radius 0.2) loses its hole in a 150-face cage: reported, not hidden."""
    t = trimesh.creation.torus(1.0, 0.8, major_sections=32, minor_sections=16)
    V, F = np.asarray(t.vertices), np.asarray(t.faces, dtype=np.int64)
    msgs: list[str] = []
    layers, info = cagegen.build_cages(V, F, face_counts=[150], method="lazy", return_info=True,
                                       progress=msgs.append, grid_size=16, max_iter=5)
    U, G = layers[1]
    g = trimesh.Trimesh(U, G, process=False)
    true_genus = int((2 - g.euler_number) // 2)
    li = info["backend"]["layers"][0]
    assert li["genus_fine"] == 1 and li["genus"] == true_genus == genus(U, G)
    assert true_genus == 0 and li["genus_changed"] is True
    assert info["backend"]["genus_changes"] == [{"layer": 1, "from": 1, "to": 0}]
    assert any("genus 1 -> 0" in m for m in msgs)
    assert info["certified"] is True


def test_genus_helper():
    s = trimesh.creation.icosphere(subdivisions=2)
    assert genus(s.vertices, s.faces) == 0
    t = trimesh.creation.torus(1.0, 0.3)
    assert genus(t.vertices, t.faces) == 1
    # two disjoint tori: genus 2, one open surface: None
    V2 = np.vstack([t.vertices, t.vertices + [5.0, 0, 0]])
    F2 = np.vstack([t.faces, t.faces + len(t.vertices)])
    assert genus(V2, F2) == 2
    assert genus(s.vertices, s.faces[:-1]) is None


def test_layer_hook_does_not_modify_input_and_rejects_bad_options(neck):
    V, F = neck
    V0, F0 = V.copy(), F.copy()
    Vf = np.asfortranarray(V)
    U, G, _info = lazy_cage_layer(Vf, F, 200, grid_size=16, max_iter=4)
    assert np.array_equal(V, V0) and np.array_equal(F, F0)
    assert U.dtype == np.float64 and G.dtype == np.int64 and G.shape[1] == 3
    assert cagegen.verify_nesting([(V, F), (U, G)]).ok
    for bad in ({"n_faces": 2}, {"n_faces": 10.5}, {"grid_size": 4}, {"max_iter": 0}, {"decimator": "x"}):
        kw = {"n_faces": 200, "grid_size": 16, "max_iter": 4, **bad}
        with pytest.raises(ValueError):
            lazy_cage_layer(V, F, **kw)
    with pytest.raises(cagegen.MeshInputError):
        lazy_cage_layer(V[:, :2], F, 200)


def test_no_certified_candidate_raises_cage_error(neck, monkeypatch):
    import cagegen.copyleft.lazy as lazy_mod

    monkeypatch.setattr(lazy_mod, "_accept", lambda *a: "rejected by the test")
    V, F = neck
    with pytest.raises(CageError) as exc:
        cagegen.build_cages(V, F, method="lazy", face_counts=[300], grid_size=12, max_iter=2)
    assert exc.value.layer == 1 and "rejected by the test" in str(exc.value)


def test_missing_gpytoolbox_gives_backend_unavailable(monkeypatch):
    for name in [m for m in sys.modules if m == "gpytoolbox" or m.startswith("gpytoolbox.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "gpytoolbox", None)
    monkeypatch.delitem(sys.modules, "cagegen.copyleft.lazy", raising=False)
    with pytest.raises(BackendUnavailableError) as exc:
        registry.get_backend("lazy")
    assert "gpytoolbox" in str(exc.value) and "lazy" in str(exc.value)
    assert "lazy" not in cagegen.available_backends()
    with pytest.raises(BackendUnavailableError):
        importlib.import_module("cagegen.copyleft.lazy")
    s = trimesh.creation.icosphere(subdivisions=3)
    with pytest.raises(BackendUnavailableError):
        cagegen.build_cages(s.vertices, s.faces, face_counts=[100], method="lazy")


def test_mixed_nested_and_lazy_hierarchy_certified(neck):
    """Nested (flow + re-inflation) for layer 1, lazy for layer 2: the whole list is certified."""
    from cagegen.nested import nested_backend

    V, F = neck
    (L1,), _ = nested_backend(V, F, [600])
    U, G, info = lazy_cage_layer(*L1, 150, **FAST)
    rep = cagegen.verify_nesting([(V, F), L1, (U, G)])
    assert rep.ok, str(rep)
    assert rep.pairs[0].min_gap_rel < rep.pairs[1].min_gap_rel  # the nested cage is the tighter one
    assert info["n_faces"] == len(G)


def test_nested_backend_falls_back_to_lazy(neck, monkeypatch, failing_flow):
    """Flow always failing and no intermediate layer allowed: the layer comes from the lazy cage, reported."""
    import cagegen.nested.backend as nb

    monkeypatch.setattr(nb, "flow_inside", failing_flow)
    V, F = neck
    msgs: list[str] = []
    layers, info = nb.nested_backend(V, F, [600], max_recovery_depth=0, progress=msgs.append, fallback="lazy")
    assert cagegen.verify_nesting([(V, F)] + layers).ok
    li = info["layers"][0]
    assert li["fallback"] == "lazy" and li["lazy"]["n_faces"] == len(layers[0][1])
    assert li["verification"]["ok"] is True
    fb = [r for r in info["recovery"] if r["stage"] == "fallback"]
    assert len(fb) == 1 and "lazy" in fb[0]["action"] and "layer 1" in fb[0]["reason"]
    assert any("falling back to a lazy cage" in m for m in msgs)
    with pytest.raises(CageError) as exc:  # without a fallback the failure is raised
        nb.nested_backend(V, F, [600], max_recovery_depth=0, fallback=None)
    assert exc.value.layer == 1


def test_nested_fallback_without_gpytoolbox_raises_the_original_error(neck, monkeypatch, failing_flow):
    import cagegen.nested.backend as nb

    monkeypatch.setattr(nb, "flow_inside", failing_flow)
    monkeypatch.setitem(sys.modules, "cagegen.copyleft.lazy", None)  # import of the hook fails
    V, F = neck
    with pytest.raises(CageError, match="lazy fallback unavailable") as exc:
        nb.nested_backend(V, F, [600], max_recovery_depth=0, fallback="lazy")
    assert exc.value.layer == 1
    with pytest.raises(ValueError, match="fallback"):
        nb.nested_backend(V, F, [600], max_recovery_depth=0, fallback="bogus")


def test_clearance_is_kept_by_pushing_out(neck, neck_lazy):
    """With ``min_gap`` (what nestmg's pipeline passes under TetWild) every layer keeps it, certified by the
    verifier; the offset alone does not (the decimation cuts back towards the fine layer), so the
    tightest accepted candidates are pushed out (issue 27: 'gap 6.95e-05 < 0.0025')."""
    V, F = neck
    want = 0.03
    pairs = neck_lazy[1]["verification"]["pairs"]
    assert min(p["min_gap_rel"] for p in pairs) < want  # without the clearance
    msgs: list[str] = []
    layers, info = cagegen.build_cages(V, F, face_counts=[600, 150], method="lazy", return_info=True,
                                       min_gap=want, progress=msgs.append, **FAST)
    assert info["certified"] is True
    ver = info["verification"]
    assert ver["min_gap_required"] == want and all(p["min_gap_rel"] >= want for p in ver["pairs"])
    rep = cagegen.verify_nesting(layers, min_gap=want)  # independent re-verification
    assert rep.ok and all(p.min_gap_rel >= want for p in rep.pairs)
    be = info["backend"]
    assert be["min_gap_requested"]["relative"] == pytest.approx(want)
    diag = cagegen._geometry.bbox_diagonal(V)
    assert be["min_gap_requested"]["absolute"] == pytest.approx(want * diag)
    assert sum(li["pushed"] for li in be["layers"]) >= 1  # the clearance came from the push-out
    for li, p in zip(be["layers"], ver["pairs"]):
        assert li["gap"] == pytest.approx(want * diag)
        if li["distance"] is not None:  # the backend's exact figure: at least min_gap, and agrees with the
            # verifier's (exact below its threshold, otherwise the vertex-face figure, an upper bound)
            assert want <= li["distance"] / diag <= p["min_gap_rel"] * (1 + 1e-9)
            if p["min_gap_exact"]:
                assert li["distance"] / diag == pytest.approx(p["min_gap_rel"], rel=1e-6)
    assert sum("gap" in m and "min_gap 0.03" in m for m in msgs) == 2
    json.dumps(info)


def test_blocked_push_out_rejects_the_candidate(neck, monkeypatch):
    """A candidate that cannot be moved out to the clearance is not accepted (never returned too close)."""
    import cagegen.copyleft.lazy as lazy_mod
    import cagegen.nested.backend as nb

    blocked = {"passes": 1, "distance_before": 0.0, "distance": 0.0, "reason": "blocked (test)"}
    monkeypatch.setattr(nb, "push_out", lambda *a, **kw: (None, blocked))
    monkeypatch.setattr(lazy_mod, "_distance_lower_bound", lambda *a: 0.0)  # every candidate needs the push
    V, F = neck
    with pytest.raises(CageError, match="push-out failed: blocked") as exc:
        cagegen.build_cages(V, F, method="lazy", face_counts=[300], min_gap=0.01, grid_size=12, max_iter=2)
    assert exc.value.layer == 1
    with pytest.raises(ValueError, match="gap"):
        lazy_cage_layer(V, F, 300, gap=-1.0)
    with pytest.raises(ValueError, match="min_gap"):
        cagegen.build_cages(V, F, method="lazy", face_counts=[300], min_gap=float("nan"))


def test_distance_lower_bound_is_below_the_exact_distance(neck, neck_lazy):
    from cagegen.copyleft.lazy import _distance_lower_bound
    from cagegen.collision import min_distance

    V, F = neck
    (L1, L2) = neck_lazy[0][1:]
    for (Vf, Ff), (U, G) in (((V, F), L1), (L1, L2)):
        exact = min_distance(U, G, Vf, Ff)
        lb = _distance_lower_bound(U, G, Vf, Ff)
        assert lb <= exact and exact > 0
    # a sphere inside a concentric sphere of twice the radius: distance 1, the bound within an edge of it
    s = trimesh.creation.icosphere(subdivisions=3)
    V1, F1 = np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int64)
    edge = float(np.linalg.norm(V1[F1[:, 0]] - V1[F1[:, 1]], axis=1).max())
    lb = _distance_lower_bound(2.0 * V1, F1, V1, F1)
    assert 1.0 - 2 * edge - 1e-9 <= lb <= 1.0
