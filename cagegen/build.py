"""The one entry point of :mod:`cagegen`: :func:`build_cages` (audit, backend, certification).

Re-exported by the package (``cagegen.build_cages``); kept in its own module so that
:mod:`cagegen.components` can import it without importing the package ``__init__``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable

import numpy as np

from ._geometry import as_mesh_arrays, bbox_diagonal, signed_volume
from .audit import MeshAudit, check_mesh
from .errors import CageError, CageOptionError, CageTypeError, LevelsError, MeshInputError
from .options import CageOptions, cage_options
from .registry import backend_spec, get_backend, get_budget, get_schedule, options_class
from .sizes import check_face_counts, default_face_counts
from .verify import verify_nesting

__all__ = ["UNCERTIFIED_METHODS", "build_cages", "fallback_layers"]

#: Methods whose layers are not expected to nest (baselines): reported, not gated.
UNCERTIFIED_METHODS = frozenset({"decimate"})


def fallback_layers(info: dict) -> list[dict]:
    """Cage layers that a backend built with an opt-in fallback, read from :func:`build_cages`' info.

    Parameters
    ----------
    info : dict
        ``build_cages(..., return_info=True)[1]`` (or ``Hierarchy.cage_info``).

    Returns
    -------
    list of dict
        ``{"layer": k, "fallback": name}`` per such layer (k = 1 for the first cage); [] when none.

    Examples
    --------
    >>> fallback_layers({"backend": {"layers": [{"layer": 1}, {"layer": 2, "fallback": "lazy"}]}})
    [{'layer': 2, 'fallback': 'lazy'}]
    """
    layers = (info.get("backend") or {}).get("layers") or []
    return [{"layer": int(d.get("layer", i + 1)), "fallback": d["fallback"]}
            for i, d in enumerate(layers) if isinstance(d, dict) and d.get("fallback")]


def _options(method: str, options: CageOptions | None, opts: dict) -> CageOptions:
    """The method's options object, from ``options`` or from loose keyword ``opts`` (not both)."""
    cls = options_class(method)
    if options is None:
        return cage_options(cls, method, **opts)
    if opts:
        raise CageOptionError(f"give the options as options= or by name, not both (got {sorted(opts)})")
    if not isinstance(options, cls):
        raise CageOptionError(f"method {method!r} takes {cls.__name__}, got {type(options).__name__}")
    return options


def _layer_loop(method: str, layer_fn: Callable, V: np.ndarray, F: np.ndarray, face_counts: list[int],
                kwargs: dict, say: Callable[[str], None], plan: list[dict] | None = None,
                ) -> tuple[list, dict]:
    """The loop over the layers of a per-layer backend (:mod:`cagegen.registry`): layer ``k`` around layer
    ``k - 1``, lengths relative to the input's diagonal on every layer, one progress line and the same info
    keys per layer for every such backend."""
    import igl

    t0 = time.perf_counter()
    diag0, vol0 = bbox_diagonal(V), signed_volume(V, F)
    min_gap = float(kwargs.get("min_gap", 0.0))
    layers, per_layer, changes = [], [], []
    Vp, Fp = V, F
    for k, m in enumerate(face_counts, start=1):
        t = time.perf_counter()
        try:
            U, G, li = layer_fn(Vp, Fp, int(m), unit=diag0, **{**kwargs, **(plan[k - 1] if plan else {})})
        except CageError as exc:
            raise CageError(f"layer {k}: {exc}", layer=k, reason=exc.reason) from exc
        note = li.pop("progress", "")
        li["layer"] = k
        li["hausdorff_relative_to_input"] = float(igl.hausdorff(U, G, V, F)) / diag0
        li["volume_ratio_to_input"] = signed_volume(U, G) / vol0
        if li.get("genus_changed"):
            changes.append({"layer": k, "from": li["genus_fine"], "to": li["genus"]})
        per_layer.append(li)
        layers.append((U, G))
        genus = f", genus {li['genus_fine']} -> {li['genus']}" if li.get("genus_changed") else ""
        say(f"{method}: layer {k}: {len(G)} faces (target {m}){', ' + note if note else ''}, max distance "
            f"{li['hausdorff_relative_to_input']:.4f} of the diagonal, {time.perf_counter() - t:.2f} s"
            f"{genus}")
        Vp, Fp = U, G
    info = {
        "method": method,
        "nested_by_construction": method not in UNCERTIFIED_METHODS,
        "genus_changes": changes,
        "min_gap_requested": {"relative": min_gap, "absolute": min_gap * diag0},
        "seconds": time.perf_counter() - t0,
        "layers": per_layer,
    }
    return layers, info


def build_cages(
    V,
    F,
    levels: int | None = None,
    method: str = "nested",
    face_counts=None,
    verify: bool = True,
    return_info: bool = False,
    progress: bool | Callable[[str], None] | None = None,
    *,
    options: CageOptions | None = None,
    components: str = "single",
    audit: MeshAudit | None = None,
    **opts,
):
    """Build a hierarchy of cages around a closed surface, finest first.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
        Closed, manifold, single-piece, outward-oriented, self-intersection-free surface (audited;
        the caller's arrays are never modified).
    levels : int, optional
        Total number of layers, input included. Needed unless ``face_counts`` is given.
    method : str
        Registered backend (``"nested"``, ``"decimate"``, ``"lazy"``, ...; see
        :func:`available_backends`).
    face_counts : sequence of int, optional
        Target faces per cage, finest first (``levels - 1`` entries, strictly decreasing). Default:
        :func:`default_face_counts` (4x fewer faces per level).
    verify : bool
        Run :func:`verify_nesting` on the result. For certified methods (all but ``"decimate"``) a
        failing pair raises :class:`CageError`; for ``"decimate"`` the figures are only recorded.
        ``verify=False`` skips it (``info["certified"]`` is then False).
    return_info : bool
        Also return the info dict.
    progress : bool or callable, optional
        ``progress(message)`` is called at each stage; ``True`` prints the messages to stderr;
        ``None``/``False`` is silent. Backends that accept a ``progress`` keyword get the callable.
    options : CageOptions, optional
        The method's options (:func:`cagegen.options_class`, e.g. :class:`cagegen.NestedOptions`), among
        them ``repair`` (merge duplicate vertices, drop unreferenced ones and orient outward before the
        audit) and ``min_gap`` (clearance demanded between consecutive layers, relative to the input's
        bounding-box diagonal, see :func:`verify_nesting`). Default: the class's defaults.
    components : {"single", "separate"}
        ``"single"`` (default): the input must be one closed piece. ``"separate"``: one hierarchy per
        disjoint closed piece; the return value is then a *list* with one ``build_cages`` result per
        piece (see :func:`cagegen.components.build_cages_per_component`).
    audit : MeshAudit, optional
        A passed audit of exactly ``(V, F)`` (``check_mesh(V, F, return_audit=True)``, after any repair),
        from a caller that audited the input already: the input is then not audited again (nor repaired),
        and the verifier does not repeat its exact self-intersection test.
    **opts
        Instead of ``options``: its fields by name (``build_cages(V, F, 3, "sdf", c=0.02)`` is
        ``options=SdfOptions(c=0.02)``); validated by the class, unknown names refused.

    Returns
    -------
    layers : list of (V_i, F_i)
        ``V_i`` (n_i,3) float64, ``F_i`` (m_i,3) int64; ``layers[0]`` is the audited input.
    info : dict
        Only with ``return_info=True``: ``method``, ``face_counts``, ``audit`` (input audit),
        ``backend`` (the backend's own info), ``verification`` (:meth:`NestingReport.to_dict` or None),
        ``nested`` (bool or None), ``certified`` (bool), ``seconds`` per stage. JSON-serialisable if
        the backend's info is.

    Raises
    ------
    MeshInputError
        The input surface is unusable (the message names each problem).
    LevelsError
        ``levels`` / ``face_counts`` cannot be met.
    BackendUnavailableError
        The method's optional dependency is missing.
    CageError
        The backend failed, or (certified methods) a layer does not nest; ``.layer`` names it.
    """
    options = _options(method, options, opts)
    if components == "separate":
        from .components import build_cages_per_component

        if audit is not None:
            raise CageOptionError("audit= is the audit of one piece: not with components='separate'")
        return build_cages_per_component(
            V, F, levels, method, face_counts=face_counts, verify=verify, return_info=return_info,
            progress=progress, repair=options.repair, options=dataclasses.replace(options, repair=False),
        )
    if components != "single":
        raise CageOptionError(f"components must be 'single' or 'separate', got {components!r}")
    t0 = time.perf_counter()
    report_to = _reporter(progress)
    say = report_to if report_to is not None else (lambda msg: None)
    _budget_first(method, options, F, face_counts, levels)
    V, F, audit, given = _audited_input(V, F, audit, options.repair)
    t_audit = time.perf_counter() - t0
    say(f"input: {V.shape[0]} vertices, {F.shape[0]} faces, audit ok "
        f"({'passed in' if given else f'{t_audit:.2f} s'})")
    face_counts = _face_counts(face_counts, levels, int(F.shape[0]))
    min_gap = float(options.min_gap or 0.0)
    say(f"{method}: building {len(face_counts)} cages with face counts {face_counts}")
    t1 = time.perf_counter()
    cages, backend_info = _run_backend(method, options, V, F, face_counts, verify, report_to, say)
    t_backend = time.perf_counter() - t1
    layers = [(V, F)] + _checked_cages(method, cages, len(face_counts))
    report = None
    t_verify = 0.0
    if verify:
        t2 = time.perf_counter()
        report = verify_nesting(layers, min_gap=min_gap, audited=(0,))  # layer 0: the audited input
        t_verify = time.perf_counter() - t2
        say(f"verification: {'nested' if report.ok else 'NOT nested'} ({t_verify:.2f} s)")
        if method not in UNCERTIFIED_METHODS:
            report.raise_if_failed()
    if not return_info:
        return layers
    info = {
        "method": method,
        "face_counts": [int(c) for c in face_counts],
        "achieved_face_counts": [int(Fk.shape[0]) for _, Fk in layers[1:]],
        "audit": audit.to_dict(),
        "backend": backend_info,
        "verification": None if report is None else report.to_dict(),
        "nested": None if report is None else bool(report.ok),
        "certified": bool(report is not None and report.ok and method not in UNCERTIFIED_METHODS),
        "seconds": {"audit": t_audit, "backend": t_backend, "verify": t_verify,
                    "total": time.perf_counter() - t0},
    }
    return layers, info


def _budget_first(method: str, options: CageOptions, F, face_counts, levels: int | None) -> None:
    """The backend's time-budget check (registry ``budget``) on the input's face count as given, before
    the audit: a run the budget refuses fails in milliseconds, not after the exact self-intersection test
    (seconds to a minute at 200-350k faces, ``benchmarks/results/audit``). An unusable ``F`` or face count
    is left to the audit and :func:`_face_counts`, which say what is wrong."""
    check = get_budget(method)
    try:
        shape = np.shape(F)
        if check is None or shape[1:] != (3,):
            return
        counts = _face_counts(face_counts, levels, int(shape[0]))
    except (ValueError, TypeError):  # LevelsError is a ValueError; a ragged F is the audit's to name
        return
    check(int(shape[0]), counts, **options.backend_kwargs())


def _audited_input(V, F, audit: MeshAudit | None,
                   repair: bool) -> tuple[np.ndarray, np.ndarray, MeshAudit, bool]:
    """The input as float64 / int64 copies and its audit: the caller's (checked to be a passed audit of
    arrays of this size, its exact self-intersection test included) or :func:`check_mesh`'s."""
    if audit is None:
        return (*check_mesh(V, F, repair=repair, name="input", return_audit=True), False)
    if not isinstance(audit, MeshAudit):
        raise CageOptionError(f"audit must be a cagegen.MeshAudit, got {type(audit).__name__}")
    V, F = as_mesh_arrays(V, F, "input")
    size = (audit.n_vertices, audit.n_faces) == (len(V), len(F))
    if not (audit.ok and audit.n_self_intersections == 0 and size):
        raise CageOptionError(f"audit= must be a passed audit (self-intersections tested) of this input's "
                              f"{len(V)} vertices and {len(F)} faces; got {audit!r}")
    return V, F, audit, True


def _reporter(progress) -> Callable[[str], None] | None:
    """``progress`` as a message callable: True prints to stderr, None / False is silent (None)."""
    if progress is None or progress is False:
        return None
    if progress is True:
        return lambda msg: print(f"[cagegen] {msg}", file=sys.stderr, flush=True)
    if callable(progress):
        return progress
    raise CageTypeError(f"progress must be a bool or a callable, got {type(progress).__name__}")


def _face_counts(face_counts, levels: int | None, n_faces: int) -> list[int]:
    """The cages' face counts: the default 4x per level, or the caller's, checked against ``levels``."""
    if face_counts is None:
        if levels is None:
            raise LevelsError("give levels (number of layers, input included) or face_counts")
        face_counts = default_face_counts(n_faces, levels)
    else:
        face_counts = check_face_counts(face_counts, n_faces)
        if levels is not None and len(face_counts) != levels - 1:
            raise LevelsError(
                f"levels={levels} needs {levels - 1} face counts (input excluded), got {len(face_counts)}"
            )
    if not face_counts:
        raise LevelsError("no cage requested (levels must be >= 2)")
    return face_counts


def _run_backend(method: str, options: CageOptions, V: np.ndarray, F: np.ndarray, face_counts: list[int],
                 verify: bool, report_to, say: Callable[[str], None]) -> tuple[list, dict]:
    """The registered backend on the audited input: the keywords its spec takes, then its own loop or
    :func:`_layer_loop` (after its schedule). The backend gets copies: it may not modify layer 0."""
    spec = backend_spec(method)
    backend = get_backend(method)
    kwargs = options.backend_kwargs()
    min_gap = float(options.min_gap or 0.0)
    if report_to is not None and "progress" in spec.takes:
        kwargs["progress"] = report_to
    if min_gap > 0 and "min_gap" in spec.takes:
        kwargs["min_gap"] = min_gap  # the backend must build the clearance the verifier will demand
    if verify and "certify" in spec.takes:
        kwargs["certify"] = False  # the whole hierarchy is verified afterwards: once is enough
    if not spec.layer:
        return backend(V.copy(), F.copy(), list(face_counts), **kwargs)
    schedule = get_schedule(method)
    # the whole run checked before any layer (e.g. sdf's time budget)
    plan = None if schedule is None else schedule(V, F, list(face_counts), t0=time.perf_counter(), **kwargs)
    return _layer_loop(method, backend, V.copy(), F.copy(), list(face_counts), kwargs, say, plan)


def _checked_cages(method: str, cages, n_expected: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The backend's cages as float64 / int64 arrays; :class:`CageError` naming a missing or invalid one."""
    cages = list(cages)
    if len(cages) != n_expected:
        raise CageError(f"backend {method!r} returned {len(cages)} layers for {n_expected} face counts",
                        layer=min(len(cages), n_expected) + 1)
    out = []
    for k, layer in enumerate(cages, start=1):
        try:
            Vk, Fk = layer
            Vk, Fk = as_mesh_arrays(Vk, Fk, f"layer {k}")
        except (MeshInputError, TypeError, ValueError) as exc:
            raise CageError(f"backend {method!r} returned an invalid layer {k}: {exc}", layer=k) from exc
        out.append((Vk, Fk))
    return out

