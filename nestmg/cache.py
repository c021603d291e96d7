"""On-disk cache for expensive pipeline stages (cages, tet layers), keyed by inputs and options.

Entries live in ``$NESTMG_CACHE`` (default ``~/.cache/nestmg``) as ``<key>.npz`` (arrays) plus
``<key>.json`` (metadata), both written atomically (temp file + rename) so an interrupted run never
leaves a half-written entry behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["arrays_digest", "atomic_write_bytes", "cache_dir", "cache_key", "load_entry", "save_entry"]

CACHE_VERSION = "4"


def cache_dir() -> Path:
    """Directory of the cache (``$NESTMG_CACHE`` or ``~/.cache/nestmg``), created on demand."""
    d = Path(os.environ.get("NESTMG_CACHE", Path.home() / ".cache" / "nestmg"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def cache_key(arrays: list[np.ndarray], options: dict[str, Any]) -> str:
    """SHA-256 key of the given arrays' bytes/shapes/dtypes and a JSON dump of ``options``."""
    h = hashlib.sha256(CACHE_VERSION.encode())
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    h.update(json.dumps(options, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Rename the finished temporary file ``tmp`` to ``path`` with the permissions a plain ``open`` gives
    (``0o666`` less the umask: ``mkstemp`` makes its files readable by their owner only)."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    os.replace(tmp, path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 of named arrays (names, shapes, dtypes and bytes, in name order)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(str((name, a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_entry(key: str, arrays: dict[str, np.ndarray], meta: dict[str, Any], directory: Path | None = None) -> None:
    """Store ``arrays`` and JSON ``meta`` under ``key`` (atomic).

    The metadata records the arrays' SHA-256 (``"sha256"``), so that a reload can prove it returns
    exactly the arrays that were stored (and, for cages, certified) -- see :func:`load_entry`.
    """
    import io

    d = Path(directory) if directory is not None else cache_dir()
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(d / f"{key}.npz", buf.getvalue())
    meta = {**meta, "sha256": arrays_digest(arrays)}
    atomic_write_bytes(d / f"{key}.json", json.dumps(meta, indent=1, default=str).encode())


def load_entry(key: str, directory: Path | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Return ``(arrays, meta)`` stored under ``key``, or None when absent, unreadable or altered.

    An entry whose arrays no longer match the SHA-256 recorded when it was saved (edited, corrupted,
    or written by an older version without it) is treated as absent, so it is rebuilt and re-verified.
    """
    d = Path(directory) if directory is not None else cache_dir()
    npz, js = d / f"{key}.npz", d / f"{key}.json"
    if not (npz.exists() and js.exists()):
        return None
    try:
        with np.load(npz) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(js.read_text())
    except Exception:  # noqa: BLE001 - any unreadable entry (BadZipFile, zlib.error, bad JSON...) is a miss
        return None
    if not isinstance(meta, dict) or meta.pop("sha256", None) != arrays_digest(arrays):
        return None
    return arrays, meta
