"""cagegen.build_cages: audit first, backend from the registry, certification of every layer."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

import cagegen
from cagegen import registry
from cagegen.errors import BackendUnavailableError, CageError, LevelsError, MeshInputError


def _ico(sub: int, r: float = 1.0):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


@pytest.fixture(scope="module")
def ball():
    return _ico(4)  # 5120 faces


def _scaled_spheres(V, F, face_counts, *, scales=None, progress=None):
    """Test backend: icospheres of growing radius (nested unless ``scales`` says otherwise)."""
    scales = scales or [1.2 + 0.2 * k for k in range(len(face_counts))]
    subs = {1280: 3, 320: 2, 80: 1}
    layers = [_ico(subs[c], s) for c, s in zip(face_counts, scales)]
    if progress:
        progress("scaled spheres done")
    return layers, {"scales": scales}


@pytest.fixture
def spheres_backend(monkeypatch):
    monkeypatch.setitem(registry._BACKENDS, "spheres",
                        registry.BackendSpec(_scaled_spheres, takes=frozenset({"progress"})))
    return "spheres"


def test_certified_hierarchy(ball, spheres_backend):
    V0, F0 = ball[0].copy(), ball[1].copy()
    msgs = []
    layers, info = cagegen.build_cages(
        *ball, method="spheres", face_counts=[1280, 320], return_info=True, progress=msgs.append
    )
    assert np.array_equal(ball[0], V0) and np.array_equal(ball[1], F0)  # caller's arrays untouched
    assert len(layers) == 3 and np.array_equal(layers[0][0], V0) and np.array_equal(layers[0][1], F0)
    assert info["certified"] is True and info["nested"] is True
    assert info["achieved_face_counts"] == [1280, 320]
    assert info["backend"] == {"scales": [1.2, 1.4]}
    pairs = info["verification"]["pairs"]
    assert [p["ok"] for p in pairs] == [True, True]
    assert pairs[0]["min_winding"] == pytest.approx(1.0, abs=1e-2)
    assert info["audit"]["ok"] is True and info["audit"]["genus"] == 0
    json.dumps(info)
    assert "scaled spheres done" in msgs and any("verification: nested" in m for m in msgs)
    assert cagegen.build_cages(*ball, 3, method="spheres", face_counts=[1280, 320])[2][1].shape == (320, 3)


def test_default_face_counts_used(ball, spheres_backend):
    # 5120 faces, 3 levels -> [1280, 320]
    layers = cagegen.build_cages(*ball, 3, method="spheres")
    assert [F.shape[0] for _, F in layers] == [5120, 1280, 320]


def test_non_nested_layer_raises_naming_it(ball, monkeypatch):
    def backend(V, F, face_counts):
        return _scaled_spheres(V, F, face_counts, scales=[1.4, 1.2])  # layer 2 inside layer 1

    monkeypatch.setitem(registry._BACKENDS, "bad", backend)
    with pytest.raises(CageError) as ei:
        cagegen.build_cages(*ball, method="bad", face_counts=[1280, 320])
    assert ei.value.layer == 2 and "does not contain layer 1" in str(ei.value)
    # verify=False skips the gate but the result is then not certified
    layers, info = cagegen.build_cages(*ball, method="bad", face_counts=[1280, 320], verify=False,
                                       return_info=True)
    assert info["certified"] is False and info["verification"] is None and len(layers) == 3


def test_min_gap_is_passed_to_the_verifier(ball, spheres_backend):
    diag = np.linalg.norm(ball[0].max(0) - ball[0].min(0))
    with pytest.raises(CageError, match="min_gap") as ei:
        cagegen.build_cages(*ball, method="spheres", face_counts=[1280], min_gap=0.25 / diag)
    assert ei.value.layer == 1
    assert len(cagegen.build_cages(*ball, method="spheres", face_counts=[1280], min_gap=0.15 / diag)) == 2


def test_input_is_audited_before_the_backend(ball, monkeypatch):
    called = []
    monkeypatch.setitem(registry._BACKENDS, "spy", lambda *a, **k: called.append(1))
    with pytest.raises(MeshInputError, match="open boundary"):
        cagegen.build_cages(ball[0], ball[1][1:], 2, method="spy")
    with pytest.raises(MeshInputError, match="inside-out"):
        cagegen.build_cages(ball[0], ball[1][:, ::-1], 2, method="spy")
    assert not called
    # repair=True flips the inside-out input, then the backend runs
    monkeypatch.setitem(registry._BACKENDS, "spheres", _scaled_spheres)
    layers = cagegen.build_cages(ball[0], ball[1][:, ::-1], method="spheres", face_counts=[1280], repair=True)
    assert np.array_equal(layers[0][1], ball[1])


def test_input_audited_once_per_run(ball, spheres_backend, monkeypatch):
    """One exact self-intersection test of the input per run: the audit's; the verifier skips layer 0,
    and a caller's passed audit (audit=) replaces build_cages' own. Same layers and report either way."""
    import cagegen.audit
    import cagegen.verify

    tested = []
    for mod in (cagegen.audit, cagegen.verify):
        real = mod.self_intersection_pairs
        monkeypatch.setattr(mod, "self_intersection_pairs",
                            lambda V, F, *a, real=real: tested.append(len(F)) or real(V, F, *a))
    layers, info = cagegen.build_cages(*ball, method="spheres", face_counts=[1280, 320], return_info=True)
    assert tested == [5120, 1280, 320]  # the audit's, then the cages' (not the input's again)
    assert info["verification"]["pairs"][0]["self_intersections_fine"] == 0 and info["certified"]

    _, _, audit = cagegen.check_mesh(*ball, return_audit=True)
    tested.clear()
    monkeypatch.setattr(cagegen.build, "check_mesh", lambda *a, **k: pytest.fail("audited again"))
    layers2, info2 = cagegen.build_cages(*ball, method="spheres", face_counts=[1280, 320], return_info=True,
                                         audit=audit)
    assert tested == [1280, 320]
    assert all(np.array_equal(Va, Vb) and np.array_equal(Fa, Fb)
               for (Va, Fa), (Vb, Fb) in zip(layers, layers2))

    def figures(i):  # the verifier's figures but its seconds and igl's threaded winding sums (last bits)
        return [{k: v for k, v in p.items() if k not in ("seconds", "min_winding")}
                for p in i["verification"]["pairs"]]

    assert figures(info2) == figures(info)
    assert info2["verification"]["pairs"][0]["min_winding"] == pytest.approx(1.0, abs=1e-12)
    assert info2["audit"] == info["audit"]
    # an audit of another mesh, or without the self-intersection test, is refused in one line
    _, _, small = cagegen.check_mesh(*_ico(2), return_audit=True)
    with pytest.raises(cagegen.CageOptionError, match="passed audit"):
        cagegen.build_cages(*ball, method="spheres", face_counts=[1280], audit=small)
    no_self = cagegen.audit_mesh(*ball, self_intersections=False)
    with pytest.raises(cagegen.CageOptionError, match="self-intersections tested"):
        cagegen.build_cages(*ball, method="spheres", face_counts=[1280], audit=no_self)


def test_bad_backend_output(ball, monkeypatch):
    monkeypatch.setitem(registry._BACKENDS, "short", lambda V, F, c: ([_ico(3, 1.2)], {}))
    with pytest.raises(CageError, match="returned 1 layers for 2"):
        cagegen.build_cages(*ball, method="short", face_counts=[1280, 320])
    monkeypatch.setitem(registry._BACKENDS, "junk", lambda V, F, c: ([(np.zeros((3, 2)), np.zeros((1, 3)))], {}))
    with pytest.raises(CageError) as ei:
        cagegen.build_cages(*ball, method="junk", face_counts=[1280])
    assert ei.value.layer == 1


def test_progress_true_prints_to_stderr(ball, spheres_backend, capsys):
    cagegen.build_cages(*ball, method="spheres", face_counts=[1280], progress=True)
    err = capsys.readouterr().err
    assert "[cagegen] input: 2562 vertices, 5120 faces" in err and "scaled spheres done" in err
    cagegen.build_cages(*ball, method="spheres", face_counts=[1280], progress=False)
    assert capsys.readouterr().err == ""
    with pytest.raises(TypeError, match="progress"):
        cagegen.build_cages(*ball, method="spheres", face_counts=[1280], progress="yes")


def test_levels_and_method_errors(ball, spheres_backend):
    with pytest.raises(LevelsError, match="needs 2 face counts"):
        cagegen.build_cages(*ball, 3, method="spheres", face_counts=[1280])
    with pytest.raises(LevelsError, match="levels"):
        cagegen.build_cages(*ball, method="spheres")
    with pytest.raises(LevelsError, match="at most"):
        cagegen.build_cages(*ball, 6, method="spheres")
    with pytest.raises(ValueError, match="unknown cage method"):
        cagegen.build_cages(*ball, 2, method="no-such-method")
    monkeypatch_target = "cagegen.no_such_module:fn"
    registry._BACKENDS["missing"] = monkeypatch_target
    try:
        with pytest.raises(BackendUnavailableError):
            cagegen.build_cages(*ball, 2, method="missing")
        assert "missing" not in cagegen.available_backends()
    finally:
        del registry._BACKENDS["missing"]
    assert "decimate" in cagegen.available_backends()


def test_public_exports():
    for name in ["build_cages", "verify_nesting", "NestingReport", "audit_mesh", "check_mesh",
                 "default_face_counts", "register_backend", "available_backends", "errors"]:
        assert hasattr(cagegen, name)
    assert cagegen.errors.CageError is CageError


def test_per_layer_backend_is_looped_by_build_cages(ball, monkeypatch):
    """A registered per-layer function gets the previous layer and the input's diagonal as ``unit``;
    build_cages loops, reports one line per layer and writes the same info keys as for every such backend."""
    calls = []

    def grow(V, F, n_faces, *, unit, factor=1.2):
        calls.append((len(F), n_faces, unit))
        c = V.mean(axis=0)
        return c + factor * (V - c), F.copy(), {"n_faces": len(F), "progress": "grown"}

    monkeypatch.setitem(registry._BACKENDS, "grow", registry.BackendSpec(grow, layer=True))
    msgs = []
    layers, info = cagegen.build_cages(*ball, method="grow", face_counts=[1280, 320], return_info=True,
                                       progress=msgs.append)
    diag = cagegen._geometry.bbox_diagonal(ball[0])
    assert calls == [(5120, 1280, diag), (5120, 320, diag)]
    assert info["certified"] and [len(F) for _, F in layers] == [5120] * 3
    be = info["backend"]
    assert be["method"] == "grow" and be["nested_by_construction"] is True and be["genus_changes"] == []
    assert [li["layer"] for li in be["layers"]] == [1, 2] and "progress" not in be["layers"][0]
    assert be["layers"][1]["volume_ratio_to_input"] == pytest.approx(1.44**3, rel=1e-9)
    assert be["layers"][0]["hausdorff_relative_to_input"] > 0
    assert sum(m.startswith("grow: layer ") and ", grown, max distance" in m for m in msgs) == 2


def test_registry_declares_what_each_backend_takes():
    for name in ("nested", "skeleton"):
        spec = registry.backend_spec(name)
        assert not spec.layer and spec.own_loop  # each says why it loops itself
    for name in ("decimate", "lazy", "sdf"):
        assert registry.backend_spec(name).layer and not registry.backend_spec(name).own_loop
    assert registry.get_schedule("sdf") is cagegen.sdf.sdf_schedule  # its time budget: the whole run
    assert registry.get_schedule("decimate") is None
    with pytest.raises(TypeError, match="takes must be a subset"):
        registry.register_backend("x", lambda *a: None, takes=("colour",))
    with pytest.raises(TypeError, match="CageOptions"):
        registry.register_backend("x", lambda *a: None, options=dict)
    assert "x" not in registry.registered_backends()
