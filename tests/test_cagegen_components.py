"""cagegen.components: several closed pieces -> one certified hierarchy each, or a clear refusal."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import cagegen
from cagegen import build_cages, split_components
from cagegen.errors import MeshInputError


def _ball(sub=3, r=1.0, c=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices) + np.asarray(c), np.asarray(s.faces, dtype=np.int64)


def _union(*meshes):
    Vs, Fs, off = [], [], 0
    for V, F in meshes:
        Vs.append(V)
        Fs.append(F + off)
        off += len(V)
    return np.vstack(Vs), np.vstack(Fs)


def test_split_is_exact_and_ordered():
    a, b, c = _ball(2), _ball(1, c=(5, 0, 0)), _ball(3, c=(0, 5, 0))
    V, F = _union(a, b, c)
    pieces = split_components(V, F)
    assert [len(Fk) for _, Fk in pieces] == [320, 80, 1280]
    for (Vk, Fk), (Vo, Fo) in zip(pieces, (a, b, c)):
        np.testing.assert_array_equal(Vk, Vo)
        np.testing.assert_array_equal(Fk, Fo)


def test_default_refuses_and_names_the_option():
    V, F = _union(_ball(), _ball(c=(3, 0, 0)))
    with pytest.raises(MeshInputError, match=r"several connected components: 2 .*components='separate'"):
        build_cages(V, F, 2, method="decimate")
    with pytest.raises(ValueError, match="components must be"):
        build_cages(V, F, 2, method="decimate", components="joint")


@pytest.mark.parametrize("gap", [1.0, 1e-6])
def test_separate_hierarchies_are_certified_per_piece(gap):
    """Two spheres, far apart or nearly touching (gap 1e-6 of the radius): one certified hierarchy each."""
    try:
        cagegen.registry.get_backend("nested")
    except cagegen.BackendUnavailableError:
        pytest.skip("nested backend not available")
    a, b = _ball(3), _ball(3, r=0.7, c=(1.7 + gap, 0, 0))
    V, F = _union(a, b)
    V0, F0 = V.copy(), F.copy()
    out = build_cages(V, F, 2, method="nested", components="separate", return_info=True)
    assert len(out) == 2
    for k, ((layers, info), (Vk, Fk)) in enumerate(zip(out, (a, b))):
        assert info["component"] == k and info["n_components"] == 2
        assert info["certified"] and cagegen.verify_nesting(layers).ok
        np.testing.assert_array_equal(layers[0][0], Vk)
        assert [len(Fl) for _, Fl in layers] == [1280, 320]
    np.testing.assert_array_equal(V, V0)
    np.testing.assert_array_equal(F, F0)


def test_intersecting_or_nested_pieces_are_refused():
    V, F = _union(_ball(2), _ball(2, c=(1.5, 0, 0)))  # overlapping spheres
    with pytest.raises(MeshInputError, match="components 0 and 1 intersect"):
        build_cages(V, F, face_counts=[60], method="decimate", components="separate")
    V, F = _union(_ball(2, r=2.0), _ball(2, r=0.5))  # a ball floating inside a bigger one
    with pytest.raises(MeshInputError, match="component 1 lies inside component 0"):
        build_cages(V, F, face_counts=[60], method="decimate", components="separate")


def test_a_bad_piece_is_named_and_repair_applies_to_all():
    a, b = _ball(2), _ball(2, c=(3, 0, 0))
    b_open = (b[0], b[1][1:])
    V, F = _union(a, b_open)
    with pytest.raises(MeshInputError, match=r"(?s)component 1 of 2 is not a usable closed surface:.*open boundary"):
        build_cages(V, F, face_counts=[60], method="decimate", components="separate")
    b_flipped = (b[0], b[1][:, ::-1].copy())
    V, F = _union(a, b_flipped)
    with pytest.raises(MeshInputError, match="(?s)component 1 of 2.*inside-out"):
        build_cages(V, F, face_counts=[60], method="decimate", components="separate")
    out = build_cages(V, F, face_counts=[60], method="decimate", components="separate", repair=True)
    assert [len(layers[1][1]) for layers in out] == [60, 60]
