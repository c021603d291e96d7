"""Tet meshing of one closed surface layer (TetWild by default, TetGen optional).

Sizing rule for a hierarchy: layer ``k`` is meshed with target edge length ``h * 2**k``
(``h`` = ``edge_length`` x the *input's* bounding-box diagonal). Halving the
resolution per level gives ~8x fewer tets per coarser layer when the layers enclose similar volumes;
the cage backends use 4x fewer surface faces per level to match (``cagegen.default_face_counts``).

TetWild's boundary is only within ``epsilon`` (relative to the layer's bounding-box diagonal) of the
input surface, so a cage that touches the finer surface can leave a few fine nodes outside the coarse
tet mesh: the prolongation extrapolates and counts them (``n_outside``). TetGen keeps the input
boundary exactly.

Time limit: both meshers run in a separate worker process (``nestmg/_mesh_worker.py``, started once
and reused), killed when a call runs past its time limit -- TetGen's mesh improvement can loop
forever on some inputs, and a mesher segfault then ends the worker, not the caller. The limit defaults
to :data:`TIME_LIMIT_FACTOR` x the sizing estimate of the meshing time
(:func:`nestmg.sizing.fine_mesh_seconds`), at least :data:`MIN_TIME_LIMIT` seconds; the environment
variable ``NESTMG_MESH_TIME_LIMIT`` (seconds, or ``none``) or ``tetrahedralize(time_limit=...)``
changes it, and ``time_limit=None`` meshes in-process without a limit.
"""

from __future__ import annotations

import atexit
import importlib.util
import logging
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from cagegen import as_mesh_arrays, bbox_diagonal, in_temp_dir, normalize
from cagegen.errors import MeshInputError, NestmgError

from ._mesh_worker import run_job
from .errors import NestmgInputError

__all__ = [
    "MESHERS",
    "MIN_TIME_LIMIT",
    "TIME_LIMIT_ENV",
    "TIME_LIMIT_FACTOR",
    "TetMeshError",
    "TetMeshTimeoutError",
    "mesh_time_limit",
    "orient_tets",
    "spatial_order",
    "tet_quality",
    "tet_volumes",
    "tetrahedralize",
]

MESHERS = ("tetwild", "tetgen")

#: the automatic time limit of one :func:`tetrahedralize` call is this many times the sizing estimate of
#: its meshing time (the estimate is within ~3x of the measured times on a shared 2-core machine) ...
TIME_LIMIT_FACTOR = 10.0
#: ... and never below this many seconds, per mesher. TetGen: a 2k-tet mesh takes 0.05 s, a hang forever.
#: TetWild has not been seen to hang, but its time on CAD parts is far from the estimate (angle_block.stl,
#: 704 faces: 60 s on a loaded 2-core machine, where 60 s killed it): its floor only stops a runaway.
MIN_TIME_LIMIT = {"tetgen": 60.0, "tetwild": 900.0}
#: environment variable overriding the automatic limit: seconds, or "none" for no limit
TIME_LIMIT_ENV = "NESTMG_MESH_TIME_LIMIT"

_log = logging.getLogger("nestmg.tetmesh")


class TetMeshError(NestmgError, RuntimeError):
    """The mesher failed or produced an unusable tet mesh."""


class TetMeshTimeoutError(TetMeshError):
    """The mesher ran past its time limit and was stopped (the message says how to raise the limit)."""


def tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed volumes (t,) of tets ``T`` (t,4) of nodes ``V`` (n,3); positive = right-handed."""
    a, b, c, d = (V[T[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def orient_tets(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Return a copy of ``T`` with every tet positively oriented (swap two indices where negative)."""
    T = np.array(T, dtype=np.int64, copy=True)
    neg = tet_volumes(V, T) < 0
    T[neg, 2], T[neg, 3] = T[neg, 3].copy(), T[neg, 2].copy()
    return T


def tet_quality(V: np.ndarray, T: np.ndarray, sliver_deg: float = 5.0) -> dict:
    """Dihedral-angle quality of a tet mesh.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
    sliver_deg : float
        A tet whose smallest dihedral angle is below this (degrees) counts as a sliver.

    Returns
    -------
    dict
        ``min_dihedral_deg`` (smallest over the mesh), ``p01_min_dihedral_deg`` (1st percentile of the
        per-tet minimum), ``max_dihedral_deg``, ``n_slivers`` and ``sliver_fraction``.
    """
    V = np.asarray(V, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if len(T) == 0:
        return {"min_dihedral_deg": float("nan"), "p01_min_dihedral_deg": float("nan"),
                "max_dihedral_deg": float("nan"), "n_slivers": 0, "sliver_fraction": 0.0}
    P = V[T]
    # outward-or-inward face normals of the 4 faces (face i is opposite vertex i)
    faces = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
    N = np.stack([np.cross(P[:, b] - P[:, a], P[:, c] - P[:, a]) for a, b, c in faces], axis=1)
    N /= np.maximum(np.linalg.norm(N, axis=2, keepdims=True), 1e-300)
    # the dihedral angle at the edge shared by faces i and j is pi - angle(n_i, n_j)
    ang = np.stack([np.pi - np.arccos(np.clip(np.einsum("ij,ij->i", N[:, i], N[:, j]), -1.0, 1.0))
                    for i in range(4) for j in range(i + 1, 4)], axis=1)
    dmin = np.degrees(ang.min(axis=1))
    dmax = np.degrees(ang.max(axis=1))
    n_sl = int((dmin < sliver_deg).sum())
    return {"min_dihedral_deg": float(dmin.min()), "p01_min_dihedral_deg": float(np.percentile(dmin, 1)),
            "max_dihedral_deg": float(dmax.max()), "n_slivers": n_sl, "sliver_fraction": n_sl / len(T)}


def _flat(V: np.ndarray, T: np.ndarray, rtol: float = 1e-12) -> np.ndarray:
    """Mask of flat tets: |volume| <= ``rtol`` x (longest edge)^3 (a regular tet has 0.118)."""
    P = V[T]
    longest = np.max([np.linalg.norm(P[:, i] - P[:, j], axis=1)
                      for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], axis=0)
    return np.abs(tet_volumes(V, T)) <= rtol * longest**3


def _has_flat_tets(V: np.ndarray, T: np.ndarray) -> bool:
    """True if some tet is flat (FEM-unusable: unbounded cotangent weights)."""
    return bool(len(T) and _flat(V, T).any())


def _drop_boundary_slivers(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove flat tets whose four nodes all lie on the boundary surface.

    TetGen keeps the input surface exactly; where that surface has nearly coplanar neighbouring
    triangles it may fill the gap between them with a sliver of ~zero volume. Such a tet adds nothing
    to the domain, and its cotangent weights are unbounded, so it is dropped. Flat tets with an
    interior node are left for the caller to reject.
    """
    from solvers.fem import boundary_nodes

    flat = _flat(V, T)
    on_bnd = np.zeros(len(V), dtype=bool)
    on_bnd[boundary_nodes(T)] = True
    drop = flat & on_bnd[T].all(axis=1)
    if not drop.any():
        return V, T
    return _compact(V, T[~drop])


def _compact(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(T)
    if len(used) == len(V):
        return V, T
    remap = -np.ones(len(V), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[T]


# ----------------------------------------------------------------------------- time limit and worker
def mesh_time_limit(V: np.ndarray, F: np.ndarray, edge_length: float, mesher: str = "tetwild") -> float | None:
    """The automatic time limit (seconds) of meshing ``(V, F)`` at ``edge_length``; None = no limit.

    ``$NESTMG_MESH_TIME_LIMIT`` if set (seconds, or ``none``), else :data:`TIME_LIMIT_FACTOR` x the
    sizing estimate :func:`nestmg.sizing.fine_mesh_seconds` of the expected tets, at least
    :data:`MIN_TIME_LIMIT`.
    """
    env = os.environ.get(TIME_LIMIT_ENV, "").strip()
    if env:
        if env.lower() in ("none", "off", "inf", "0"):
            return None
        try:
            value = float(env)
        except ValueError:
            value = float("nan")
        if not (math.isfinite(value) and value > 0):
            raise NestmgInputError(f"{TIME_LIMIT_ENV}={env!r}: give seconds (> 0) or 'none'")
        return value
    from .memory import enclosed_volume  # nestmg.memory and nestmg.sizing import this module
    from .sizing import expected_tets, fine_mesh_seconds

    n_tets = expected_tets(enclosed_volume(V, F), float(edge_length), mesher)
    return max(MIN_TIME_LIMIT[mesher], TIME_LIMIT_FACTOR * fine_mesh_seconds(len(F), n_tets, mesher))


#: how often (seconds) a worker with a CPU budget is checked
CPU_POLL_SECONDS = 0.1


def _cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) used so far by process ``pid``; None if unknown."""
    try:
        import psutil

        t = psutil.Process(pid).cpu_times()
        return float(t.user + t.system)
    except ImportError:
        pass
    except Exception:  # noqa: BLE001 - the process ended or is not readable: no CPU figure
        return None
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
    except (OSError, ValueError, IndexError):
        return None


class _MeshTimeout(Exception):
    """The worker did not answer within the time limit (it has been killed)."""


class _MeshCrash(Exception):
    """The worker died during a job (exit code in ``args[0]``)."""


class _MesherWorker:
    """One long-lived mesher process (``nestmg/_mesh_worker.py``), fed jobs over a socket."""

    SCRIPT = Path(__file__).with_name("_mesh_worker.py")

    def __init__(self) -> None:
        import tempfile
        from multiprocessing import Pipe

        self.owner = os.getpid()
        self.dir = tempfile.TemporaryDirectory(prefix="nestmg-mesher-")  # fTetWild's working files
        self.out = tempfile.TemporaryFile(dir=self.dir.name)  # noqa: SIM115 - the meshers' printing, closed in close()
        ours, theirs = Pipe(duplex=True)
        args = [sys.executable, str(self.SCRIPT), str(theirs.fileno())]
        if threading.current_thread() is threading.main_thread():
            args.append("--die-with-parent")  # the kernel's parent-death signal follows the creating thread
        try:
            self.proc = subprocess.Popen(args, pass_fds=(theirs.fileno(),), cwd=self.dir.name,
                                         stdin=subprocess.DEVNULL, stdout=self.out, stderr=subprocess.STDOUT)
        finally:
            theirs.close()
        self.conn = ours
        self.conn.send(("path", [os.path.abspath(p) for p in sys.path if isinstance(p, str)]))

    def alive(self) -> bool:
        return self.proc.poll() is None

    def run(self, job: tuple, limit: float | None, cpu_budget: float | None = None) -> tuple:
        """Send ``job`` and wait at most ``limit`` seconds (None: no limit) for the reply, and while the
        worker has used at most ``cpu_budget`` CPU seconds on it (None: no budget)."""
        self.conn.send(job)
        if not self._wait(limit, cpu_budget):
            raise _MeshTimeout
        try:
            reply = self.conn.recv()
        except EOFError:
            raise _MeshCrash(self.proc.wait()) from None
        self._log_output()
        return reply

    def _wait(self, limit: float | None, cpu_budget: float | None) -> bool:
        """True when the reply arrived within ``limit`` wall seconds and ``cpu_budget`` CPU seconds."""
        start = None if cpu_budget is None else _cpu_seconds(self.proc.pid)
        if start is None:
            return self.conn.poll(limit)
        end = None if limit is None else time.monotonic() + limit
        while True:
            left = None if end is None else max(0.0, end - time.monotonic())
            if self.conn.poll(CPU_POLL_SECONDS if left is None else min(CPU_POLL_SECONDS, left)):
                return True
            if left is not None and time.monotonic() >= end:
                return False
            used = _cpu_seconds(self.proc.pid)
            if used is not None and used - start > cpu_budget:
                return False

    def _log_output(self) -> None:
        self.out.seek(0)
        text = self.out.read().decode(errors="replace").strip()
        self.out.seek(0)
        self.out.truncate()
        for line in text.splitlines():
            _log.debug("mesher: %s", line)

    def close(self, kill: bool = False) -> None:
        """End the worker: at once (``kill``) or by closing its socket (it exits at EOF)."""
        if kill:
            self.proc.kill()
        self.conn.close()
        try:
            self.proc.wait(timeout=None if kill else 5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.out.close()
        self.dir.cleanup()


_worker: _MesherWorker | None = None
_worker_lock = threading.Lock()


def _close_worker() -> None:
    global _worker
    if _worker is not None and _worker.owner == os.getpid():
        _worker.close()
    _worker = None


atexit.register(_close_worker)


def _run_in_worker(mesher: str, V: np.ndarray, F: np.ndarray, opts: dict, deadline: float,
                   cpu_budget: float | None = None) -> tuple:
    """One mesher call in the worker process, answered before ``deadline`` (time.monotonic) and within
    ``cpu_budget`` CPU seconds, or killed."""
    global _worker
    with _worker_lock:
        for fresh in (False, True):
            if _worker is None or _worker.owner != os.getpid() or not _worker.alive():
                if _worker is not None and _worker.owner == os.getpid():
                    _worker.close(kill=True)
                _worker = _MesherWorker()  # a forked child never touches its parent's worker
            w = _worker
            try:
                return w.run((mesher, V, F, opts), max(0.0, deadline - time.monotonic()), cpu_budget)
            except (BrokenPipeError, ConnectionResetError) as exc:
                # the worker had died between jobs (nothing was computed): start a new one, once
                w.close(kill=True)
                _worker = None
                if fresh:
                    raise _MeshCrash(w.proc.returncode) from exc
            except BaseException:  # time-out, crash, Ctrl-C: the job is abandoned with its process
                w.close(kill=True)
                _worker = None
                raise
    raise AssertionError("unreachable")


def _mesher_call(mesher: str, V: np.ndarray, F: np.ndarray, opts: dict, deadline: float | None,
                 cpu_budget: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``run_job`` in-process (no deadline) or in the worker (killed at ``deadline`` or past ``cpu_budget``
    CPU seconds), with the mesher's failures as TetMeshError."""
    what = f"a surface with {len(V)} vertices / {len(F)} faces"
    if deadline is None:
        if mesher == "tetwild":
            with in_temp_dir():
                return run_job(mesher, V, F, opts)
        return run_job(mesher, V, F, opts)
    t = time.monotonic()
    try:
        reply = _run_in_worker(mesher, V, F, opts, deadline, cpu_budget)
    except _MeshTimeout:
        budget = "" if cpu_budget is None else f" (CPU budget {cpu_budget:.3g} s)"
        raise TetMeshTimeoutError(f"{mesher} stopped after {time.monotonic() - t:.3g} s{budget} on {what}") \
            from None
    except _MeshCrash as exc:
        rc = exc.args[0]
        how = f"signal {-rc}" if isinstance(rc, int) and rc < 0 else f"exit code {rc}"
        raise TetMeshError(f"{mesher} crashed ({how}) on {what}") from None
    if reply[0] == "ok":
        return reply[1]
    _, kind, message = reply
    raise TetMeshError(f"{mesher} failed on {what}: {message or kind}")


def _limit_hint(limit: float | None) -> str:
    return (f"time limit {limit:.3g} s: raise it with {TIME_LIMIT_ENV}=SECONDS or "
            "tetrahedralize(time_limit=SECONDS) ('none': no limit)")


#: fTetWild's edge outside the solid, relative to the target edge (:func:`outer_sizing_field`), used when
#: fTetWild's box is at least :data:`OUTER_BOX_RATIO` times the solid's volume (1: never). Measured by
#: ``benchmarks/tetwild_outside.py`` (one thread, CPU seconds, the pipeline's fine surface and edge,
#: graded / uniform, box / solid ratio in brackets; ``benchmarks/results/tetwild/tetwild_outside.json``
#: and ``_v0.json``): lucy.ply (21.3) 211.2 / 409.2, homer.obj (11.3) 57.1 / 133.7 and 54.4 / 136.9,
#: elephant.obj (10.7) 66.6 / 88.5, bunny.off (7.3) 67.6 / 89.7, angle_block.stl (3.0) 17.9 / 18.4;
#: tets within 9%. A loss above the threshold: cheburashka.obj (9.8) 383.8 / 263.9, 11% more tets
#: (``_cheburashka.json``). An earlier loaded run (no JSON) had bunny 59.5 / 51.1 and angle_block
#: 24.7 / 15.7. The ratio predicts the gain on 4 of the 5 shapes above it, not on all: one run each.
OUTER_EDGE_FACTOR = 3.0
#: fTetWild's optimisation passes at most on a cage level (``MeshingOptions.coarse_max_opt_iter``): its
#: own 80, as on the input's level. fTetWild stops at ``stop_energy`` only; where a few tets near a cage's
#: long thin triangles stay just above it (AMIPS 10-20), every few passes it halves the local sizing field,
#: so the working mesh doubles: a 250-face cage of decimated-knight.off went from 8k to 95k working tets
#: in 31 passes, and that layer took 592 s in one corpus run (``corpus/zoo_9adea45.json``; 20-35 s for the
#: whole hierarchy in others). A cap of 20 bounds that loop but cost the knight's Neumann factors
#: (medians 0.270 / 0.296 against 0.247 / 0.271 over 4 fresh hierarchies each,
#: ``setup_cost/cage_tetwild_passes_factors.json``): the refinement it cuts also serves the coarse space.
#: So the default stays 80; lower it when a cage level's meshing runs away.
COARSE_MAX_OPT_ITER = 80
#: box / solid volume ratio from which :data:`OUTER_EDGE_FACTOR` applies (see :func:`box_ratio`)
OUTER_BOX_RATIO = 8.0
#: most background-grid nodes of :func:`outer_sizing_field` (the spacing grows past it)
SIZING_GRID_NODES = 1_000_000


def _spread_bits(q: np.ndarray) -> np.ndarray:
    """The 21 low bits of each uint64 of ``q`` spread to every third bit (Morton code of one axis)."""
    x = q & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def _morton_keys(P: np.ndarray, lo: np.ndarray, span: float) -> np.ndarray:
    q = np.clip((P - lo) / span * (2**21 - 1), 0, 2**21 - 1).astype(np.uint64)
    return _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))


def spatial_order(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same surface renumbered along a Morton (Z-order) curve: vertices by position, faces by centroid.

    fTetWild's time depends on the order of its input, not only on its shape: cheburashka.obj, whose
    faces come in random order (consecutive centroids 28 mean edges apart), took 166.8 s at an edge of 0.05
    of the diagonal and 12.7 s renumbered; homer.obj took 16.7 s as given and 143.6 s shuffled
    (``benchmarks/tetwild_order.py``, ``benchmarks/results/tetwild/tetwild_order.json``). Each face keeps
    its vertices' cyclic order (its orientation).

    Returns
    -------
    V2 : (n,3) float array
    F2 : (m,3) int array
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    lo = V.min(axis=0)
    span = max(float(np.ptp(V, axis=0).max()), 1e-300)
    order = np.argsort(_morton_keys(V, lo, span), kind="stable")
    rank = np.empty(len(V), dtype=np.int64)
    rank[order] = np.arange(len(V))
    G = rank[F]
    G = G[np.argsort(_morton_keys(V[F].mean(axis=1), lo, span), kind="stable")]
    return V[order], G


def box_ratio(V: np.ndarray, F: np.ndarray) -> float:
    """Volume of fTetWild's working box (the bounding box grown by 1/15 of its diagonal on every side)
    over the solid's enclosed volume: how much of fTetWild's work a uniform box spends outside."""
    from .memory import enclosed_volume  # nestmg.memory imports this module

    lo, hi = V.min(axis=0), V.max(axis=0)
    grow = float(np.linalg.norm(hi - lo)) / 15.0
    vol = enclosed_volume(V, F)
    return float(np.prod(hi - lo + 2 * grow) / vol) if vol > 0 else float("inf")


def outer_sizing_field(V: np.ndarray, F: np.ndarray, h: float, factor: float) -> dict:
    """fTetWild keywords for a mesh at edge ``h`` inside the solid and ``factor * h`` away from it.

    fTetWild meshes the whole (enlarged) bounding box at the target edge, optimises all of it and
    discards the outside at the end: on homer.obj at 124k tets the working mesh had ~700k tets. Here its
    global edge is ``factor * h`` and a background grid (spacing ``s >= h``, Kuhn tets) asks for ``h``
    at every grid node inside the solid (winding number) or within ``1.8 s`` of the surface (so every
    grid cell that meets the solid has ``h`` at all its corners), growing by half the distance beyond.
    fTetWild's main passes then run on the coarse mesh and its sizing-field passes refine the solid
    (``apply_sizingfield``). Measured on homer (h = 0.0121 of the diagonal, one thread): 50.7 against
    178.5 CPU s, 124,194 against 123,318 tets, minimum dihedral angle 12.9 against 11.5 degrees.
    """
    import igl

    lo, hi = V.min(axis=0) - 0.15, V.max(axis=0) + 0.15  # fTetWild's box is the bbox plus ~1/15
    s = max(h, float(np.prod(hi - lo) / SIZING_GRID_NODES) ** (1 / 3))
    n = np.ceil((hi - lo) / s).astype(int) + 1
    axes = [lo[i] + s * np.arange(n[i]) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    Fi = np.asarray(F, dtype=np.int64)
    wn = igl.fast_winding_number(np.asarray(V, dtype=np.float64), Fi, G)
    d = np.sqrt(igl.point_mesh_squared_distance(G, np.asarray(V, dtype=np.float64), Fi)[0])
    band = 1.8 * s
    values = np.where((wn > 0.5) | (d < band), h, np.minimum(factor * h, h + 0.5 * (d - band)))
    return {"edge_length_abs": factor * h, "bg_vertices": G, "bg_tets": _kuhn_tets(n),
            "bg_values": values.astype(np.float64)}


def _kuhn_tets(n: np.ndarray) -> np.ndarray:
    """The six Kuhn tets of every cell of an ``n[0] x n[1] x n[2]`` node grid (C order), int32."""
    import itertools

    idx = np.arange(int(np.prod(n))).reshape(tuple(n))
    c = [a.ravel() for a in np.meshgrid(*[np.arange(k - 1) for k in n], indexing="ij")]
    tets = []
    for perm in itertools.permutations(range(3)):
        o = [0, 0, 0]
        path = [idx[c[0], c[1], c[2]]]
        for ax in perm:
            o[ax] += 1
            path.append(idx[c[0] + o[0], c[1] + o[1], c[2] + o[2]])
        tets.append(np.stack(path, axis=1))
    return np.concatenate(tets).astype(np.int32)


#: TetGen's modes, tried in order while the previous one fails (a TetGen error, flat tets, or its share
#: of the time limit). "exact": no merging of coplanar facets or close vertices, so the boundary is the
#: input's triangles (a cage touching the finer surface keeps it inside; merging lost 3e-4 of a torus
#: cage's volume, docs/experiments.md). Exact mode fails on some surfaces with many (nearly) coplanar
#: neighbouring faces, e.g. the convex hull of a rotated torus (flat caps): an internal TetGen error,
#: flat tets between coplanar facets, or a mesh-improvement loop on those flat tets that never ends (the
#: hang of issue 27). "merged": TetGen's own treatment of coplanar facets (merged within 0.1 degrees),
#: which meshes those; the boundary may then move by the height of a fold below 0.1 degrees.
_TETGEN_MODES = {
    "exact": {"nomergefacet": True, "nomergevertex": True},
    "merged": {"nomergefacet": False, "nomergevertex": True},
}
#: TetGen's radius-edge bound does not remove slivers: when a mode leaves flat tets it is retried with
#: these dihedral-angle bounds (TetGen's -q/d switch) before the next mode
_TETGEN_MINDIHEDRAL = (0.0, 10.0, 18.0)
#: CPU seconds (plus 5x the time estimate) TetGen's exact mode may use before the merged mode is tried.
#: CPU, not wall seconds: a wall-clock share made the mesh depend on the machine's load (the test torus's
#: exact mode, 1.4 CPU s, passed its 7.1 s share under load 4 in 5 of 10 runs and was meshed in merged
#: mode instead: another mesh, another convergence factor)
EXACT_MODE_SECONDS = 3.0


def _tetgen(V, F, h, minratio, deadline, limit):
    """TetGen through its modes (:data:`_TETGEN_MODES`): the first usable mesh, else one TetMeshError.

    Usable: no flat tet, or only flat tets whose four nodes are on the boundary (dropped, see
    :func:`_drop_boundary_slivers`) after the last dihedral bound.
    """
    failures, timed_out = [], False
    modes = list(_TETGEN_MODES.items())
    # a mode that is not the last may use EXACT_MODE_SECONDS + 5x the estimate in CPU seconds (TetGen meshes
    # ~1e5 tets/s, so the budget is reached only by the mesh-improvement loop, not by work): a loop costs
    # seconds; half the remaining wall time protects the call's own limit
    from .memory import enclosed_volume  # nestmg.memory and nestmg.sizing import this module
    from .sizing import expected_tets, fine_mesh_seconds

    estimate = fine_mesh_seconds(len(F), expected_tets(enclosed_volume(V, F), h, "tetgen"), "tetgen")
    for i, (mode, flags) in enumerate(modes):
        mode_deadline, cpu_budget = None, None
        if deadline is not None:
            remaining = max(0.0, deadline - time.monotonic())
            last = i == len(modes) - 1
            mode_deadline = time.monotonic() + (remaining if last else remaining / 2)
            cpu_budget = None if last else EXACT_MODE_SECONDS + 5 * estimate
        mesh = None
        for mindihedral in _TETGEN_MINDIHEDRAL:
            opts = {"quality": True, "minratio": minratio, "mindihedral": mindihedral, "fixedvolume": True,
                    "maxvolume": h**3 / (6 * np.sqrt(2)), "steinerleft": -1, **flags}
            try:
                Vt, T = _mesher_call("tetgen", V, F, opts, mode_deadline, cpu_budget)
            except TetMeshError as exc:
                mesh = None
                timed_out = timed_out or isinstance(exc, TetMeshTimeoutError)
                failures.append(f"{mode} mode: {exc}")
                break
            Vt, T = _compact(Vt, T)
            mesh = (Vt, orient_tets(Vt, T))
            if not _has_flat_tets(*mesh):
                break
        if mesh is not None and _has_flat_tets(*mesh):
            mesh = _drop_boundary_slivers(*mesh)
            if _has_flat_tets(*mesh):
                failures.append(f"{mode} mode: {int(_flat(*mesh).sum())} flat (near-zero volume) tets")
                mesh = None
        if mesh is not None:
            if failures:
                _log.info("tetgen: %s; meshed in %s mode", "; ".join(failures), mode)
            return mesh
    msg = f"tetgen failed on a surface with {len(V)} vertices / {len(F)} faces: {'; '.join(failures)}"
    if timed_out:
        raise TetMeshTimeoutError(f"{msg}; {_limit_hint(limit)}; or try mesher='tetwild'")
    raise TetMeshError(f"{msg}; try mesher='tetwild'")


def tetrahedralize(
    V: np.ndarray,
    F: np.ndarray,
    *,
    mesher: str = "tetwild",
    edge_length: float = 0.05,
    edge_length_abs: float | None = None,
    epsilon: float = 1e-3,
    minratio: float = 1.5,
    threads: int = 0,
    stop_energy: float = 10.0,
    max_opt_iter: int = 80,
    coarsen: bool = False,
    simplify: bool = True,
    outer_edge_factor: float = OUTER_EDGE_FACTOR,
    time_limit: float | str | None = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Tet-mesh the solid bounded by the closed surface ``(V, F)``.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, outward-oriented surface.
    mesher : {"tetwild", "tetgen"}
        ``tetwild`` (pytetwild / fTetWild, robust, boundary within ``epsilon``) or ``tetgen``
        (fast, keeps the boundary exactly; needs the ``tetgen`` extra and a clean input).
    edge_length : float
        Target edge length relative to the bounding-box diagonal of ``V`` (used when ``edge_length_abs``
        is None).
    edge_length_abs : float, optional
        Target edge length in the units of ``V`` (overrides ``edge_length``).
    epsilon : float
        TetWild envelope, relative to the bounding-box diagonal (ignored by tetgen).
    minratio : float
        TetGen radius-edge quality bound (ignored by tetwild).
    threads : int
        TetWild threads (0 = all cores).
    stop_energy, max_opt_iter
        TetWild's optimisation stops when the largest conformal AMIPS energy of a tet is below
        ``stop_energy`` or after ``max_opt_iter`` passes (fTetWild's defaults: 10 and 80).
    coarsen : bool
        TetWild: coarsen the output as far as the quality allows. Without it the boundary triangles of a
        coarse cage keep ~2-8x more tets than the target edge length asks (measured on the demo torus's
        cages: 4,400 instead of 2,354; with it 2,260, no tet below 5 degrees).
    simplify : bool
        TetWild: simplify the input surface within its envelope before meshing (fTetWild's default).
        ``benchmarks/tetwild_simplify.py`` measures it against meshing the surface as given.
    outer_edge_factor : float
        TetWild: target edge of its working mesh *outside* the solid, relative to the edge length
        (:func:`outer_sizing_field`), applied when fTetWild's box is at least :data:`OUTER_BOX_RATIO`
        times the solid (:func:`box_ratio`); 1: fTetWild's uniform sizing. fTetWild optimises a mesh of
        the whole bounding box and discards the outside at the end; a coarse outside cuts that work on
        slender shapes (homer.obj: 2.5x fewer CPU seconds, lucy.ply 1.9x).
    time_limit : float, "auto" or None
        Seconds the mesher may run (in a worker process, killed when over). ``"auto"``:
        :func:`mesh_time_limit` (``$NESTMG_MESH_TIME_LIMIT``, else 10x the sizing estimate, at least
        60 s for TetGen, 900 s for TetWild). None: no limit, and the mesher runs in this process.

    Returns
    -------
    Vt : (p,3) float64 array
        Nodes (every node used by a tet).
    T : (t,4) int64 array
        Positively oriented tets.

    Raises
    ------
    MeshInputError
        Wrong shapes or dtypes, no faces, indices out of range, NaN/inf coordinates (checked before
        the mesher runs).
    TetMeshError
        If the mesher fails, crashes, runs past ``time_limit`` (the message names the limit and how to
        raise it) or returns an empty / degenerate mesh.
    """
    # structural checks before any C++ code sees the arrays: pytetwild segfaults on an empty face
    # array, and out-of-range indices would be read out of bounds
    V, F = as_mesh_arrays(V, F, "surface")
    if not np.isfinite(V).all():
        raise MeshInputError(f"surface: {int((~np.isfinite(V)).any(axis=1).sum())} vertices have NaN/inf coordinates")
    if mesher not in MESHERS:
        raise NestmgInputError(f"unknown mesher {mesher!r}; choose from {MESHERS}")
    diag = bbox_diagonal(V)  # overflow-safe
    if not (np.isfinite(diag) and diag > 0):
        raise MeshInputError(f"surface: bounding-box diagonal {diag} (all vertices coincide, or overflow)")
    h = float(edge_length_abs) if edge_length_abs is not None else edge_length * diag
    if not np.isfinite(h) or h <= 0:
        raise NestmgInputError(f"edge length must be positive, got {h}")
    limit = mesh_time_limit(V, F, h, mesher) if time_limit == "auto" else time_limit
    if limit is not None and not (isinstance(limit, (int, float)) and limit > 0):
        raise NestmgInputError(f"time_limit must be seconds > 0, 'auto' or None, got {time_limit!r}")
    deadline = None if limit is None else time.monotonic() + float(limit)
    try:
        if mesher == "tetwild":
            # pytetwild segfaults on small inputs (diagonal 1e-9): mesh a unit-diagonal copy, map back
            Vn, c, _ = normalize(V, diag)
            Vn, Fn = spatial_order(Vn, F)  # fTetWild ran 9-13x slower on randomly ordered inputs
            opts = {"edge_length_abs": h / diag, "epsilon": epsilon, "num_threads": threads, "quiet": True,
                    "stop_energy": float(stop_energy), "num_opt_iter": int(max_opt_iter), "coarsen": bool(coarsen),
                    "simplify": bool(simplify)}
            if outer_edge_factor > 1.0 and box_ratio(Vn, Fn) >= OUTER_BOX_RATIO:
                opts.update(outer_sizing_field(Vn, Fn, h / diag, float(outer_edge_factor)))
            try:
                Vt, T = _mesher_call("tetwild", Vn, Fn, opts, deadline)
            except TetMeshTimeoutError as exc:
                raise TetMeshTimeoutError(f"{exc}; {_limit_hint(limit)}; or give a larger edge length") from None
            Vt = Vt * diag + c
        else:
            if importlib.util.find_spec("tetgen") is None:  # optional extra (AGPL: imported only when asked)
                raise TetMeshError("mesher='tetgen' needs the optional 'tetgen' package (pip install tetgen)")
            Vt, T = _tetgen(V, F, h, minratio, deadline, limit)
    except TetMeshError:
        raise
    except Exception as exc:  # the meshers raise RuntimeError / their own types on bad input
        raise TetMeshError(f"{mesher} failed on a surface with {len(V)} vertices / {len(F)} faces: {exc}") from exc
    Vt = np.asarray(Vt, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if len(T) == 0:
        raise TetMeshError(f"{mesher} returned no tets (surface {len(V)} vertices / {len(F)} faces)")
    Vt, T = _compact(Vt, T)
    T = orient_tets(Vt, T)
    if _has_flat_tets(Vt, T):  # TetGen's flat tets were handled by its modes
        n_flat = int(_flat(Vt, T).sum())
        raise TetMeshError(f"{mesher} returned {n_flat} flat (near-zero volume) tets; try mesher='tetwild'")
    return Vt, T
