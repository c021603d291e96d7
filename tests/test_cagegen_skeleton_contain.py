"""Tests of the skeleton backend's containment step (cagegen.skeleton.contain, issue 29).

The tight skeleton cage is made to contain M by re-inflating M swept down the harmonic guiding field's
level sets (IPC barrier + CCD, :func:`cagegen.nested.reinflate.reinflate`) instead of the Nested Cages
flow. Procedural shapes only (``nestmg.shapes``).
"""

from __future__ import annotations

import igl
import numpy as np
import pytest

from cagegen import CageError, CageOptionError, verify_nesting
from cagegen.skeleton import skeleton_cage
from cagegen.skeleton.contain import descend
from cagegen.skeleton.field import GuidingField
from nestmg.shapes import hand, star_of_capsules


@pytest.fixture(scope="module")
def star():
    return star_of_capsules()


def test_descend_records_the_level_crossings(star):
    """Lines followed down from M's vertices cross the requested levels in order; the recorded points
    have f equal to the level (linear interpolation inside one step of a piecewise-linear f)."""
    V, F, S = star
    diag = np.linalg.norm(np.ptp(V, axis=0))
    Vn = (V - V.mean(0)) / diag
    field = GuidingField(Vn, F, S.transformed(1 / diag, V.mean(0)).resampled(0.005).nodes, edge_length=0.02)
    levels = [0.8, 0.5, 0.2]
    P = Vn[::7]
    X, reached = descend(field, P, levels)
    assert X.shape == (3, len(P), 3)
    assert reached.mean() > 0.5  # the others stop at the first step (concave spots of M) or overshoot
    fs = [field.value(X[j, reached]) for j in range(len(levels))]
    # linear interpolation inside one RK2 step: f within a step's change of the level (f is steep near
    # the skeleton, where f = 0 is imposed on the nodes)
    for f, s, tol in zip(fs, levels, (0.12, 0.12, 0.2)):
        assert np.nanmax(np.abs(f - s)) < tol, (s, np.nanmax(np.abs(f - s)))
    assert (fs[0] > fs[1]).all() and (fs[1] > fs[2]).all()
    # the lines go inwards: every recorded point is inside M, deeper levels closer to the skeleton
    assert (igl.fast_winding_number(Vn, F, X[-1]) > 0.5).all()


def test_default_containment_certifies_the_star_with_clearance(star):
    V, F, S = star
    c = skeleton_cage(V, F, S, bending="given", min_gap=2.5e-3)
    rec = c.info["containment"]
    assert rec["target"] == "mesh" and rec["reinflate"]["reverse_steps"] > 0
    rep = verify_nesting([(V, F), (c.V, c.F)], min_gap=2.5e-3)
    assert rep.ok and rep.pairs[0].min_gap_rel >= 2.5e-3
    assert len(c.quads) == c.info["tight_cage"]["n_quads"]  # the re-inflation keeps every quad


def test_unknown_containment_is_an_option_error(star):
    V, F, S = star
    with pytest.raises(CageOptionError, match="containment"):
        skeleton_cage(V, F, S, bending="given", containment="magic")


@pytest.mark.slow
def test_old_flow_stalls_on_close_fingers_and_the_sweep_certifies():
    """Four fingers close together: M wraps around the concave corners between neighbouring finger tubes
    and the Nested Cages flow stalls (no progress over its stall window); the sweep containment
    certifies the same tight cage with the pipeline's clearance."""
    V, F, S = hand(res=44)
    with pytest.raises(CageError, match="inflation .*flow failed: stalled") as ei:
        skeleton_cage(V, F, S, bending="given", containment="flow", flow_stall_window=100)
    assert ei.value.partial.certified is False
    c = skeleton_cage(V, F, S, bending="given", min_gap=2.5e-3)
    rep = verify_nesting([(V, F), (c.V, c.F)], min_gap=2.5e-3)
    assert rep.ok and c.info["containment"]["reinflate"]["reverse_steps"] > 0


def test_containment_failure_names_the_step_and_carries_the_partial_cage(star, monkeypatch):
    """A re-inflation that fails (stubbed) twice, at both barrier ranges: a CageError naming the
    containment step, with the uncertified start cage, skeleton, sections and tight cage in
    ``exc.partial``."""
    import importlib

    rf = importlib.import_module("cagegen.nested.reinflate")  # the module (the package exports the function)

    calls = []

    def stuck(history, Ff, Vc, Fc, **kw):
        calls.append(kw["dhat"])
        return rf.ReinflateResult(cage=Vc, fine=history[-1], success=False, reason="stub: stuck", stats={})

    monkeypatch.setattr(rf, "reinflate", stuck)
    V, F, S = star
    with pytest.raises(CageError, match="containment .*stub: stuck") as ei:
        skeleton_cage(V, F, S, bending="given")
    assert calls == [5e-3, 2e-3]
    p = ei.value.partial
    assert p.certified is False and len(p.sections) == 8 and len(p.tight_V) == len(p.V)
