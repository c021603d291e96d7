"""Face counts of the cage layers.

A coarse level's tet mesh is built at an edge length proportional to its surface's edge length
``h``. Surface faces scale like ``h^-2`` and tets like ``h^-3``, so doubling ``h`` (the textbook
multigrid coarsening) divides the face count by ``ratio = 4`` and the tet count by 8.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .errors import LevelsError

__all__ = ["MIN_FACES", "check_face_counts", "default_face_counts", "fitting_levels"]

#: smallest cage of the default face counts: below ~100 faces a cage no longer follows the shape (and its
#: tet mesh has a few dozen tets, too few to be a useful coarse level)
MIN_FACES = 100


def _even(x: float) -> int:
    # closed triangle meshes have an even number of faces (3F = 2E)
    return int(2 * max(2, round(x / 2)))


def _check_levels_args(n_faces: int, levels: int, ratio: float) -> None:
    if isinstance(levels, (bool, np.bool_)) or int(levels) != levels or levels < 1:
        raise LevelsError(f"levels must be a positive integer (input included), got {levels!r}")
    if not ratio > 1:
        raise LevelsError(f"ratio must be > 1, got {ratio!r}")
    if n_faces < 4:
        raise LevelsError(f"the input has {n_faces} faces; a closed surface needs at least 4")


def fitting_levels(n_faces: int, levels: int, ratio: float = 4.0, min_faces: int = MIN_FACES) -> int:
    """How many of ``levels`` layers (input included) :func:`default_face_counts` can build from ``n_faces``.

    Parameters
    ----------
    n_faces : int
        Faces of the input surface (layer 0).
    levels : int
        Layers wanted, input included (a ceiling).
    ratio, min_faces
        As in :func:`default_face_counts`.

    Returns
    -------
    int
        The largest ``L <= levels`` whose coarsest cage keeps ``>= min_faces`` faces (1: not even one
        cage fits).

    Raises
    ------
    LevelsError
        Bad ``levels``, ``ratio`` or ``n_faces`` (as :func:`default_face_counts`).

    Examples
    --------
    >>> fitting_levels(670, 3), fitting_levels(20000, 3), fitting_levels(300, 3)
    (2, 3, 1)
    """
    _check_levels_args(n_faces, levels, ratio)
    fit = 1
    while fit < int(levels) and _even(n_faces / ratio**fit) >= min_faces:
        fit += 1
    return fit


def default_face_counts(n_faces: int, levels: int, ratio: float = 4.0, min_faces: int = MIN_FACES) -> list[int]:
    """Target face counts of the cages for a hierarchy of ``levels`` layers (input included).

    Parameters
    ----------
    n_faces : int
        Faces of the input surface (layer 0).
    levels : int
        Total number of layers, input included (``levels = 1``: no cage).
    ratio : float
        Face-count ratio between consecutive layers (> 1); 4 halves the edge length, which gives
        ~8x fewer tets per level.
    min_faces : int
        Smallest allowed cage.

    Returns
    -------
    list of int
        ``levels - 1`` even face counts, finest first: ``n_faces / ratio**k`` for ``k = 1, 2, ...``.

    Raises
    ------
    LevelsError
        If ``levels < 1``, ``ratio <= 1``, or the coarsest layer would have fewer than ``min_faces``
        faces (the message says how many levels fit, or, when none does, that ``face_counts`` can ask for
        smaller cages).

    Examples
    --------
    >>> default_face_counts(20000, 3)
    [5000, 1250]
    """
    _check_levels_args(n_faces, levels, ratio)
    counts = [_even(n_faces / ratio**k) for k in range(1, int(levels))]
    if counts and counts[-1] < min_faces:
        fit = fitting_levels(n_faces, levels, ratio, min_faces)
        if fit <= 1:  # "lower levels" cannot help: say what can
            half = _even(n_faces / 2)
            raise LevelsError(
                f"no cage fits a {n_faces}-face input at ratio {ratio:g}: its first cage would have "
                f"{counts[0]} < min_faces={min_faces} faces; smaller cages only when asked for by face_counts"
                + (f" (e.g. [{half}])" if half >= 4 else "")
            )
        raise LevelsError(
            f"cannot build {levels} levels from {n_faces} faces at ratio {ratio:g}: the coarsest cage "
            f"would have {counts[-1]} < min_faces={min_faces} faces; at most {fit} levels fit "
            "(lower levels or ratio, or pass face_counts explicitly)"
        )
    return counts


def check_face_counts(face_counts: Sequence[int], n_faces: int) -> list[int]:
    """Validate explicit cage face counts: integers >= 4, strictly decreasing, below ``n_faces``.

    Returns the counts as a list of int; raises :class:`LevelsError` naming the offending entry.
    """
    out = []
    for k, c in enumerate(face_counts):
        if isinstance(c, (bool, np.bool_)) or int(c) != c:
            raise LevelsError(f"face_counts[{k}] = {c!r} is not an integer")
        c = int(c)
        if c < 4:
            raise LevelsError(f"face_counts[{k}] = {c} < 4: a closed surface needs at least 4 faces")
        prev = n_faces if k == 0 else out[-1]
        if c >= prev:
            raise LevelsError(
                f"face_counts must decrease strictly from the input's {n_faces} faces: "
                f"face_counts[{k}] = {c} >= {prev}"
            )
        out.append(c)
    return out
