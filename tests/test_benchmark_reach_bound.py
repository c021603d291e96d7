"""The cage-independent reach bound of ``benchmarks/sdf_reach_bound.py`` on shapes with known answers.

docs/sdf.md uses it to say whether an input vertex far from the sdf cage *could* be reached by any cage
with a given clearance; a bound that is too high would turn a method's miss into a false "impossible".
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from sdf_reach_bound import reach_bound  # noqa: E402


def _surface(f, g):
    from skimage.measure import marching_cubes

    V, F, _, _ = marching_cubes(f, 0.0, spacing=(g[1] - g[0],) * 3)
    return V + g[0], F.astype(np.int64)


@pytest.fixture(scope="module")
def grid():
    g = np.linspace(-0.6, 0.9, 121)  # marching-cubes spacing 0.0125
    return g, np.meshgrid(g, g, g, indexing="ij")


def test_open_side_and_slot_between_two_balls(grid):
    g, (X, Y, Z) = grid
    # two balls of radius 0.3 whose surfaces are 0.03 apart at x = 0.3: a slot that closes to 0.03
    f = np.minimum(np.sqrt(X**2 + Y**2 + Z**2) - 0.3, np.sqrt((X - 0.63) ** 2 + Y**2 + Z**2) - 0.3)
    V, F = _surface(f, g)
    i = int(np.argmin(V[:, 0]))                                        # far side: free space right there
    j = int(np.argmin(np.linalg.norm(V - [0.3, 0, 0], axis=1)))        # the slot's narrowest point
    delta = 0.03
    res = reach_bound(V, F, V[[i, j]], [delta], h=0.008, reach=0.15)
    lo_open, lo_slot = res["bounds"][str(delta)]
    # a valid bound never exceeds a distance we can name: the point delta out along the normal
    assert 0.0 < lo_open <= delta + 1e-12

    def slot_distance(d):
        # nearest point of R_d to the slot vertex: on the circle where both offset spheres (radius 0.3 + d)
        # meet, in the mid-plane x = 0.315
        return np.hypot(0.015, np.sqrt((0.3 + d) ** 2 - 0.315**2))

    # the grid bound lies between the true distance at the relaxed clearance delta - 2 m (less m) and the
    # true distance at delta (0.0995); 0.005 of slack for the marching-cubes surface
    m = res["margin"]
    assert slot_distance(delta - 2 * m) - m - 0.005 < lo_slot <= slot_distance(delta) + 0.005
    assert lo_slot > 2 * lo_open


def test_closed_cavity_is_unreachable(grid):
    g, (X, Y, Z) = grid
    r = np.sqrt(X**2 + Y**2 + Z**2)
    V, F = _surface(np.maximum(r - 0.3, 0.08 - r), g)                 # hollow ball: a cavity of radius 0.08
    j = int(np.argmin(np.abs(np.linalg.norm(V, axis=1) - 0.08)))      # on the cavity's wall
    k = int(np.argmax(V[:, 0]))                                        # on the outer wall
    delta, reach = 0.03, 0.12
    res = reach_bound(V, F, V[[j, k]], [delta], h=0.008, reach=reach)
    lo_cavity, lo_outer = res["bounds"][str(delta)]
    # the cavity lies inside the box and is dropped: only the box's outside caps the bound (no cage reaches it)
    assert lo_cavity >= reach - res["margin"] - 1e-12
    assert 0.0 < lo_outer <= delta + 1e-12


def test_clearance_below_the_grid_resolution_is_refused(grid):
    g, (X, Y, Z) = grid
    V, F = _surface(np.sqrt(X**2 + Y**2 + Z**2) - 0.3, g)
    with pytest.raises(ValueError, match="smaller --h"):
        reach_bound(V, F, V[:1], [0.004], h=0.004, reach=0.05)
