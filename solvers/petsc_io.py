"""``.npz`` exchange of a hierarchy for ``mpirun`` jobs. Split from :mod:`solvers.petsc`."""

from __future__ import annotations

import re

import numpy as np
import scipy.sparse as sp

from .errors import SolverInputError
from .petsc_common import (
    _check_hierarchy,
    _check_vector,
)


# ---------------------------------------------------------------------------------- .npz exchange
def save_operators(path, A, Ps, *, coarse=None, b=None, **arrays) -> None:
    """Write a multigrid system (``A``, ``Ps``, given coarse operators, ``b``) to one ``.npz`` file.

    Call it on one rank only (e.g. ``if rank == 0``); every rank reads the file with
    :func:`load_operators`. (Not to be confused with :func:`nestmg.save_hierarchy`, which saves the
    geometry: surfaces, tet layers and prolongations.)

    Parameters
    ----------
    path : str or path-like
    A : (n_0, n_0) sparse
    Ps : list of sparse, ``Ps[k]`` of shape (n_k, n_{k+1})
    coarse : list of sparse, optional
        Given coarse operators ``[A_1, ..., A_L]`` (None: Galerkin).
    b : (n_0,) array_like, optional
    **arrays : extra numpy arrays stored under their names (e.g. the fine node positions).
    """
    A, Ps, coarse = _check_hierarchy(A, Ps, coarse)
    out: dict[str, np.ndarray] = {"n_levels": np.array(len(Ps) + 1)}

    def put(tag, M):
        out[f"{tag}_data"], out[f"{tag}_indices"], out[f"{tag}_indptr"] = M.data, M.indices, M.indptr
        out[f"{tag}_shape"] = np.array(M.shape)

    put("A", A)
    for k, P in enumerate(Ps):
        put(f"P{k}", P)
    if coarse is not None:
        for k, Ac in enumerate(coarse):
            put(f"C{k}", Ac)
    if b is not None:
        out["b"] = _check_vector(b, A.shape[0])
    for name, arr in arrays.items():
        if name in ("A", "Ps", "coarse", "b", "n_levels") or re.fullmatch(r"(A|P\d+|C\d+)_\w+", name):
            raise SolverInputError(f"extra array name {name!r} clashes with the system's own keys")
        out[name] = np.asarray(arr)
    np.savez(path, **out)


def load_operators(path) -> dict:
    """Read a file written by :func:`save_operators` (every rank may call it).

    Returns
    -------
    dict
        ``A`` (csr), ``Ps`` (list of csr), ``coarse`` (list or None), ``b`` (array or None), and any
        extra arrays under their names.
    """
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}

    def get(tag):
        return sp.csr_matrix((data.pop(f"{tag}_data"), data.pop(f"{tag}_indices"), data.pop(f"{tag}_indptr")),
                             shape=tuple(data.pop(f"{tag}_shape")))

    L = int(data.pop("n_levels"))
    out = {"A": get("A"), "Ps": [get(f"P{k}") for k in range(L - 1)]}
    out["coarse"] = [get(f"C{k}") for k in range(L - 1)] if "C0_data" in data else None
    out["b"] = data.pop("b", None)
    out.update(data)
    return out
