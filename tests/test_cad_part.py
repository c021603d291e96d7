"""A CAD-like part made in code (issue 27): flat faces fanned from corners, sharp edges, long thin triangles.

The nested flow used to fail on such parts (the dev zoo's STL exports: angle_block, featuretype, ...):
the flow samples F at its triangles' quadrature points, and one sliver across a flat face is sampled far
too sparsely, so F stayed cut by Ĉ ("flow no convergence after 1000 iterations"). When the flow fails
anyway, the fallback must keep the pipeline's clearance (it used to return a cage closer than ``min_gap``,
refused by the certification after minutes of work).
"""

from __future__ import annotations

import numpy as np
import pytest

from cagegen import audit_mesh, verify_nesting
from cagegen.nested.backend import nested_backend
from nestmg.shapes import SHAPES, plate_with_holes

GAP = 0.0025  # the pipeline's clearance under TetWild (2.5 epsilon)


def _aspect(V, F):
    E = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2)
    A = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    return E.max(1) ** 2 / (2 * A)  # longest edge over the height on it


@pytest.mark.parametrize("holes", [1, 3])
def test_plate_with_holes_is_a_closed_cad_like_mesh(holes):
    V, F = plate_with_holes(holes=holes, segments=16)
    a = audit_mesh(V, F)
    assert a.ok and a.genus == holes and a.n_self_intersections == 0
    hole_area = 0.5 * 16 * 0.3**2 * np.sin(2 * np.pi / 16)  # the 16-gon
    assert a.volume == pytest.approx(holes * (1 - hole_area) * 0.08, rel=1e-12)
    assert _aspect(V, F).max() > 10  # STL-like slivers, not a smooth remesh
    assert "plate_holes" in SHAPES  # `nestmg ... shape:plate_holes`


def test_nested_flow_cages_a_cad_plate_without_fallback():
    """2 holes, 32-gons, 284 faces -> 80: the flow failed here before the long edges were split for it
    (measured at 3075c35: "flow no convergence after 1000 iterations"); now certified by the flow itself,
    into the decimated layer or into the decimated envelope (with Ĉ expanded after 5 idle iterations the
    flow into the layer stalls after 200 iterations and the envelope's takes 7; after 50, 563 iterations)."""
    V, F = plate_with_holes(holes=2, segments=32)
    layers, info = nested_backend(V, F, [80], min_gap=GAP, fallback=None, max_recovery_depth=0)
    (C, G), = layers
    lay = info["layers"][0]
    assert len(G) == 80 and "fallback" not in lay and "intermediate" not in lay
    assert lay["decimation"]["source"] in ("layer", "envelope") and lay["flow"]["success"]
    assert lay["split"]["faces_out"] > len(F)  # the flow ran on the split copy ...
    rep = verify_nesting([(V, F), (C, G)], min_gap=GAP)  # ... the cage nests the caller's surface
    assert rep.ok, rep.pairs[0].reason
    assert lay["min_gap_relative"] >= GAP


@pytest.mark.parametrize("fallback", ["sdf", "lazy"])
def test_fallback_keeps_the_clearance(fallback):
    """A flow that fails (cut after 5 iterations): the fallback's cage keeps ``min_gap`` and is certified."""
    if fallback == "lazy":
        pytest.importorskip("gpytoolbox")
    from nestmg.shapes import sphere

    V, F = sphere(10)
    # target_offset=0: no envelope target (this 60-face layer's coarse envelope certifies in 5 iterations)
    layers, info = nested_backend(V, F, [60], min_gap=GAP, fallback=fallback, max_recovery_depth=0,
                                  flow_max_iter=5, target_offset=0)
    lay = info["layers"][0]
    assert lay["fallback"] == fallback
    assert any(r["stage"] == "fallback" for r in lay["recovery"])
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    assert lay["min_gap_absolute"] >= GAP * diag
    assert verify_nesting([(V, F), layers[0]], min_gap=GAP).ok


def test_envelope_target_contains_what_the_decimated_part_cuts_away():
    """The cause of the CAD flow failures: QEM leaves most of a plate outside its own decimation
    (flat faces kept in place, hole rims cut), while the decimated offset envelope leaves a few
    percent outside, by less than the clearance (measured: 97% / 0.0115 against 2.4% / 0.0008)."""
    import igl

    from cagegen.decimate import decimate_surface
    from cagegen.nested.backend import _envelope_target

    V, F = plate_with_holes(holes=4, segments=24)
    V = (V - 0.5 * (V.min(0) + V.max(0))) / np.linalg.norm(V.max(0) - V.min(0))
    U, G, _ = decimate_surface(V, F, 100)
    S = igl.signed_distance(V, U, G)[0]
    assert (S > 0).mean() > 0.5
    U2, G2, dinfo = _envelope_target(V, F, 100, 0.01)
    assert abs(len(G2) - 100) <= 2 and dinfo["envelope_faces"] > 10 * len(G2)
    S2 = igl.signed_distance(V, U2, G2)[0]
    assert (S2 > 0).mean() < 0.05 and S2.max() < GAP


def _first_flow_fails(monkeypatch, failing_flow) -> list:
    """Make the first flow of the run fail (the stand-in ``failing_flow``), the others real; returns the
    list that counts the flows."""
    import cagegen.nested.backend as nb

    real, calls = nb.flow_inside, []

    def first_fails(*args, **kwargs):
        calls.append(1)
        return failing_flow(*args, **kwargs) if len(calls) == 1 else real(*args, **kwargs)

    monkeypatch.setattr(nb, "flow_inside", first_fails)
    return calls


def test_envelope_target_is_the_recovery_when_the_papers_flow_fails(monkeypatch, failing_flow):
    """The paper's target first (tightest cages); when its flow fails, Ĉ decimated from the offset envelope
    (CAD parts, scans: featuretype, cheburashka, homer, lucy in the dev zoo) certifies with a short flow."""
    calls = _first_flow_fails(monkeypatch, failing_flow)
    V, F = plate_with_holes(holes=4, segments=24)
    layers, info = nested_backend(V, F, [100], min_gap=GAP, fallback=None, max_recovery_depth=0)
    lay = info["layers"][0]
    assert len(calls) == 2 and lay["decimation"]["source"] == "envelope"
    assert lay["failed_attempts"][0]["action"].startswith("decimate the layer")
    assert lay["flow"]["iterations"] <= 50
    assert verify_nesting([(V, F), layers[0]], min_gap=GAP).ok
    assert lay["min_gap_relative"] >= GAP


def test_later_layers_try_the_envelope_first_once_a_layer_needed_it(monkeypatch, failing_flow,
                                                                    one_ipctk_thread):
    """Layer 1's flow into its decimated layer fails, the envelope target certifies it; layer 2 then starts
    with the envelope target (``FOLLOW_PREVIOUS_SOURCE``: lucy.ply's second layer spent 37 s in a failed
    flow before the envelope certified it), so no flow of layer 2 fails."""
    calls = _first_flow_fails(monkeypatch, failing_flow)
    V, F = plate_with_holes(holes=4, segments=48)
    layers, info = nested_backend(V, F, [300, 100], min_gap=GAP, fallback=None, max_recovery_depth=0)
    one, two = info["layers"]
    assert one["decimation"]["source"] == "envelope" and len(one["failed_attempts"]) == 1
    assert one["failed_attempts"][0]["flow_iterations"] == 0 and one["failed_attempts"][0]["seconds"] >= 0
    # layer 2 goes straight to the envelope and none of its flows fails; a first envelope target may still
    # miss the clearance after the final energy (with Gauss-Newton reverse steps, REVERSE_HESSIAN, its gap
    # came out 0.00183 < GAP here) and the next envelope target certifies
    assert two["decimation"]["source"] == "envelope"
    assert all(f["action"].startswith("decimate the envelope") and f["stage"] != "flow"
               for f in two["failed_attempts"])
    assert len(calls) == 3 + len(two["failed_attempts"])
    assert verify_nesting([(V, F), *layers], min_gap=GAP).ok


def _genus(V, F) -> int:
    import igl

    return (2 - (len(V) - len(igl.edges(F)) + len(F))) // 2


def test_a_coarse_layer_closes_the_holes_it_cannot_follow(monkeypatch, failing_flow, one_ipctk_thread):
    """The envelope's offset follows the target's resolution (``TARGET_OFFSET_EDGE_FRACTION``): a 40-face
    layer around a plate with four small holes is decimated from a genus-0 envelope (featuretype.stl's
    218-face layer 2: ~300 s of failed flows from the 0.01 envelope of its genus-9 layer 1, 0.3 CPU s
    from the 0.033 one); the same layer with the offset pinned to 0.01 keeps the holes."""
    import cagegen.nested.backend as nb

    V, F = plate_with_holes(holes=4, segments=16, radius=0.08)
    assert _genus(V, F) == 4
    _first_flow_fails(monkeypatch, failing_flow)
    layers, info = nested_backend(V, F, [40], min_gap=GAP, fallback=None, max_recovery_depth=0)
    lay = info["layers"][0]
    Vn = (V - 0.5 * (V.min(0) + V.max(0))) / np.linalg.norm(V.max(0) - V.min(0))
    edge = nb._target_edge(Vn, F, 40)
    assert lay["decimation"]["source"] == "envelope"
    assert lay["decimation"]["offset"] == pytest.approx(nb.TARGET_OFFSET_EDGE_FRACTION * edge, rel=1e-9)
    assert lay["decimation"]["offset"] > 0.02 and _genus(*layers[0]) == 0
    assert verify_nesting([(V, F), layers[0]], min_gap=GAP).ok
    U, G, dinfo = nb._envelope_target(Vn, F, 40, 0.01)
    assert _genus(U, G) == 4  # at the old fixed offset the coarse target keeps every hole
