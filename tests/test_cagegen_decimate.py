"""cagegen.decimate: the naive baseline gives watertight layers at the target counts (not nested)."""

from __future__ import annotations

import numpy as np
import pytest

from cagegen import build_cages
from cagegen._geometry import edge_stats, signed_volume
from cagegen.audit import audit_mesh
from cagegen.decimate import decimate_surface
from cagegen.sizes import default_face_counts


@pytest.fixture(scope="module")
def genus2():
    from nestmg import shapes

    return shapes.genus2()  # ~10k faces, genus 2


@pytest.mark.parametrize("decimator", ["qslim", "shortest_edge"])
def test_layers_watertight_at_target_counts(genus2, decimator):
    V, F = genus2
    V0, F0 = V.copy(), F.copy()
    targets = [2400, 600, 150]
    layers, info = build_cages(V, F, method="decimate", face_counts=targets, decimator=decimator,
                               return_info=True)
    layers, info = layers[1:], info["backend"]  # build_cages' loop over decimate_layer
    assert np.array_equal(V, V0) and np.array_equal(F, F0)
    assert len(layers) == 3 and info["nested_by_construction"] is False
    for (U, G), t, li in zip(layers, targets, info["layers"]):
        assert abs(G.shape[0] - t) <= 0.1 * t
        assert li["n_faces"] == G.shape[0] and li["target"] == t and li["seconds"] >= 0
        es = edge_stats(G, U.shape[0])
        assert es.closed_manifold  # watertight, manifold, consistently oriented
        a = audit_mesh(U, G)
        assert a.ok, str(a)
        assert a.genus == 2 and a.n_self_intersections == 0
        assert U.dtype == np.float64 and G.dtype == np.int64
    # QEM keeps the volume of this smooth shape within 2% at 600 faces (measured 0.986); shortest-edge
    # collapses to midpoints shrink it (measured 0.875)
    ratio = signed_volume(*layers[1]) / signed_volume(V, F)
    if decimator == "qslim":
        assert ratio == pytest.approx(1.0, abs=0.02)
    else:
        assert 0.8 < ratio < 0.95


def test_each_layer_decimates_the_previous(genus2):
    V, F = genus2
    layers = build_cages(V, F, method="decimate", face_counts=[2400, 600])[1:]
    U1, G1 = layers[0]
    U2, G2 = decimate_surface(U1, G1, 600)[:2]
    assert np.allclose(U2, layers[1][0]) and np.array_equal(G2, layers[1][1])


def test_build_cages_decimate_reports_but_does_not_gate(genus2):
    V, F = genus2
    layers, info = build_cages(V, F, 3, method="decimate", return_info=True)
    m = len(F)
    assert [G.shape[0] for _, G in layers] == [m] + default_face_counts(m, 3)  # QEM hits even targets
    assert info["certified"] is False
    # a QEM decimation of a curved surface cuts through it: the verifier figures say so
    v = info["verification"]
    assert info["nested"] is False and v["ok"] is False
    p0 = v["pairs"][0]
    assert p0["n_outside_vertices"] > 0 and p0["n_intersecting_pairs"] > 0
    assert info["backend"]["method"] == "decimate"


def test_bad_decimator(genus2):
    with pytest.raises(ValueError, match="decimator must be one of"):
        decimate_surface(*genus2, 500, decimator="fqmr")
