"""Coarse levels read piecewise: the first coarse tet mesh cropped to a box, rows of the coarse prolongations.

:meth:`solvers.petsc.PetscMultigrid.from_distributed` needs, on each MPI rank, only the coarse tets that can
contain the rank's own fine nodes and only the rows of ``P_1, P_2, ...`` that the rank owns. A
:class:`CoarseLevels` hands out exactly those pieces, either from arrays the caller already holds or from
an ``.npz`` file written by :func:`save_coarse_levels`, which it *streams* in chunks of rows
(:data:`CHUNK_ROWS`): no rank ever materialises the global mesh or a global coarse matrix.

Cropping is exact: a tet is kept iff its bounding box meets the (slightly enlarged) box of the rank's
points, decided from per-node outcodes (one byte per coarse node: the Cohen–Sutherland test, the AND of a
tet's four outcodes is zero iff the boxes meet). Every tet that contains one of the points is kept, and
every face of the crop that is not a face of the whole mesh lies outside the enlarged box, so point
location and the on-boundary test (:func:`solvers.locate.locate_in_tets`) decide each point as on the
whole mesh.

Pure numpy and scipy; no MPI here.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .errors import SolverInputError

__all__ = ["CHUNK_ROWS", "CoarseLevels", "save_coarse_levels"]

CHUNK_ROWS = 1 << 18  # rows per streamed chunk (tets, nodes, CSR entries)


def save_coarse_levels(path, V1, T1, coarse_Ps=()) -> None:
    """Write the first coarse tet mesh and the coarse prolongations to one uncompressed ``.npz``.

    Call it on one rank; every rank then passes ``path`` to
    :meth:`solvers.petsc.PetscMultigrid.from_distributed` and reads only its own pieces.

    Parameters
    ----------
    path : str or path-like
    V1 : (n_1,3) float
        Nodes of the first coarse tet mesh.
    T1 : (t_1,4) int
        Its tets.
    coarse_Ps : list of sparse
        ``coarse_Ps[k-1]`` of shape ``(n_k, n_{k+1})``, k >= 1 (may be empty).
    """
    src = CoarseLevels.from_arrays(V1, T1, coarse_Ps)
    out = {"V1": src._V, "T1": src._T, "n_coarse": np.array(len(src._Ps))}
    for k, P in enumerate(src._Ps):
        out[f"P{k}_indptr"], out[f"P{k}_indices"], out[f"P{k}_data"] = P.indptr, P.indices, P.data
        out[f"P{k}_shape"] = np.array(P.shape)
    np.savez(path, **out)


def _outcodes(V: np.ndarray, box: np.ndarray) -> np.ndarray:
    """6-bit outcode of every point of ``V`` (n,3) against ``box`` = (lo, hi): bit 2a below, 2a+1 above."""
    code = np.zeros(len(V), dtype=np.uint8)
    for a in range(3):
        code |= (V[:, a] < box[0][a]).astype(np.uint8) << (2 * a)
        code |= (V[:, a] > box[1][a]).astype(np.uint8) << (2 * a + 1)
    return code


class CoarseLevels:
    """The coarse levels of a distributed solve, handed out piece by piece.

    Build with :meth:`from_arrays` (arrays already in memory, e.g. identical on every rank) or
    :meth:`from_file` (an ``.npz`` of :func:`save_coarse_levels`, streamed). Attributes: ``n_nodes``
    (n_1), ``n_tets`` (t_1), ``shapes`` (the prolongations' shapes, level 1 first).
    """

    def __init__(self):
        self._V = self._T = self._path = None
        self._Ps: list = []
        self.shapes: list[tuple[int, int]] = []
        self.n_nodes = self.n_tets = 0

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(cls, V1, T1, coarse_Ps=()) -> CoarseLevels:
        """From in-memory arrays (validated: shapes, finite nodes, tets indexing the nodes, P chain).

        Parameters
        ----------
        V1 : (n_1,3) float
        T1 : (t_1,4) int
        coarse_Ps : list of sparse, ``coarse_Ps[k-1]`` of shape ``(n_k, n_{k+1})``
        """
        self = cls()
        V = np.asarray(V1, dtype=np.float64)
        T = np.asarray(T1)
        if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0 or not np.isfinite(V).all():
            raise SolverInputError(f"coarse mesh nodes must be a finite (n_1,3) array, got shape {V.shape}")
        if T.ndim != 2 or T.shape[1] != 4 or len(T) == 0 or not np.issubdtype(T.dtype, np.integer):
            raise SolverInputError(f"coarse mesh tets must be a non-empty (t_1,4) int array, got {T.shape} "
                                   f"{T.dtype}")
        if T.min() < 0 or T.max() >= len(V):
            raise SolverInputError(f"coarse mesh tets index nodes outside the {len(V)} coarse nodes")
        self._V, self._T = np.ascontiguousarray(V), np.ascontiguousarray(T, dtype=np.int64)
        for k, P in enumerate(coarse_Ps):
            if not sp.issparse(P):
                raise SolverInputError(f"coarse_Ps[{k}] must be a scipy sparse matrix, got "
                                       f"{type(P).__name__}")
            self._Ps.append(sp.csr_matrix(P, dtype=np.float64))
        self._set_shapes(len(V), len(T), [P.shape for P in self._Ps])
        return self

    @classmethod
    def from_file(cls, path) -> CoarseLevels:
        """From an ``.npz`` written by :func:`save_coarse_levels`; reads only the array headers now.

        Parameters
        ----------
        path : str or path-like
            Readable by every rank that uses it (a shared file system under MPI).
        """
        self = cls()
        self._path = Path(path)
        if not self._path.is_file():
            raise SolverInputError(f"coarse levels file {str(path)!r} does not exist")
        try:
            with zipfile.ZipFile(self._path) as z:
                names = set(z.namelist())
        except zipfile.BadZipFile:
            raise SolverInputError(f"{str(path)!r} is not an .npz file (save_coarse_levels writes one)") \
                from None
        need = {"V1.npy", "T1.npy", "n_coarse.npy"}
        if not need <= names:
            raise SolverInputError(f"{str(path)!r} lacks {sorted(need - names)}: not a save_coarse_levels "
                                   "file")
        nv = self._header("V1")[0]
        nt = self._header("T1")[0]
        n_coarse = int(next(self._chunks("n_coarse"))[0])
        shapes = [tuple(int(s) for s in next(self._chunks(f"P{k}_shape"))) for k in range(n_coarse)]
        self._set_shapes(nv, nt, shapes)
        return self

    def _set_shapes(self, nv: int, nt: int, shapes: list) -> None:
        rows = nv
        for k, shape in enumerate(shapes):
            if shape[0] != rows or not 0 < shape[1] < shape[0]:
                raise SolverInputError(
                    f"coarse_Ps[{k}] has shape {tuple(shape)}; expected ({rows}, n) with 0 < n < {rows}")
            rows = shape[1]
        self.n_nodes, self.n_tets, self.shapes = int(nv), int(nt), [tuple(s) for s in shapes]

    # ------------------------------------------------------------------------------ streaming
    def _header(self, name: str) -> tuple:
        with zipfile.ZipFile(self._path) as z, z.open(f"{name}.npy") as f:
            shape, _, _ = _read_header(f)
        return shape

    def _chunks(self, name: str):
        """Yield consecutive blocks of :data:`CHUNK_ROWS` rows of array ``name`` (C order) from the file."""
        rows = CHUNK_ROWS
        with zipfile.ZipFile(self._path) as z, z.open(f"{name}.npy") as f:
            shape, fortran, dtype = _read_header(f)
            if fortran and len(shape) > 1:
                raise SolverInputError(f"{name} is stored in Fortran order; write it with save_coarse_levels")
            if len(shape) == 0:
                yield np.frombuffer(f.read(dtype.itemsize), dtype=dtype).reshape(1)
                return
            width = int(np.prod(shape[1:], dtype=np.int64))
            left = shape[0]
            while left > 0:
                n = min(rows, left)
                buf = f.read(n * width * dtype.itemsize)
                yield np.frombuffer(buf, dtype=dtype).reshape((n,) + tuple(shape[1:]))
                left -= n

    def _mesh_chunks(self, name: str):
        """``"V1"`` (nodes) or ``"T1"`` (tets), :data:`CHUNK_ROWS` rows at a time, from memory or the file."""
        if self._path is not None:
            yield from self._chunks(name)
            return
        X = self._V if name == "V1" else self._T
        for lo in range(0, len(X), CHUNK_ROWS):
            yield X[lo:lo + CHUNK_ROWS]

    # ------------------------------------------------------------------------------ pieces
    def crop(self, box) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tets whose bounding box meets ``box`` = ``(lo (3,), hi (3,))``, with their nodes.

        Returns
        -------
        V : (m,3) float64
            The nodes the kept tets use.
        T : (s,4) int64
            The kept tets, indexing ``V``.
        gid : (m,) int64
            Global (level-1) index of every row of ``V``, increasing.
        """
        box = np.asarray(box, dtype=np.float64).reshape(2, 3)
        code = np.concatenate([_outcodes(np.asarray(c, dtype=np.float64), box) for c in self._mesh_chunks("V1")])
        kept = []
        for T in self._mesh_chunks("T1"):
            T = np.asarray(T, dtype=np.int64)
            c = code[T]
            kept.append(T[(c[:, 0] & c[:, 1] & c[:, 2] & c[:, 3]) == 0])
        del code
        T = np.concatenate(kept) if kept else np.zeros((0, 4), dtype=np.int64)
        gid, T = np.unique(T, return_inverse=True)
        T = T.reshape(-1, 4).astype(np.int64)
        V = np.empty((len(gid), 3))
        lo = 0
        for chunk in self._mesh_chunks("V1"):  # the kept nodes' coordinates, chunk by chunk
            a, b = np.searchsorted(gid, [lo, lo + len(chunk)])
            V[a:b] = chunk[gid[a:b] - lo]
            lo += len(chunk)
        return V, T, gid

    def rows(self, k: int, rows: np.ndarray) -> sp.csr_matrix:
        """Rows ``rows`` of ``P_k`` (level k+1 -> k, k >= 1), with global column indices.

        Parameters
        ----------
        k : int
            Level of the rows, 1 for the first coarse level (``coarse_Ps[k-1]``).
        rows : (m,) int, increasing
            Level-k node indices.

        Returns
        -------
        (m, n_{k+1}) csr_matrix
        """
        rows = np.asarray(rows, dtype=np.int64)
        shape = self.shapes[k - 1]
        if self._path is None:
            return sp.csr_matrix(self._Ps[k - 1][rows])
        tag = f"P{k - 1}"
        starts, ends = np.zeros(len(rows), dtype=np.int64), np.zeros(len(rows), dtype=np.int64)
        lo = 0
        for chunk in self._chunks(f"{tag}_indptr"):  # indptr has n_k + 1 entries: row r spans [p[r], p[r+1])
            hi = lo + len(chunk)
            a, b = np.searchsorted(rows, [lo, hi])
            starts[a:b] = chunk[rows[a:b] - lo]
            a2, b2 = np.searchsorted(rows + 1, [lo, hi])
            ends[a2:b2] = chunk[rows[a2:b2] + 1 - lo]
            lo = hi
        counts = ends - starts
        indptr = np.concatenate([[0], np.cumsum(counts)])
        cols = self._select(f"{tag}_indices", starts, ends, np.int64)
        vals = self._select(f"{tag}_data", starts, ends, np.float64)
        return sp.csr_matrix((vals, cols, indptr), shape=(len(rows), shape[1]))

    def _select(self, name: str, starts: np.ndarray, ends: np.ndarray, dtype) -> np.ndarray:
        """Entries of the 1-D array ``name`` at positions in the disjoint increasing ranges [starts, ends)."""
        keep = ends > starts
        starts, ends = starts[keep], ends[keep]
        out, lo = [], 0
        for chunk in self._chunks(name):
            pos = np.arange(lo, lo + len(chunk))
            j = np.searchsorted(starts, pos, side="right") - 1
            mask = (j >= 0) & (pos < ends[np.maximum(j, 0)]) if len(starts) else np.zeros(len(pos), bool)
            out.append(np.asarray(chunk[mask], dtype=dtype))
            lo += len(chunk)
        return np.concatenate(out) if out else np.zeros(0, dtype=dtype)


def _read_header(f) -> tuple:
    """(shape, fortran_order, dtype) of the ``.npy`` stream ``f``, positioned at its data afterwards."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    return np.lib.format.read_array_header_2_0(f)
