"""Build a multigrid hierarchy from a closed surface: cages -> tet layers -> prolongations.

``build_hierarchy(V, F, levels=3, method="nested")`` runs the three stages of the pipeline

1. ``cagegen.build_cages``: surfaces ``(V_k, F_k)``, finest (the input) first, each cage certified to
   contain the previous layer (except for ``method="decimate"``, the naive baseline);
2. :func:`nestmg.tetmesh.tetrahedralize` on every layer, target edge length ``h_0 * 2**k``;
3. :func:`nestmg.prolongation.prolongation` between consecutive tet layers.

Certification happens at the tet level too: TetWild's boundary is only within ``epsilon`` of a cage,
so a fine node can fall just outside the coarse tet mesh. For certified methods the coarse layer is
then re-meshed with a 4x smaller envelope (at most ``tet_retries`` times); whatever remains is
extrapolated and reported as ``n_outside`` per level.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from .cache import cache_key, load_entry, save_entry
from .memory import check_tet_memory
from .progress import Timer, stages
from .prolongation import ProlongationReport, prolongation
from .tetmesh import tetrahedralize

__all__ = ["Hierarchy", "build_hierarchy", "tet_hierarchy"]


@dataclass
class Hierarchy:
    """A geometric multigrid hierarchy (finest level first).

    Attributes
    ----------
    surfaces : list of (V, F)
        Layer surfaces; ``surfaces[0]`` is the input.
    tets : list of (V, T)
        Tet mesh of every layer: ``V`` (n_k,3) float, ``T`` (t_k,4) int.
    P : list of (n_k, n_{k+1}) csr_matrix
        ``P[k]`` prolongs level ``k+1`` to level ``k``; restriction is ``P[k].T``.
    prolongation_reports : list of ProlongationReport
        ``n_outside`` and extrapolation distance per level.
    method : str
        Cage backend used.
    cage_info : dict
        Backend figures and the nesting verifier's report.
    timings : dict
        Seconds per stage (``cages``, ``tets``, ``prolongation``).
    """

    surfaces: list[tuple[np.ndarray, np.ndarray]]
    tets: list[tuple[np.ndarray, np.ndarray]]
    P: list[sp.csr_matrix]
    prolongation_reports: list[ProlongationReport]
    method: str
    cage_info: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)

    @property
    def levels(self) -> int:
        """Number of levels."""
        return len(self.tets)

    @property
    def n_outside(self) -> list[int]:
        """Fine nodes extrapolated (outside every coarse tet), per level pair."""
        return [r.n_outside for r in self.prolongation_reports]

    @property
    def surfaces_nested(self) -> bool | None:
        """Whether the cage verifier certified every surface pair (None when not run)."""
        ver = self.cage_info.get("verification")
        return None if ver is None else bool(ver.get("ok"))

    @property
    def fallbacks(self) -> list[dict]:
        """Cage layers built by a backend's fallback (e.g. ``{"layer": 2, "fallback": "lazy"}``); [] if none."""
        layers = (self.cage_info.get("backend") or {}).get("layers") or []
        return [{"layer": int(d.get("layer", i + 1)), "fallback": d["fallback"]}
                for i, d in enumerate(layers) if isinstance(d, dict) and d.get("fallback")]

    def save(self, directory) -> Any:
        """Write the hierarchy to ``directory`` (:func:`nestmg.usermesh.save_hierarchy`)."""
        from .usermesh import save_hierarchy

        return save_hierarchy(self, directory)

    @classmethod
    def load(cls, directory) -> Hierarchy:
        """Read a hierarchy written by :meth:`save` (:func:`nestmg.usermesh.load_hierarchy`)."""
        from .usermesh import load_hierarchy

        return load_hierarchy(directory)

    @property
    def certified(self) -> bool:
        """True when the surfaces are certified nested *and* no fine node lies outside a coarse tet mesh."""
        return bool(self.surfaces_nested) and all(n == 0 for n in self.n_outside)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (no arrays)."""
        return {
            "method": self.method,
            "fallbacks": self.fallbacks,
            "levels": self.levels,
            "surface_faces": [len(F) for _, F in self.surfaces],
            "nodes": [len(V) for V, _ in self.tets],
            "tets": [len(T) for _, T in self.tets],
            "prolongation": [r.to_dict() for r in self.prolongation_reports],
            "n_outside": self.n_outside,
            "surfaces_nested": self.surfaces_nested,
            "certified": self.certified,
            "timings": self.timings,
            "cage_info": self.cage_info,
            "options": self.options,
        }

    def __repr__(self) -> str:
        fb = "".join(f", layer {d['layer']} by fallback {d['fallback']!r}" for d in self.fallbacks)
        lines = [f"Hierarchy(method={self.method!r}{fb}, levels={self.levels}, certified={self.certified})",
                 "level  faces     nodes      tets   nnz(P)  n_outside"]
        for k, ((_, F), (V, T)) in enumerate(zip(self.surfaces, self.tets)):
            nnz = self.P[k].nnz if k < len(self.P) else 0
            nout = self.n_outside[k] if k < len(self.P) else 0
            lines.append(f"{k:>5} {len(F):>6} {len(V):>9} {len(T):>9} {nnz:>8} {nout:>10}")
        return "\n".join(lines)


def _bbox_diag(V: np.ndarray) -> float:
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def _mesh_layer(V, F, mesher, h, epsilon, use_cache):
    """Tet-mesh one layer, through the cache."""
    opts = {"stage": "tets", "mesher": mesher, "h": round(h, 12), "epsilon": epsilon}
    key = cache_key([V, F], opts)
    if use_cache:
        hit = load_entry(key)
        if hit is not None:
            return hit[0]["V"], hit[0]["T"]
    check_tet_memory(V, F, h, mesher)  # refuse before meshing a layer that would not fit
    Vt, T = tetrahedralize(V, F, mesher=mesher, edge_length=h, epsilon=epsilon)
    if use_cache:
        save_entry(key, {"V": Vt, "T": T}, opts)
    return Vt, T


def tet_hierarchy(
    surfaces: list[tuple[np.ndarray, np.ndarray]],
    *,
    mesher: str = "tetwild",
    edge_length_fac: float | None = None,
    epsilon: float = 1e-3,
    extrapolation: str = "clamped",
    tet_retries: int = 2,
    cache: bool = True,
    progress: bool | None = None,
    fine: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[list, list, list, dict]:
    """Tet-mesh every surface layer and build the prolongations between consecutive layers.

    Parameters
    ----------
    surfaces : list of (V, F)
        Closed surfaces, finest first (each coarser one meant to contain the previous).
    mesher, epsilon
        See :func:`nestmg.tetmesh.tetrahedralize`.
    edge_length_fac : float, optional
        Layer ``k`` gets target edge length ``h_0 * 2**k`` with ``h_0 = edge_length_fac *
        diag(surfaces[0])``; default (None): ``h_0`` = mean edge length of the input surface, so the
        fine tets match the input's resolution.
    extrapolation : str
        Rule for fine nodes outside the coarse tet mesh (see :mod:`nestmg.prolongation`).
    tet_retries : int
        With TetWild, re-mesh a coarse layer with a 4x smaller envelope up to this many times while
        fine nodes remain outside it (0 disables).
    cache : bool
        Reuse tet meshes from the on-disk cache.
    progress : bool or None
        Show a progress bar (None: only on a terminal).
    fine : (V, T), optional
        The caller's own tet mesh of ``surfaces[0]``, used as level 0 unchanged instead of meshing it
        (:func:`nestmg.usermesh.hierarchy_from_tets`).

    Returns
    -------
    tets : list of (V, T)
    P : list of csr_matrix
    reports : list of ProlongationReport
    timings : dict
        ``tets`` and ``prolongation`` seconds, and ``tet_retries`` per level.
    """
    timer = Timer()
    V0, F0 = surfaces[0]
    if edge_length_fac is None:  # match the input surface's resolution
        h0 = float(np.linalg.norm(V0[F0[:, 1]] - V0[F0[:, 0]], axis=1).mean())
    else:
        h0 = edge_length_fac * _bbox_diag(V0)
    tets: list = []
    eps = [epsilon] * len(surfaces)
    retries = [0] * len(surfaces)
    with stages(len(surfaces), "tet layers", progress) as bar:
        for k, (V, F) in enumerate(surfaces):
            bar.describe(f"tet layer {k} ({len(F)} faces, {mesher})")
            with timer("tets"):
                if k == 0 and fine is not None:  # the caller's own fine tet mesh, kept as it is
                    tets.append(fine)
                else:
                    tets.append(_mesh_layer(V, F, mesher, h0 * 2**k, eps[k], cache))
            bar.advance()
    Ps, reps = [], []
    for k in range(len(surfaces) - 1):
        with timer("prolongation"):
            P, rep = prolongation(tets[k][0], tets[k + 1][0], tets[k + 1][1], extrapolation=extrapolation)
        while rep.n_outside > 0 and mesher == "tetwild" and retries[k + 1] < tet_retries:
            retries[k + 1] += 1
            eps[k + 1] /= 4
            with timer("tets"):
                tets[k + 1] = _mesh_layer(*surfaces[k + 1], mesher, h0 * 2 ** (k + 1), eps[k + 1], cache)
            with timer("prolongation"):
                P, rep = prolongation(tets[k][0], tets[k + 1][0], tets[k + 1][1], extrapolation=extrapolation)
        Ps.append(P)
        reps.append(rep)
    timings = dict(timer.seconds)
    timings["tet_retries"] = retries
    timings["epsilon"] = eps
    return tets, Ps, reps, timings


def build_hierarchy(
    V: np.ndarray,
    F: np.ndarray,
    levels: int = 3,
    *,
    method: str = "nested",
    face_counts: list[int] | None = None,
    mesher: str = "tetwild",
    edge_length_fac: float | None = None,
    epsilon: float = 1e-3,
    extrapolation: str = "clamped",
    tet_retries: int | None = None,
    cache: bool = True,
    progress: bool | None = None,
    cage_opts: dict | None = None,
    same_domain_levels: int = 0,
) -> Hierarchy:
    """Cages, tet layers and prolongations for the closed surface ``(V, F)``.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, manifold, single-component surface (audited; a clear error otherwise).
    levels : int
        Number of levels (input + ``levels - 1`` coarser layers: cages, after ``same_domain_levels``), >= 2.
    method : str
        Cage backend (``nested``, ``decimate``, ...; see ``cagegen.available_backends()``).
    face_counts : list of int, optional
        Cage face counts, finest first (default: 4x fewer faces per level).
    mesher, edge_length_fac, epsilon, extrapolation
        See :func:`tet_hierarchy`.
    tet_retries : int, optional
        Default 2 for certified methods, 0 for ``decimate`` (its layers are not nested anyway).
    cache : bool
        Reuse cages and tet meshes from the on-disk cache (``$NESTMG_CACHE``).
    progress : bool or None
        Progress bars (None: only on a terminal).
    cage_opts : dict, optional
        Extra options for the cage backend. With TetWild and a certified method, ``min_gap`` defaults
        to ``2.5 * epsilon`` (cages keep that clearance, relative to the bounding-box diagonal, so
        TetWild's envelope cannot put fine nodes outside the coarse tets).
    same_domain_levels : int
        Coarsen within the input surface first: levels ``1 .. same_domain_levels`` re-mesh the *input*
        surface at 2x, 4x, ... the fine edge length (same domain, so no fine node needs
        extrapolation; with TetGen the boundary is kept exactly), and only the remaining
        ``levels - same_domain_levels - 1`` levels are cages. For large fine meshes (ENVIRONMENT.md,
        "At scale"): a same-domain level is useful while its edge length stays below the input surface's
        own edge length, since the mesher cannot coarsen the boundary. 0 (default): cages only.

    Returns
    -------
    Hierarchy

    Raises
    ------
    cagegen.MeshInputError
        Bad input surface.
    cagegen.CageError
        A cage layer could not be built or certified (names the layer).
    """
    import cagegen

    if levels < 2:
        raise ValueError(f"levels must be >= 2, got {levels}")
    if not isinstance(same_domain_levels, (int, np.integer)) or not 0 <= same_domain_levels <= levels - 2:
        raise ValueError(
            f"same_domain_levels must be an integer in [0, levels - 2] = [0, {levels - 2}] (at least one cage "
            f"level), got {same_domain_levels!r}"
        )
    n_surf = levels - int(same_domain_levels)  # input + cages
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    cage_opts = dict(cage_opts or {})
    if mesher == "tetwild" and method != "decimate":
        # TetWild's boundary is only within `epsilon` (relative to each layer's bbox diagonal) of its
        # input, outward on the fine layer and inward on the cage: a clearance of 2.5 epsilon between
        # consecutive cages keeps every fine node inside the coarse tet mesh (tet-level nesting).
        cage_opts.setdefault("min_gap", 2.5 * epsilon)
    timer = Timer()
    opts = {"stage": "cages", "method": method, "levels": n_surf, "face_counts": face_counts, **cage_opts}
    key = cache_key([V, F], opts)
    hit = load_entry(key) if cache else None
    with timer("cages"):
        if hit is not None:
            arrays, info = hit
            surfaces = [(arrays[f"V{k}"], arrays[f"F{k}"]) for k in range(n_surf)]
            info = dict(info, cached=True)
        else:
            t0 = time.perf_counter()
            surfaces, info = cagegen.build_cages(
                V, F, n_surf, method=method, face_counts=face_counts, return_info=True, progress=progress, **cage_opts
            )
            info = dict(info, seconds=time.perf_counter() - t0)
            if cache:
                arrays = {}
                for k, (Vk, Fk) in enumerate(surfaces):
                    arrays[f"V{k}"], arrays[f"F{k}"] = Vk, Fk
                save_entry(key, arrays, info)
    if tet_retries is None:
        tet_retries = 0 if method == "decimate" else 2
    surfaces = [surfaces[0]] * int(same_domain_levels) + list(surfaces)  # same-domain layers first
    tets, Ps, reps, tt = tet_hierarchy(
        surfaces,
        mesher=mesher,
        edge_length_fac=edge_length_fac,
        epsilon=epsilon,
        extrapolation=extrapolation,
        tet_retries=tet_retries,
        cache=cache,
        progress=progress,
    )
    timings = {**timer.seconds, **tt}
    return Hierarchy(
        surfaces=surfaces,
        tets=tets,
        P=Ps,
        prolongation_reports=reps,
        method=method,
        cage_info=info,
        timings=timings,
        options={
            "levels": levels, "face_counts": face_counts, "mesher": mesher, "edge_length_fac": edge_length_fac,
            "epsilon": epsilon, "extrapolation": extrapolation, "cage_opts": cage_opts,
            "same_domain_levels": int(same_domain_levels),
        },
    )
