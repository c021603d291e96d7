"""Typed options of the pipeline's stages: sizing, meshing, solving (cages: :mod:`cagegen.options`).

Frozen dataclasses, validated on construction (a bad value is a one-line :class:`OptionError`, a
:class:`nestmg.NestmgInputError`). Every length is relative to the bounding-box diagonal of the
normalised input unless its name or help says otherwise. :func:`nestmg.build_hierarchy` takes one object
per stage and records them in ``Hierarchy.options`` (``dataclasses.asdict``); the command line's flags are
generated from the same fields (:func:`add_arguments`, :func:`from_arguments`), so they cannot drift::

    h = build_hierarchy(V, F, 3, "nested", sizing=SizingOptions(max_tets=200_000),
                        meshing=MeshingOptions(mesher="tetgen"), cages=NestedOptions(energy="volume"))
    r = solve_on_hierarchy(h.tets_in("normalized"), h.P, "poisson-neumann", SolverOptions(accel="cg"))
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from cagegen.options import OptionFieldError, check_fields, field_spec
from solvers import DEFAULT_MAXITER, SMOOTHERS

from .errors import NestmgInputError
from .problems import COARSE, SMOOTHING
from .sizing import DEFAULT_TIME_BUDGET
from .tetmesh import COARSE_MAX_OPT_ITER, OUTER_EDGE_FACTOR

__all__ = ["DEFAULT_CYCLE", "DEFAULT_NU", "DEFAULT_SMOOTHER", "ELASTICITY_COARSE_NU", "ELASTICITY_CYCLE",
           "ELASTICITY_NU", "ELASTICITY_SMOOTHER", "MeshingOptions", "OptionError", "SizingOptions",
           "SolverOptions", "THREE_SWEEP_POISSON_RATIO", "add_arguments", "from_arguments"]

#: The cycle, fine-level sweeps and smoother of the scalar problems (:meth:`SolverOptions.resolved`):
#: ``MultigridSolver``'s default cycle (:data:`solvers.multilevel.DEFAULT_SMOOTHER`), two forward Gauss–Seidel
#: sweeps before the coarse correction and two backward after it on the fine level, four on coarse levels as
#: sparse as the fine one, one on dense ones (``coarse_nu`` not set).
DEFAULT_CYCLE, DEFAULT_NU, DEFAULT_SMOOTHER = "V", 2, "gauss_seidel"
#: The same for the elasticity problems (issue 32 item 2): the F-cycle, ``nu`` forward Gauss–Seidel sweeps
#: before the coarse correction and as many backward ones after it on the fine level (two, three from
#: ν = :data:`THREE_SWEEP_POISSON_RATIO`), four on the coarser levels (:data:`ELASTICITY_COARSE_NU`).
ELASTICITY_CYCLE, ELASTICITY_NU, ELASTICITY_SMOOTHER, ELASTICITY_COARSE_NU = "F", 2, "gauss_seidel", 4
#: Poisson ratio from which elasticity's fine level gets three sweeps instead of two: at ν = 0.45 two
#: took 17-22 MG-PCG iterations on fandisk (173k tets) and spot (349k), three take at most 20 for a few
#: percent more CPU seconds; at ν = 0.3 two are the faster (docs/elasticity.md).
THREE_SWEEP_POISSON_RATIO = 0.4


class OptionError(NestmgInputError):
    """One field of a nestmg options dataclass is invalid (``field`` names it, ``problem`` says what)."""

    def __init__(self, owner: str, field: str, problem: str):
        super().__init__(f"{owner}.{field}: {problem}")
        self.owner, self.field, self.problem = owner, field, problem


@dataclass(frozen=True)
class SizingOptions:
    """How large each level is (:func:`nestmg.sizing.plan_hierarchy`)."""

    edge_length: float | None = field_spec(
        None, "fine tet edge length / bbox diagonal (default: the input's mean edge, enlarged to fit "
              "max_tets and mesh_time_budget)", low=0.0, strict=True, kind=float)
    max_tets: int | None = field_spec(None, "cap on the fine level's expected tets when edge_length is not "
                                            "given (default 1.5M)", low=1, kind=int)
    mesh_time_budget: float | None = field_spec(
        DEFAULT_TIME_BUDGET, "seconds (2 cores) allowed for meshing the fine level; the fine edge grows to "
                             "fit (None: no limit)", low=0.0, kind=float, optional=True)
    coarsening: float | None = field_spec(8.0, "wanted tet ratio between consecutive cage levels (None: the "
                                               "edge length doubles)", low=1.0, strict=True, kind=float,
                                          optional=True, expert=True)
    face_counts: tuple[int, ...] | None = field_spec(
        None, "cage face counts, finest first (default: 4x fewer per level)", kind=tuple, expert=True)
    same_domain_levels: int = field_spec(0, "levels that re-mesh the input at 2x, 4x... the fine edge before "
                                            "the cages", low=0, expert=True)
    fine_level: str | None = field_spec(
        None, "refine: the fine level is a red refinement of the input meshed at twice the edge (default "
              "with TetWild); mesh: the input meshed at the fine edge (default with TetGen)",
        choices=("refine", "mesh", None), expert=True)
    predecimate: bool = field_spec(True, "with TetWild, decimate an input much finer than the fine tets "
                                         "first", expert=True)

    def __post_init__(self) -> None:
        fc = self.face_counts
        if fc is not None:  # a list is accepted and stored as a tuple (hashable, frozen)
            if isinstance(fc, (str, bytes)) or not hasattr(fc, "__iter__"):
                raise OptionError("SizingOptions", "face_counts",
                                  f"must be a sequence of integers, got {fc!r}")
            fc = tuple(fc)
            if not fc or any(isinstance(n, bool) or not isinstance(n, int) and not hasattr(n, "__index__")
                             or n < 4 for n in fc):
                raise OptionError("SizingOptions", "face_counts", f"must be integers >= 4, got {list(fc)}")
            object.__setattr__(self, "face_counts", tuple(int(n) for n in fc))
        _check(self)


@dataclass(frozen=True)
class MeshingOptions:
    """How every layer is tet-meshed and prolonged (:func:`nestmg.tetmesh.tetrahedralize`)."""

    mesher: str = field_spec("tetwild", "tet mesher (TetGen is AGPL: opt-in)", choices=("tetwild", "tetgen"))
    epsilon: float = field_spec(1e-3, "TetWild envelope / bbox diagonal", low=0.0, strict=True, high=1.0,
                                expert=True)
    extrapolation: str = field_spec("clamped", "rule for fine nodes outside the coarse tets",
                                    choices=("clamped", "linear", "closest_point", "nearest_vertex"),
                                    expert=True)
    tet_retries: int | None = field_spec(
        None, "re-mesh a coarse TetWild layer with a 4x smaller envelope while fine nodes are outside it "
              "(default 2; 0 for decimate)", low=0, kind=int, expert=True)
    stop_energy: float = field_spec(10.0, "TetWild's stop energy", low=0.0, strict=True, expert=True)
    max_opt_iter: int = field_spec(80, "TetWild's optimisation passes at most", low=1, expert=True)
    outer_edge_factor: float = field_spec(
        OUTER_EDGE_FACTOR, "TetWild's edge outside the solid / the target edge, where its box is >= 8x the "
                           "solid's volume (1: off, fTetWild's uniform sizing)", low=1.0, expert=True)
    threads: int | None = field_spec(None, "TetWild threads (default: its own)", low=0, kind=int, expert=True)
    coarsen_coarse: bool = field_spec(True, "TetWild's coarsen on the coarse levels", expert=True)
    coarse_max_opt_iter: int = field_spec(
        COARSE_MAX_OPT_ITER, "TetWild's optimisation passes at most on the cage levels (the smaller of "
                             "this and max_opt_iter)", low=1, expert=True)

    def __post_init__(self) -> None:
        _check(self)

    def tetwild_kwargs(self) -> dict[str, Any]:
        """The TetWild keywords of :func:`nestmg.tetmesh.tetrahedralize` these options set."""
        kw = {"stop_energy": self.stop_energy, "max_opt_iter": self.max_opt_iter,
              "outer_edge_factor": self.outer_edge_factor}
        return kw if self.threads is None else {**kw, "threads": self.threads}


@dataclass(frozen=True)
class SolverOptions:
    """The model problem's solver (:func:`nestmg.solve_on_hierarchy`, :meth:`nestmg.Problem.multigrid`).

    ``coarse``, ``lam`` and ``poisson_ratio`` set up the problem (:func:`nestmg.setup_problem`); the
    smoothing fields build the :class:`solvers.MultigridSolver`; ``cycle`` ... ``maxiter`` are the solve's.
    ``nu`` and ``cycle`` default to None, "not set": :meth:`resolved` fills them in for the problem at hand
    (the one place that rule lives); a value the caller gives always wins.
    """

    coarse: str = field_spec("galerkin", "coarse operators", choices=tuple(COARSE), expert=True)
    smoothing: str = field_spec("robust", "preset: robust (smoother / nu / coarse_nu below, boundary-layer "
                                          "sweeps) or fast (textbook V(1,1))", choices=SMOOTHING, expert=True)
    smoother: str | None = field_spec(None, "smoother (robust preset; default gauss_seidel: forward before, "
                                            "backward after the coarse correction)",
                                      choices=(*sorted(SMOOTHERS), None), expert=True)
    nu: int | None = field_spec(None, "pre/post smoothing sweeps on the fine level (robust preset; default "
                                      "2; elasticity 3 at ν >= 0.4)", low=1, kind=int, expert=True)
    coarse_nu: int | None = field_spec(None, "sweeps on the coarser levels (default 2 nu, 1 on dense levels of "
                                             "the default cycle; elasticity 4)",
                                       low=1, kind=int, expert=True)
    local: bool = field_spec(True, "extra sweeps on the boundary layer of Neumann and diffusion problems",
                             expert=True)
    coarse_scaling: str | None = field_spec("auto", "auto: energy for re-discretised and weighted operators",
                                            choices=("auto", "energy", None), expert=True)
    cycle: str | None = field_spec(None, "multigrid cycle (default V, F for elasticity)",
                                   choices=("V", "W", "F", None), expert=True)
    accel: str | None = field_spec(None, "cg: MG-preconditioned CG", choices=("cg", None))
    tol: float = field_spec(1e-8, "relative residual to reach", low=0.0, strict=True)
    maxiter: int = field_spec(DEFAULT_MAXITER, "cap on cycles (or CG iterations)", low=1)
    lam: float = field_spec(1e-2, "λ of diffusion-neumann", low=0.0, strict=True)
    poisson_ratio: float = field_spec(0.3, "ν of the elasticity problems, in (-1, 0.5)", low=-1.0,
                                      strict=True, high=0.5)

    def __post_init__(self) -> None:
        _check(self)
        given = self.smoother not in (None, DEFAULT_SMOOTHER) or self.nu not in (None, DEFAULT_NU)
        if self.smoothing == "fast" and (given or self.coarse_nu is not None):
            raise OptionError("SolverOptions", "smoothing", "'fast' is a preset: leave smoother, nu and "
                                                            "coarse_nu at their defaults")

    def resolved(self, problem: str | None = None, poisson_ratio=None) -> SolverOptions:
        """These options with ``smoother``, ``nu`` and ``cycle`` set for ``problem`` (given fields are kept).

        Not set, they are :data:`DEFAULT_SMOOTHER`, :data:`DEFAULT_NU` and :data:`DEFAULT_CYCLE` (the
        V-cycle, two forward / backward Gauss–Seidel sweeps on the fine level; ``coarse_nu`` stays None:
        ``MultigridSolver``'s default rule below), except for an
        elasticity problem under the ``"robust"`` preset: :data:`ELASTICITY_SMOOTHER`,
        :data:`ELASTICITY_CYCLE`, ``nu`` = :data:`ELASTICITY_NU` (two forward sweeps before the coarse
        correction, two backward after it), three from ν = :data:`THREE_SWEEP_POISSON_RATIO`, and
        ``coarse_nu`` = :data:`ELASTICITY_COARSE_NU` whatever ``nu``. Measured under CG on fandisk and spot
        (docs/elasticity.md): fewer iterations and fewer CPU seconds than that V-cycle at ν = 0.3 and 0.45.

        Parameters
        ----------
        problem : str, optional
            The model problem's name (None: no problem context, the plain defaults).
        poisson_ratio : float or array of float, optional
            The elasticity problem's ν (default :attr:`poisson_ratio`); per-tet values: their maximum.

        Returns
        -------
        SolverOptions
            ``smoother``, ``nu`` and ``cycle`` not None (and ``coarse_nu`` for elasticity); ``self`` when
            nothing was left to fill in.
        """
        from .elasticity import ELASTICITY_PROBLEMS

        el = problem in ELASTICITY_PROBLEMS and self.smoothing == "robust"
        if None not in (self.smoother, self.nu, self.cycle) and not (el and self.coarse_nu is None):
            return self
        if el:
            ratio = float(np.max(self.poisson_ratio if poisson_ratio is None else poisson_ratio))
            nu = ELASTICITY_NU + (ratio >= THREE_SWEEP_POISSON_RATIO)
            defaults = (ELASTICITY_SMOOTHER, nu, ELASTICITY_CYCLE, ELASTICITY_COARSE_NU)
        else:
            defaults = (DEFAULT_SMOOTHER, DEFAULT_NU, DEFAULT_CYCLE, None)
        given = (self.smoother, self.nu, self.cycle, self.coarse_nu)
        smoother, nu, cycle, coarse_nu = (g if g is not None else d for g, d in zip(given, defaults))
        return dataclasses.replace(self, smoother=smoother, nu=nu, cycle=cycle, coarse_nu=coarse_nu)


def _check(obj: Any) -> None:
    try:
        check_fields(obj)
    except OptionFieldError as exc:
        raise OptionError(exc.owner, exc.field, exc.problem) from None


def typed(value: Any, cls: type, name: str) -> Any:
    """``value`` if it is a ``cls``, ``cls()`` (the defaults) for None; a one-line error otherwise.

    Raises
    ------
    NestmgInputError
        ``"{name} must be a nestmg.{cls}, got {type}"``.
    """
    if value is None:
        return cls()
    if not isinstance(value, cls):
        raise NestmgInputError(f"{name} must be a nestmg.{cls.__name__}, got {type(value).__name__}")
    return value


def as_dict(obj: Any) -> dict[str, Any]:
    """``dataclasses.asdict(obj)`` with tuples as lists (the JSON of ``Hierarchy.options``)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(obj).items()}


# ----------------------------------------------------------------------------- command line


def flag(name: str) -> str:
    """The command-line flag of the field ``name`` (``mesh_time_budget`` -> ``--mesh-time-budget``)."""
    return "--" + name.replace("_", "-")


def add_arguments(group: Any, cls: type, *, skip: tuple = (), defaults: dict | None = None) -> None:
    """Add one flag per field of ``cls`` (with ``cli`` metadata) to an argparse group.

    Booleans that default to True become ``--no-NAME``; ``None`` defaults are written ``none``; a
    tuple field takes several values. Values are checked by ``cls`` itself (:func:`from_arguments`).
    Each flag's action carries the field's ``expert`` marker (``action.expert``: listed by ``--help-all``
    only, see :mod:`nestmg.cli`).
    """
    for f in fields(cls):
        meta = f.metadata
        if not meta.get("cli", False) or f.name in skip:
            continue
        default = (defaults or {}).get(f.name, f.default)
        helptext = meta["help"] + ("" if default is None else f" (default {default})")
        if meta["kind"] is bool:
            if default:
                action = group.add_argument(f"--no-{f.name.replace('_', '-')}", dest=f.name,
                                            action="store_false", help=f"do not: {meta['help']}")
            else:
                action = group.add_argument(flag(f.name), dest=f.name, action="store_true", help=meta["help"])
        else:
            kw: dict[str, Any] = {"dest": f.name, "default": default, "help": helptext}
            if meta["kind"] is tuple:
                kw.update(type=_parse(int), nargs="+")
            elif meta["choices"] is not None:
                kw.update(type=_parse_choice(meta["choices"]), choices=meta["choices"],
                          metavar="{" + ",".join(str(c).lower() for c in meta["choices"]) + "}")
            else:
                kw["type"] = _parse(meta["kind"])
            action = group.add_argument(flag(f.name), **kw)
        action.expert = bool(meta.get("expert", False))


def _parse(kind: type):
    """An argparse ``type``: ``kind`` (int, float, str), or None for ``none``."""

    def parse(text: str):
        if text.lower() == "none":
            return None
        try:
            return kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None

    return parse


def _parse_choice(choices: tuple):
    """An argparse ``type`` for a field with ``choices``: the choice that ``text`` names in any case
    (``--cycle w`` is ``"W"``), None for ``none``; other text is returned for argparse to refuse."""
    by_lower = {str(c).lower(): c for c in choices if c is not None}

    def parse(text: str):
        if text.lower() == "none":
            return None
        return by_lower.get(text.lower(), text)

    return parse


def from_arguments(cls: type, args: argparse.Namespace, **fixed: Any) -> Any:
    """``cls`` from the parsed flags of :func:`add_arguments` (fields without a flag keep their defaults)."""
    values = {f.name: getattr(args, f.name) for f in fields(cls) if hasattr(args, f.name)}
    return cls(**{**values, **fixed})
