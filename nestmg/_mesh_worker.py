"""The external tet meshers (TetGen, fTetWild) behind a process boundary, for :mod:`nestmg.tetmesh`.

Run as a script (``python _mesh_worker.py FD``) this serves mesh jobs on the socket ``FD`` until the
socket closes. It imports only numpy and the mesher a job asks for (never the nestmg package), so it
starts in a fraction of a second, and :func:`nestmg.tetmesh.tetrahedralize` can kill it when a job runs
past its time limit (TetGen's mesh improvement can loop forever on some inputs) or see it die (a
segfault in the C++ code) without losing the calling process. Imported, it gives the same
:func:`run_job` to the in-process path (``time_limit=None``).

Protocol (pickled tuples over a :class:`multiprocessing.connection.Connection`): the parent first sends
``("path", sys_path)``, then jobs ``(mesher, V, F, opts)``; each job is answered by ``("ok", (Vt, T))``
or ``("error", type_name, message)``.
"""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

__all__ = ["run_job"]


def _tetgen(V: np.ndarray, F: np.ndarray, opts: dict) -> tuple[np.ndarray, np.ndarray]:
    import numpy as np
    import tetgen

    Vt, T, _, _ = tetgen.TetGen(V, F.astype(np.int32)).tetrahedralize(**opts)
    return np.asarray(Vt, dtype=np.float64), np.asarray(T, dtype=np.int64)


def _tetwild(V: np.ndarray, F: np.ndarray, opts: dict) -> tuple[np.ndarray, np.ndarray]:
    import numpy as np
    import pytetwild

    Vt, T = pytetwild.tetrahedralize(V, F.astype(np.int32), **opts)
    return np.asarray(Vt, dtype=np.float64), np.asarray(T, dtype=np.int64)


_JOBS = {"tetgen": _tetgen, "tetwild": _tetwild}


def run_job(mesher: str, V: np.ndarray, F: np.ndarray, opts: dict) -> tuple[np.ndarray, np.ndarray]:
    """Run one mesher call: ``(nodes, tets)`` of the surface ``(V, F)`` with the mesher's own keywords.

    fTetWild writes ``__tracked_surface.stl`` into the working directory: the worker runs in a
    temporary one; the in-process caller wraps this call in :func:`cagegen.in_temp_dir`.
    """
    return _JOBS[mesher](V, F, opts)


def _die_with_parent() -> None:
    """Linux: have the kernel kill this worker when its parent dies (e.g. a CI timeout's os._exit)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - no prctl: the closed socket still ends the loop
        return


def _serve(fd: int) -> None:
    from multiprocessing.connection import Connection

    conn = Connection(fd)
    while True:
        try:
            msg = conn.recv()
        except EOFError:  # the parent closed the socket (or died)
            return
        if msg[0] == "path":  # the parent's import path (absolute), so the meshers import as there
            sys.path[:] = msg[1]
            continue
        mesher, V, F, opts = msg
        try:
            reply = ("ok", run_job(mesher, V, F, opts))
        except Exception as exc:  # noqa: BLE001 - any mesher error goes back to the parent, which words it
            reply = ("error", type(exc).__name__, str(exc))
        try:
            conn.send(reply)
        except (BrokenPipeError, ConnectionResetError, EOFError):
            return


if __name__ == "__main__":
    # sys.path[0] is this file's folder (nestmg/): its modules must not shadow top-level names (numpy
    # is imported only after this, by the first job or by unpickling the first array)
    sys.path.pop(0)
    if "--die-with-parent" in sys.argv:
        _die_with_parent()
        if os.getppid() == 1:  # the parent died before prctl
            sys.exit(0)
    _serve(int(sys.argv[1]))
