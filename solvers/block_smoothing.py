"""Nodal block Gauss–Seidel for vector problems with interleaved unknowns (elasticity: 3 per node).

Unknown ``i`` belongs to block (node) ``i // blocksize``. One sweep visits the blocks in order and
sets ``x_B <- x_B + D_B⁻¹ (b - A x)_B`` with ``D_B`` the diagonal block. Two orderings:

``"multicolor"`` (default)
    The blocks are coloured so that no two blocks of one colour are coupled (pyamg's compiled
    largest-degree-first colouring of the block graph, seeded: deterministic). Blocks of one colour then
    update at once: a sweep is one sparse product per colour on that colour's rows, numpy-vectorised.
    A symmetric sweep runs the colours forward then backward (the adjoint pair). Measured on a Kuhn
    cube (200k unknowns): 1.5–2 SpMV per sweep, against ~1 for point Gauss–Seidel.
``"natural"``
    The node order, through pyamg's compiled ``block_gauss_seidel`` kernel (a generic small-gemm loop,
    about 2 SpMV per sweep on 3x3 blocks; kept for comparison).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from pyamg.relaxation import relaxation

from .errors import SolverInputError
from .smoothing import Smoother, _check_iterations

__all__ = ["setup_block_gauss_seidel"]


def _diagonal_blocks(Ab: sp.bsr_matrix, bs: int) -> np.ndarray:
    """Inverses of the diagonal blocks (m, bs, bs) of a BSR matrix; each must be positive definite."""
    m = Ab.shape[0] // bs
    D = np.zeros((m, bs, bs))
    rows = np.repeat(np.arange(m), np.diff(Ab.indptr))
    on = Ab.indices == rows
    D[rows[on]] = Ab.data[on]
    if not np.all(np.linalg.eigvalsh(0.5 * (D + np.swapaxes(D, 1, 2)))[:, 0] > 0):
        raise SolverInputError("block Gauss-Seidel needs positive definite diagonal blocks")
    return np.linalg.inv(D)


class _MulticolorSweeps:
    """Set-up data of the multicolour sweeps.

    The update of all blocks of colour ``c`` at once is ``x_c <- x_c + D_c⁻¹ (b_c - A_c x) =
    x_c + (D⁻¹b)_c - (D_c⁻¹ A_c) x`` (exact: blocks of one colour are not coupled). ``D⁻¹ A`` is formed
    once (one compiled BSR product with the block-diagonal ``D⁻¹``: ``D_a⁻¹ A_ab``, same sparsity) and
    split into one BSR matrix of rows per colour: a sweep costs one SpMV, the block-diagonal product
    ``D⁻¹ b`` and a gather/scatter of ``x`` per colour. The columns keep the caller's numbering, so reads
    of ``x`` keep the mesh ordering's locality (measured: permuting the system so that colours are
    contiguous made the sweep slower).
    """

    def __init__(self, Ab: sp.bsr_matrix, bs: int, Dinv: np.ndarray):
        from pyamg import amg_core

        # largest-degree-first colouring (pyamg's compiled kernel) with seeded tie-break weights: the same
        # colours for every smoother built on this operator, so a forward pre-smoother and the backward
        # post-smoother built separately are an adjoint pair (the cycle stays symmetric for CG)
        m = len(Dinv)
        color = np.empty(m, dtype=Ab.indptr.dtype)
        amg_core.vertex_coloring_LDF(m, Ab.indptr, Ab.indices, color, np.random.default_rng(0).random(m))
        color = color.astype(np.int64)
        Db = sp.bsr_matrix((Dinv, np.arange(m), np.arange(m + 1)), shape=Ab.shape)
        DA = sp.bsr_matrix(Db @ Ab)  # D_a⁻¹ A_ab for every stored block (a, b): scipy's compiled BSR product
        counts = np.diff(DA.indptr)
        rows = np.repeat(np.arange(m), counts)
        by_color = np.argsort(color[rows], kind="stable")  # block rows of each colour, in their order
        ends = np.cumsum(np.bincount(color[rows], minlength=color.max() + 1))
        self.Dinv = Db.tocsr()
        self.dofs, self.rows = [], []
        start = 0
        for c, end in enumerate(ends):
            R = np.flatnonzero(color == c)
            sel = by_color[start:end]
            indptr = np.zeros(len(R) + 1, dtype=np.int64)
            np.cumsum(counts[R], out=indptr[1:])
            shape = (bs * len(R), Ab.shape[1])
            rows_c = sp.bsr_matrix((DA.data[sel], DA.indices[sel], indptr), shape=shape)
            # 1x1 blocks: CSR (scipy's BSR product with many right-hand sides is a slow generic loop there)
            self.rows.append(rows_c.tocsr() if bs == 1 else rows_c)
            self.dofs.append((bs * R[:, None] + np.arange(bs)).ravel())
            start = end
        self.colors = len(self.dofs)

    def sweep(self, x: np.ndarray, b: np.ndarray, backward: bool) -> None:
        """One forward or backward sweep over the colours, ``x`` updated in place."""
        db = self.Dinv @ b
        seq = range(self.colors - 1, -1, -1) if backward else range(self.colors)
        for c in seq:
            d = self.dofs[c]
            x[d] += db[d] - self.rows[c] @ x


def setup_block_gauss_seidel(A: sp.csr_matrix, blocksize: int = 3, sweep: str = "forward",
                             iterations: int = 1, ordering: str = "multicolor") -> Smoother:
    """Nodal block Gauss–Seidel smoother (see the module docstring).

    Parameters
    ----------
    A : (n, n) csr_matrix
        ``n`` divisible by ``blocksize``; every diagonal block symmetric positive definite.
    blocksize : int
        Unknowns per node (3 for elasticity).
    sweep : {"forward", "backward", "symmetric"}
    iterations : int
    ordering : {"multicolor", "natural"}

    Returns
    -------
    Smoother
        Named ``"block_gauss_seidel"``; ``params`` has the sweep, iterations, block size, ordering and
        number of colours.
    """
    if sweep not in ("forward", "backward", "symmetric"):
        raise SolverInputError(f"sweep must be 'forward', 'backward' or 'symmetric', got {sweep!r}")
    if ordering not in ("multicolor", "natural"):
        raise SolverInputError(f"ordering must be 'multicolor' or 'natural', got {ordering!r}")
    it = _check_iterations(iterations)
    bs = int(blocksize)
    if bs < 1 or A.shape[0] % bs:
        raise SolverInputError(
            f"block Gauss-Seidel: {A.shape[0]} unknowns are not a multiple of blocksize={bs}")
    A = sp.csr_matrix(A)
    Ab = A.tobsr(blocksize=(bs, bs))
    Dinv = _diagonal_blocks(Ab, bs)
    params = {"sweep": sweep, "iterations": it, "omega": 1.0, "blocksize": bs, "ordering": ordering}
    if ordering == "multicolor":
        mc = _MulticolorSweeps(Ab, bs, Dinv)
        params["colors"] = mc.colors
        dirs = {"forward": (False,), "backward": (True,), "symmetric": (False, True)}[sweep]

        def apply(A, x, b):
            for _ in range(it):
                for backward in dirs:
                    mc.sweep(x, b, backward)
    else:
        def apply(A, x, b):
            if it:
                relaxation.block_gauss_seidel(Ab, x, b, iterations=it, sweep=sweep, blocksize=bs, Dinv=Dinv)

    # omega: no over-relaxation (kept so that the adjoint test of forward/backward pairs reads as point GS's)
    return Smoother("block_gauss_seidel", apply, it * (2.0 if sweep == "symmetric" else 1.0), params)
