"""One BLAS thread while a multigrid cycle or solve runs.

The cycles' BLAS work is short: dot products and norms of level vectors and the coarsest level's dense
triangular solves (a few thousand unknowns). OpenBLAS's threads gain nothing there and cost a lot when they
spin beside other work: on a 1M-tet Neumann problem (2 cores) the MG-PCG solve took 0.217 s with two BLAS
threads against 0.185 s with one on an idle machine, and 0.569 against 0.272 s beside a BLAS job
(``benchmarks/results/user_mesh/blas_threads_ff45427.json``).
The limit is set and restored around each solve and each preconditioner application (about 10 us), and
around the set-up (:class:`solvers.MultigridSolver`'s construction and its deferred probe): the deflation
probe's Lanczos steps are tall-skinny products (n x 24) beside cycles: lucy.ply's Neumann set-up with the
probe took 10.8 s with two BLAS threads against 4.7 s with one beside two other processes, and as long either
way on an idle machine (``benchmarks/results/setup_cost/setup_blas_threads_{loaded,idle}.json``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

from threadpoolctl import ThreadpoolController

F = TypeVar("F", bound=Callable)

_controller: ThreadpoolController | None = None


def one_blas_thread():
    """Context manager: the loaded BLAS libraries limited to one thread, the caller's limits restored after."""
    global _controller
    if _controller is None:  # lazily: the libraries loaded by then (numpy's, scipy's) are the ones limited
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


def under_one_blas_thread(fn: F) -> F:
    """Decorator: ``fn`` runs under :func:`one_blas_thread`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
