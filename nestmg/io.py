"""Mesh input/output: read OBJ/OFF/PLY/STL, normalise, write atomically.

Reading keeps the file's vertices as they are (no silent merging): OBJ/OFF/PLY go through libigl's
reader, which, unlike trimesh with ``process=False``, does not split vertices along texture seams
(trimesh opens ``spot.obj`` that way). STL stores a triangle soup by design, so its exactly
coincident corners are merged (documented repair). Other formats go through trimesh.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from cagegen.errors import MeshInputError

from .cache import atomic_write_bytes, publish

__all__ = [
    "TET_FORMATS", "denormalize", "json_default", "load_mesh", "load_tet_mesh", "normalize", "read_cells",
    "save_mesh", "save_tet_mesh",
]

_IGL_FORMATS = {".obj", ".off", ".ply"}
#: Volume-mesh formats read through meshio (gmsh, Medit, VTK XML and legacy).
TET_FORMATS = (".msh", ".mesh", ".vtu", ".vtk")


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh.

    Parameters
    ----------
    path : str or PathLike
        OBJ, OFF, PLY, STL (or anything trimesh reads).

    Returns
    -------
    V : (n,3) float64 array
    F : (m,3) int64 array

    Raises
    ------
    MeshInputError
        Missing or unreadable file, no triangles, or non-triangle faces.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshInputError(f"mesh file not found: {path}")
    ext = path.suffix.lower()
    try:
        if ext in _IGL_FORMATS:
            import igl

            V, F = igl.read_triangle_mesh(str(path))
        else:
            import trimesh

            m = trimesh.load(str(path), force="mesh", process=(ext == ".stl"))
            V, F = m.vertices, m.faces
    except MeshInputError:
        raise
    except Exception as exc:
        raise MeshInputError(f"could not read {path.name}: {exc}") from exc
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise MeshInputError(f"{path.name}: no triangles read (faces array of shape {F.shape})")
    return V, F


def normalize(V: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre the bounding box at the origin and scale its diagonal to 1.

    Parameters
    ----------
    V : (n,3) float array

    Returns
    -------
    Vn : (n,3) float64 array
        New array (``V`` is not modified).
    center : (3,) float array
    scale : float
        ``Vn = (V - center) / scale``; undo with :func:`denormalize`.
    """
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshInputError(f"vertices must be a non-empty (n,3) array, got shape {V.shape}")
    if not np.isfinite(V).all():
        raise MeshInputError(f"{int((~np.isfinite(V)).any(axis=1).sum())} vertices have NaN/inf coordinates")
    from cagegen import bbox_diagonal
    from cagegen import normalize as unit_box

    scale = bbox_diagonal(V)  # overflow-safe
    if not (np.isfinite(scale) and scale > 0):
        raise MeshInputError(f"bounding-box diagonal {scale} (all vertices coincide, or overflow)")
    return unit_box(V, scale)


def denormalize(Vn: np.ndarray, center: np.ndarray, scale: float) -> np.ndarray:
    """Inverse of :func:`normalize`: ``Vn * scale + center``."""
    return np.asarray(Vn) * scale + np.asarray(center)


def save_mesh(path: str | os.PathLike, V: np.ndarray, F: np.ndarray) -> None:
    """Write a triangle mesh (format from the extension) atomically (temp file + rename).

    OBJ and OFF are written by libigl with 15 significant digits (trimesh wrote 8 decimals), PLY as
    binary doubles; trimesh writes the other formats (its import was 0.4 CPU s of ``nestmg cages``).
    """
    path = Path(path)
    if path.suffix.lower() in _IGL_FORMATS:
        _save_igl(path, np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64))
        return
    import trimesh

    m = trimesh.Trimesh(np.asarray(V), np.asarray(F), process=False)
    data = m.export(file_type=path.suffix.lstrip(".").lower() or "obj")
    atomic_write_bytes(path, data.encode() if isinstance(data, str) else data)


def _save_igl(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    """:func:`igl.write_triangle_mesh` to a temporary file of the same folder and extension, then a rename."""
    import igl

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        binary = path.suffix.lower() == ".ply"  # igl's ASCII PLY keeps 6 digits
        igl.write_triangle_mesh(tmp, V, F, igl.FileEncoding.Binary if binary else igl.FileEncoding.Ascii)
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_cells(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a volume-mesh file through meshio: nodes, linear tets and triangles, as stored.

    Parameters
    ----------
    path : str or PathLike
        ``.msh`` (gmsh), ``.mesh`` (Medit), ``.vtu``, ``.vtk`` (see :data:`TET_FORMATS`).

    Returns
    -------
    V : (n,3) float64 array
        Every node of the file, in file order (none dropped or merged).
    T : (t,4) int64 array or None
        All ``tetra`` blocks, in file order (None when the file has none).
    F : (m,3) int64 array or None
        All ``triangle`` blocks (None when none).

    Raises
    ------
    MeshInputError
        Missing or unreadable file, or second-order tets (``tetra10``: not a P1 fine level).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshInputError(f"mesh file not found: {path}")
    import contextlib
    import io

    import meshio

    said = io.StringIO()
    try:  # meshio prints its complaints and, for a file no reader takes, calls sys.exit(1)
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(str(path))
    except SystemExit:
        why = " ".join(said.getvalue().split()).removeprefix("Error: ") or "no meshio reader takes it"
        raise MeshInputError(f"could not read {path.name}: {why}") from None
    except Exception as exc:
        raise MeshInputError(f"could not read {path.name}: {exc}") from exc
    V = np.ascontiguousarray(m.points, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshInputError(f"{path.name}: nodes must be 3D, got an array of shape {V.shape}")
    blocks = {c.type: [] for c in m.cells}
    for c in m.cells:
        blocks[c.type].append(np.asarray(c.data, dtype=np.int64))
    if "tetra10" in blocks and "tetra" not in blocks:
        raise MeshInputError(f"{path.name}: second-order tets (tetra10); give the P1 mesh of their vertices "
                             "(nestmg.usermesh.p1_to_p2_prolongation adds a P2 level on top)")
    T = np.concatenate(blocks["tetra"]) if "tetra" in blocks else None
    F = np.concatenate(blocks["triangle"]) if "triangle" in blocks else None
    return V, T, F


def load_tet_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a linear tet mesh (``.msh``, ``.mesh``, ``.vtu``, ``.vtk``) through meshio.

    Nodes and tets are returned exactly as stored (same order; the caller's fine level for
    :func:`nestmg.hierarchy_from_tets`). Lower-dimensional cells (boundary triangles, lines) are ignored.

    Returns
    -------
    V : (n,3) float64 array
    T : (t,4) int64 array

    Raises
    ------
    MeshInputError
        Unreadable file, or no tetrahedra in it.
    """
    V, T, F = read_cells(path)
    if T is None:
        what = f"{len(F)} triangles (a surface)" if F is not None else "no tets or triangles"
        raise MeshInputError(f"{Path(path).name}: no tetrahedra in the file, it holds {what}")
    return V, T


def save_tet_mesh(path: str | os.PathLike, V: np.ndarray, T: np.ndarray, point_data: dict | None = None,
                  cell_data: dict | None = None) -> None:
    """Write a tet mesh (and point / cell fields) through meshio, atomically (temp file + rename).

    The pair of :func:`load_tet_mesh`: the format comes from the extension (``.vtu``, ``.msh``,
    ``.mesh``, ``.vtk``).

    Parameters
    ----------
    path : path ending in ``.vtu`` (or another meshio tet format)
    V : (n,3) float array
    T : (t,4) int array, or (t,10) for quadratic tets (meshio ``tetra10``: vertices, then the edge nodes
        ``01, 12, 02, 03, 13, 23``; :attr:`nestmg.curved.CurvedMesh.T10`), which ParaView draws curved
    point_data : dict of name -> (n,) or (n,c) array, optional
    cell_data : dict of name -> (t,) array, optional
    """
    import tempfile

    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T = np.asarray(T, dtype=np.int64)
    mesh = meshio.Mesh(np.asarray(V, dtype=np.float64), [("tetra10" if T.shape[1] == 10 else "tetra", T)],
                       point_data={k: np.asarray(v) for k, v in (point_data or {}).items()},
                       cell_data={k: [np.asarray(v)] for k, v in (cell_data or {}).items()})
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        meshio.write(tmp, mesh)
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def json_default(o):
    """``json.dumps(..., default=json_default)``: numpy scalars and arrays as Python numbers and lists."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
