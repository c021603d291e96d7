"""cagegen.sizes: default face counts (4x per level) and validation of explicit counts."""

from __future__ import annotations

import pytest

from cagegen.errors import LevelsError
from cagegen.sizes import check_face_counts, default_face_counts


def test_default_counts_quarter_per_level():
    assert default_face_counts(20000, 3) == [5000, 1250]
    assert default_face_counts(20000, 1) == []
    c = default_face_counts(100000, 5)
    assert c == [25000, 6250, 1562, 390]
    assert all(x % 2 == 0 for x in c)  # closed triangle meshes have an even face count
    assert default_face_counts(9000, 3, ratio=3) == [3000, 1000]


def test_too_many_levels_says_how_many_fit():
    with pytest.raises(LevelsError, match=r"at most 3 levels fit"):
        default_face_counts(5000, 5)  # 1250, 312, 78 < 100
    with pytest.raises(LevelsError, match="min_faces"):
        default_face_counts(5000, 3, min_faces=1000)
    assert default_face_counts(5000, 3) == [1250, 312]


def test_bad_arguments():
    for bad in (0, -1, 2.5):
        with pytest.raises(LevelsError, match="levels"):
            default_face_counts(1000, bad)
    with pytest.raises(LevelsError, match="ratio"):
        default_face_counts(1000, 2, ratio=1.0)
    with pytest.raises(LevelsError, match="at least 4"):
        default_face_counts(2, 2)


def test_check_face_counts():
    assert check_face_counts([500, 100], 2000) == [500, 100]
    with pytest.raises(LevelsError, match=r"face_counts\[1\] = 600 >= 500"):
        check_face_counts([500, 600], 2000)
    with pytest.raises(LevelsError, match=r"face_counts\[0\] = 2000 >= 2000"):
        check_face_counts([2000], 2000)
    with pytest.raises(LevelsError, match="not an integer"):
        check_face_counts([500.5], 2000)
    with pytest.raises(LevelsError, match="at least 4"):
        check_face_counts([2], 2000)
