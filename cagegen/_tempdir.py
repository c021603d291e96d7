"""A fresh temporary working directory: fTetWild writes a tracking file (``__tracked_surface.stl``)
into the current directory, which must not be the user's."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

__all__ = ["in_temp_dir"]


@contextlib.contextmanager
def in_temp_dir(prefix: str = "nestmg-tetwild-") -> Iterator[str]:
    """Run the body in a fresh temporary working directory (restored and removed afterwards).

    Parameters
    ----------
    prefix : str
        Prefix of the directory's name.

    Yields
    ------
    str
        The directory's path (the current working directory inside the ``with`` block).

    Examples
    --------
    >>> import os
    >>> from cagegen import in_temp_dir
    >>> before = os.getcwd()
    >>> with in_temp_dir() as d:
    ...     os.getcwd() == os.path.realpath(d)
    True
    >>> os.getcwd() == before, os.path.exists(d)
    (True, False)
    """
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix=prefix) as d:
        os.chdir(d)
        try:
            yield d
        finally:
            os.chdir(old)
