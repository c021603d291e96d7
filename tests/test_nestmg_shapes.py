import numpy as np
import pytest
import trimesh

from nestmg import shapes

# (name, genus) of every built-in shape
GENUS = {"sphere": 0, "torus": 1, "genus2": 2, "neck_blobs": 0, "thin_plate": 0, "plate_holes": 3}


@pytest.mark.parametrize("name", sorted(shapes.SHAPES))
def test_shapes_are_closed_manifold_single_piece(name):
    V, F = shapes.SHAPES[name](res=24)
    m = trimesh.Trimesh(V, F, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert len(m.split(only_watertight=False)) == 1
    assert m.volume > 0
    assert m.euler_number == 2 - 2 * GENUS[name]
    assert V.dtype == np.float64 and F.dtype == np.int64


def test_sphere_volume_and_radius():
    V, F = shapes.sphere(res=32)
    r = np.linalg.norm(V, axis=1)
    assert np.abs(r - 1).max() < 2e-3  # vertices projected onto the level set
    vol = trimesh.Trimesh(V, F, process=False).volume
    assert abs(vol - 4 / 3 * np.pi) / (4 / 3 * np.pi) < 0.01


def test_relaxation_improves_triangles():
    f, b = shapes.shape_sdf("torus")
    q = []
    for relax in (0, 5):
        V, F = shapes.mesh_implicit(f, b, res=24, level=0.06, relax=relax)
        a = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
        q.append(a.min() / a.mean())
    assert q[0] < 0.01 and q[1] > 0.1, q  # raw marching cubes has slivers; relaxed triangles do not


def test_nested_isosurfaces_are_nested():
    import cagegen

    S = shapes.nested_isosurfaces("genus2", [0.0, 0.06, 0.2], [40, 24, 14])
    rep = cagegen.verify_nesting(S)
    assert rep.ok, str(rep)
    with pytest.raises(ValueError, match="increasing"):
        shapes.nested_isosurfaces("torus", [0.1, 0.0], [20, 20])
    with pytest.raises(ValueError, match="unknown shape"):
        shapes.shape_sdf("cube")
