"""Typed options of the cage backends: one frozen dataclass per backend, validated on construction.

Every length is relative to the bounding-box diagonal of the input surface (the first layer) unless the
field's help says otherwise (``sdf``'s lengths in units of its iso-value ``c``, ``skeleton``'s in units of
an inscribed radius, ``*_abs`` in the input's units). :func:`cagegen.build_cages` turns its keyword
options into the method's class (:func:`cage_options`), so an unknown or ill-typed option fails at once,
before the audit, with a one-line :class:`cagegen.CageOptionError`.

``field_spec`` / :func:`check_fields` are the small declarative validator the classes share (also used
by :mod:`nestmg.options`): each field carries ``help`` and its bounds or choices in its metadata.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from .errors import CageError, CageOptionError, NestmgError

__all__ = [
    "CageOptions",
    "DecimateOptions",
    "LazyOptions",
    "NestedOptions",
    "OptionFieldError",
    "SdfOptions",
    "SkeletonOptions",
    "cage_options",
    "check_fields",
    "field_spec",
]

_SDF_TIME_BUDGET = 900.0  # cagegen.sdf.backend.DEFAULT_TIME_BUDGET (not imported: igl / ipctk stay lazy)
_NESTED_TIME_BUDGET = 900.0  # cagegen.nested.backend.DEFAULT_TIME_BUDGET (likewise)


def check_time_budget(estimate: float, budget: float | None, what: str) -> None:
    """Raise :class:`CageError` (layer 1, reason ``"time budget"``) when a backend's ``estimate`` of its
    seconds exceeds ``cage_time_budget`` (None: no limit), before any work. ``what`` says what was asked
    and what was estimated; the message, ``"{what} exceeds cage_time_budget=..."``, names the ways out."""
    if budget is not None and estimate > float(budget):
        raise CageError(
            f"{what} exceeds cage_time_budget={float(budget):.0f} s; pass a larger cage_time_budget (None: no "
            f"limit; nestmg CLI: --cage-time-budget, 0: no limit), or decimate the input first (nestmg solve and "
            f"build_hierarchy do: SizingOptions(predecimate=True))", layer=1, reason="time budget")


class OptionFieldError(CageOptionError):
    """One field of an options dataclass is invalid; ``field`` names it, ``problem`` says what is wrong."""

    def __init__(self, owner: str, field: str, problem: str):
        super().__init__(f"{owner}.{field}: {problem}")
        self.owner, self.field, self.problem = owner, field, problem


def field_spec(default: Any, help: str, *, low: float | None = None, strict: bool = False,
               high: float | None = None, choices: tuple | None = None, kind: type | None = None,
               optional: bool = False, cli: bool = True, expert: bool = False) -> Any:
    """A dataclass field with its validation rule and help text in ``metadata``.

    Parameters
    ----------
    default
        Default value (None allowed: the field is then optional).
    help : str
        One line for ``--help`` and the docs.
    low, strict, high
        Numeric bounds: ``value > low`` if ``strict`` else ``value >= low``; ``value < high``.
    choices : tuple, optional
        Allowed values.
    kind : type, optional
        ``int``, ``float``, ``bool`` or ``str`` (default: the type of ``default``).
    optional : bool
        None is allowed (always when the default is None or None is among ``choices``).
    cli : bool
        Whether the command line offers it (:func:`nestmg.options.add_arguments`).
    expert : bool
        A tuning knob: its flag is listed by ``--help-all`` only, not by ``--help``.
    """
    kind = kind or (type(default) if default is not None else None)
    optional = optional or default is None or (choices is not None and None in choices)
    meta = {"help": help, "low": low, "strict": strict, "high": high, "choices": choices, "kind": kind,
            "cli": cli, "optional": optional, "expert": expert}
    return dataclasses.field(default=default, metadata=meta)


def _problem(value: Any, meta: dict, optional: bool) -> str | None:
    """What is wrong with ``value`` under the rule ``meta`` (None: nothing)."""
    if value is None:
        return None if optional else "must not be None"
    if meta["choices"] is not None:
        return None if value in meta["choices"] else f"must be one of {list(meta['choices'])}, got {value!r}"
    kind = meta["kind"]
    if kind is bool and not isinstance(value, (bool, np.bool_)):
        return f"must be True or False, got {value!r}"
    if kind in (int, float):
        ok = isinstance(value, (int, np.integer) if kind is int else (int, float, np.number))
        if not ok or isinstance(value, (bool, np.bool_)):
            return f"must be {'an integer' if kind is int else 'a number'}, got {value!r}"
        low, high = meta["low"], meta["high"]
        finite = math.isfinite(float(value))
        if low is not None and (not finite or (value <= low if meta["strict"] else value < low)):
            return f"must be {'>' if meta['strict'] else '>='} {low:g}, got {value!r}"
        if high is not None and (not finite or not value < high):
            return f"must be < {high:g}, got {value!r}"
        if not finite:
            return f"must be finite, got {value!r}"
    if kind is str and not isinstance(value, str):
        return f"must be a string, got {value!r}"
    return None


def check_fields(obj: Any, error: type[NestmgError] | None = None) -> None:
    """Validate every field of the dataclass ``obj`` against its :func:`field_spec` metadata.

    Raises
    ------
    OptionFieldError
        (or ``error(owner, field, problem)``) for the first invalid field, in one line.
    """
    error = error or OptionFieldError
    for f in fields(obj):
        if "help" not in f.metadata:
            continue
        problem = _problem(getattr(obj, f.name), f.metadata, optional=f.metadata["optional"])
        if problem is not None:
            raise error(type(obj).__name__, f.name, problem)


@dataclass(frozen=True)
class CageOptions:
    """Options every cage method takes (:func:`cagegen.build_cages`)."""

    repair: bool = field_spec(False, "merge duplicate vertices, drop unreferenced ones, flip STL caps and "
                                     "orient outward before the audit (nestmg: an input with overlapping "
                                     "bodies, self-intersections or pinches becomes the boundary of the "
                                     "solid TetWild meshes)")
    min_gap: float | None = field_spec(None, "clearance between consecutive layers / bbox diagonal (default "
                                             "0; nestmg: 2.5 epsilon under TetWild)", low=0.0, kind=float,
                                       expert=True)

    #: fields build_cages consumes itself (not passed to the backend)
    COMMON = ("repair", "min_gap")

    def __post_init__(self) -> None:
        check_fields(self)

    def backend_kwargs(self) -> dict[str, Any]:
        """The backend's keyword arguments: every field but :attr:`COMMON`."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.COMMON}


@dataclass(frozen=True)
class DecimateOptions(CageOptions):
    """``"decimate"``: the naive baseline (:func:`cagegen.decimate.decimate_layer`)."""

    decimator: str = field_spec("qslim", "decimator tried first (libigl's qslim or decimate)",
                                choices=("qslim", "shortest_edge"))
    block_intersections: bool = field_spec(False, "refuse collapses that create self-intersections")
    check_self: bool = field_spec(True, "check each layer for self-intersections")


@dataclass(frozen=True)
class NestedOptions(CageOptions):
    """``"nested"``: flow + re-inflation (Sacht et al. 2015; :func:`cagegen.nested.nested_backend`)."""

    energy: str = field_spec("volume", "cage energy once the fine surface is at rest",
                             choices=("volume", "step", "surface_arap", "volumetric_arap"))
    quad_order: int = field_spec(2, "quadrature degree of the flow", low=1)
    min_gap_abs: float | None = field_spec(None, "min_gap in the input's units (overrides min_gap)", low=0.0,
                                           kind=float)
    decimate_from: str = field_spec("previous", "decimate the previous layer or the input",
                                    choices=("previous", "input"))
    decimator: str = field_spec("qslim", "decimator tried first (libigl's qslim or decimate)",
                                choices=("qslim", "shortest_edge"))
    max_recovery_depth: int = field_spec(2, "intermediate layers allowed when recovering", low=0)
    fallback: str | None = field_spec("sdf", "last resort when the flow fails", choices=("sdf", "lazy", None))
    target_offset: float | None = field_spec(None, "offset of the second target's envelope / diagonal "
                                                   "(default: from min_gap)", low=0.0, kind=float)
    flow_step: float = field_spec(1e-3, "flow step / diagonal", low=0.0, strict=True)
    flow_max_iter: int = field_spec(1000, "flow iterations at most", low=1)
    dhat: float = field_spec(5e-3, "barrier activation distance / diagonal", low=0.0, strict=True)
    kappa: float = field_spec(1e4, "barrier stiffness while re-inflating", low=0.0, strict=True)
    dhat_final: float = field_spec(1e-3, "final energy's barrier distance / diagonal", low=0.0, strict=True)
    kappa_final: float = field_spec(1e3, "barrier stiffness of the final energy", low=0.0, strict=True)
    max_move: float = field_spec(5e-3, "largest vertex move per re-inflation step / diagonal", low=0.0,
                                 strict=True)
    final_iters: int = field_spec(60, "iterations of the final energy", low=0)
    cage_threads: int | None = field_spec(None, "threads of the contact library (ipctk); 1: the same cages "
                                                "every run (default: all cores, faster)", low=1, kind=int)
    cage_time_budget: float | None = field_spec(
        _NESTED_TIME_BUDGET, "wall-clock seconds the nested cages may take, estimated before any work (None: "
                             "no limit)", low=0.0, kind=float, optional=True)


@dataclass(frozen=True)
class SdfOptions(CageOptions):
    """``"sdf"``: SDF envelope, constrained QEM, barrier optimisation (Qiu et al. 2024; ``sdf_cage_layer``).

    ``c``, ``h``, ``r``, ``l`` and ``1/beta`` are relative to the input's diagonal; ``margin``,
    ``spacing``, ``dhat``, ``hug``, ``hug_dhat``, ``tighten`` are in units of ``c``; ``hug_radius`` in
    units of ``r`` (the module :mod:`cagegen.sdf.backend` explains those beyond the paper).
    """

    c: float = field_spec(0.01, "envelope iso-value / diagonal", low=0.0, strict=True)
    h: float | None = field_spec(None, "grid spacing / diagonal (default c, refined for small targets)",
                                 low=0.0, strict=True, kind=float)
    amplify: bool = field_spec(True, "local amplification near nearly-touching parts (paper eqs. 2-3)")
    r: float = field_spec(0.025, "amplification radius / diagonal", low=0.0, strict=True)
    l: float = field_spec(0.15, "amplification length / diagonal", low=0.0, strict=True)  # noqa: E741
    alpha: float = field_spec(3.0, "amplification exponent", low=0.0)
    beta: float = field_spec(8.0, "amplification sharpness (1/beta / diagonal)", low=0.0, strict=True)
    margin: float = field_spec(0.3, "clearance of the simplification on the distance grid, units of c",
                               low=0.0)
    optimize: bool = field_spec(True, "run the barrier-protected optimisation")
    spacing: float = field_spec(0.5, "target cage spacing of the optimisation, in units of c", low=0.0,
                                strict=True)
    dhat: float = field_spec(0.25, "barrier activation distance, in units of c", low=0.0, strict=True)
    opt_iters: int = field_spec(15, "descent steps per round", low=0)
    flip_rounds: int = field_spec(1, "rounds of edge flips", low=0)
    opt_time_limit: float = field_spec(30.0, "CPU seconds of the descent", low=0.0)
    pull: float = field_spec(50.0, "weight of the input-to-cage pull (0: off)", low=0.0)
    prepass: bool = field_spec(True, "allow the plain-QEM pre-pass")
    max_retries: int = field_spec(3, "rebuilds with c doubled", low=0)
    hug: float = field_spec(0.1, "spacing target near active points, in units of c (0: off)", low=0.0)
    hug_radius: float = field_spec(1.0, "falloff radius of hug, in units of r", low=0.0)
    hug_dhat: float = field_spec(0.05, "barrier distance with hug, in units of c", low=0.0, strict=True)
    tighten: float = field_spec(1.5, "tightening target, in units of c (0: off)", low=0.0)
    tighten_rounds: int = field_spec(3, "tightening rounds at most", low=0)
    bridge_retry: float = field_spec(0.5, "rebuild at c * bridge_retry when the envelope bridged a concavity "
                                          "(0: off)", low=0.0)
    cage_time_budget: float | None = field_spec(
        _SDF_TIME_BUDGET, "wall-clock seconds the sdf cages may take, estimated before any work (None: no "
                          "limit)", low=0.0, kind=float, optional=True)


@dataclass(frozen=True)
class SkeletonOptions(CageOptions):
    """``"skeleton"``: cages that follow a curve skeleton (Casti et al. 2019; ``skeleton_cage``).

    ``skeleton`` (a :class:`cagegen.skeleton.Skeleton`, path or arrays) must be in the frame of the surface
    given to :func:`cagegen.build_cages` (nestmg's normalised frame under :func:`nestmg.build_hierarchy`).
    """

    skeleton: Any = field_spec(None, "curve skeleton inside the input (None: extracted, needs pygel3d)",
                               kind=object, cli=False)
    bending: Any = field_spec("auto", "'auto', 'given' or node indices", kind=object, cli=False)
    n_seeds: int = field_spec(20, "seeds per section", low=1)
    seed_radius: float = field_spec(0.2, "seed circle radius, in units of the section's inscribed radius",
                                    low=0.0, strict=True)
    tet_edge_length: float | None = field_spec(None, "field tet edge / diagonal (default from the radii)",
                                               low=0.0, strict=True, kind=float)
    preinflate_rounds: int = field_spec(3, "pre-inflation rounds", low=0)
    drop_bad_sections: bool = field_spec(True, "drop a bending node whose section breaks the junction hull")
    relocate_sections: bool = field_spec(True, "move sections that few integral lines reach")
    symmetry: Any = field_spec(None, "None, 'auto' or (point, normal)", kind=object, cli=False)
    skeleton_cache: Any = field_spec(None, "None ($NESTMG_CACHE/skeleton), False or a path", kind=object,
                                     cli=False)
    untangle: bool = field_spec(True, "flatten degenerate or crossing sections before each assembly")
    containment: str = field_spec("mesh", "how the cage comes to contain M: mesh (M swept down the guiding "
                                          "field, re-inflated) or flow (the Nested Cages flow)",
                                  choices=("mesh", "flow"))
    nested_face_counts: str = field_spec("above", "how the finer nested layers are sized")


@dataclass(frozen=True)
class LazyOptions(CageOptions):
    """``"lazy"``: SDF offset + decimation + binary search (gpytoolbox, GPL; ``copyleft.lazy.lazy_layer``)."""

    grid_size: int = field_spec(50, "SDF grid cells per side", low=4)
    max_iter: int = field_spec(10, "binary-search steps", low=1)
    decimator: str = field_spec("shortest_edge", "gpytoolbox's decimator (libigl's decimate or qslim)",
                                choices=("shortest_edge", "qslim"))
    self_union: bool = field_spec(True, "union the offset with itself (removes self-intersections)")


def cage_options(options_class: type[CageOptions], method: str, **opts: Any) -> CageOptions:
    """``options_class(**opts)`` with one-line :class:`CageOptionError` for unknown names.

    Parameters
    ----------
    options_class : type
        The method's class (:func:`cagegen.registry.options_class`).
    method : str
        Method name, for the message.
    **opts
        Option values by field name.
    """
    known = {f.name for f in fields(options_class)}
    unknown = sorted(set(opts) - known)
    if unknown:
        raise CageOptionError(f"unknown option(s) for the {method} backend: {unknown}")
    return options_class(**opts)
