"""Typed options per stage (issue 28): validation, defaults that match the code they configure, the command
line generated from the same fields, and ``Hierarchy.options`` / the cache keyed on them."""

from __future__ import annotations

import dataclasses
import inspect
import json

import numpy as np
import pytest

import cagegen
from cagegen import (
    CageOptionError,
    CageOptions,
    DecimateOptions,
    LazyOptions,
    NestedOptions,
    SdfOptions,
    SkeletonOptions,
    build_cages,
    options_class,
)
from nestmg import (
    MeshingOptions,
    NestmgInputError,
    OptionError,
    SizingOptions,
    SolverOptions,
    build_hierarchy,
    shapes,
)

# backend keywords that build_cages passes itself (not options) or that only the backend's own callers use
_NOT_OPTIONS = {"progress", "certify", "min_gap", "unit", "deadline", "check_input", "inner"}


def _keyword_defaults(fn) -> dict:
    return {p.name: p.default for p in inspect.signature(fn).parameters.values()
            if p.default is not inspect.Parameter.empty and p.name not in _NOT_OPTIONS}


def _fields(cls) -> dict:
    return {f.name: f.default for f in dataclasses.fields(cls) if f.name not in CageOptions.COMMON}


def test_cage_options_match_the_backends_keywords():
    """Every backend keyword is a field with the same default, and no field is unknown to the backend."""
    from cagegen.decimate import decimate_layer
    from cagegen.nested.backend import _DEFAULTS, nested_backend
    from cagegen.sdf.backend import sdf_cage_layer
    from cagegen.skeleton.backend import skeleton_backend, skeleton_cage

    assert _fields(DecimateOptions) == _keyword_defaults(decimate_layer)
    assert _fields(NestedOptions) == {**_keyword_defaults(nested_backend), **_DEFAULTS}
    # the layer's own functions repeat the re-inflation defaults in their signatures (for direct callers):
    # the same values as the options, or a default would differ by entry point
    from cagegen.nested.backend import nest_pair
    from cagegen.nested.reinflate import reinflate

    for fn in (nest_pair, reinflate):
        own = _keyword_defaults(fn)
        shared = own.keys() & _DEFAULTS.keys()
        assert {k: own[k] for k in shared} == {k: _DEFAULTS[k] for k in shared}, fn.__name__
        assert len(shared) >= 6, fn.__name__
    assert _fields(SdfOptions) == _keyword_defaults(sdf_cage_layer)
    assert _fields(SkeletonOptions) == {**_keyword_defaults(skeleton_cage),
                                        **_keyword_defaults(skeleton_backend)}
    lazy = pytest.importorskip("cagegen.copyleft.lazy")
    assert _fields(LazyOptions) == _keyword_defaults(lazy.lazy_layer)


def test_registry_gives_each_method_its_class():
    for name, cls in (("decimate", DecimateOptions), ("nested", NestedOptions), ("sdf", SdfOptions),
                      ("skeleton", SkeletonOptions), ("lazy", LazyOptions)):
        assert options_class(name) is cls
    with pytest.raises(cagegen.UnknownMethodError):
        options_class("magic")


@pytest.mark.parametrize("make, message", [
    (lambda: NestedOptions(energy="rubber"), "NestedOptions.energy: must be one of"),
    (lambda: SdfOptions(c=0.0), "SdfOptions.c: must be > 0, got 0.0"),
    (lambda: SdfOptions(opt_iters=2.5), "SdfOptions.opt_iters: must be an integer"),
    (lambda: CageOptions(min_gap=-1e-3), "CageOptions.min_gap: must be >= 0"),
    (lambda: DecimateOptions(check_self="yes"), "DecimateOptions.check_self: must be True or False"),
    (lambda: SizingOptions(edge_length=float("inf")), "SizingOptions.edge_length: must be > 0, got inf"),
    (lambda: SizingOptions(face_counts=[100, 2]), "SizingOptions.face_counts: must be integers >= 4"),
    (lambda: SizingOptions(max_tets=0), "SizingOptions.max_tets: must be >= 1"),
    (lambda: MeshingOptions(epsilon=1.5), "MeshingOptions.epsilon: must be < 1"),
    (lambda: MeshingOptions(mesher="gmsh"), "MeshingOptions.mesher: must be one of ['tetwild', 'tetgen']"),
    (lambda: SolverOptions(nu=0), "SolverOptions.nu: must be >= 1, got 0"),
    (lambda: SolverOptions(poisson_ratio=0.5), "SolverOptions.poisson_ratio: must be < 0.5"),
    (lambda: SolverOptions(smoother="magic"), "SolverOptions.smoother: must be one of"),
])
def test_bad_fields_are_one_line_errors_naming_the_field(make, message):
    with pytest.raises((CageOptionError, OptionError)) as ei:
        make()
    assert message in str(ei.value) and "\n" not in str(ei.value)
    assert isinstance(ei.value, ValueError) and isinstance(ei.value, cagegen.NestmgError)
    if isinstance(ei.value, OptionError):
        assert isinstance(ei.value, NestmgInputError) and ei.value.field in message


def test_options_are_frozen_and_serialisable():
    o = SizingOptions(face_counts=[300, 80])
    assert o.face_counts == (300, 80)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.max_tets = 5  # type: ignore[misc]
    for obj in (o, MeshingOptions(), SolverOptions(), NestedOptions(), SdfOptions()):
        d = dataclasses.asdict(obj)
        assert type(obj)(**d) == obj
        json.dumps(d)


def test_build_cages_takes_the_class_or_its_fields_by_name():
    V, F = shapes.sphere(res=10)
    a = build_cages(V, F, 2, "decimate", face_counts=[100], decimator="shortest_edge")
    b = build_cages(V, F, 2, "decimate", face_counts=[100], options=DecimateOptions(decimator="shortest_edge"))
    for (Va, Fa), (Vb, Fb) in zip(a, b, strict=True):
        assert np.array_equal(Va, Vb) and np.array_equal(Fa, Fb)
    with pytest.raises(CageOptionError, match=r"unknown option\(s\) for the decimate backend: \['c'\]"):
        build_cages(V, F, 2, "decimate", c=0.01)
    with pytest.raises(CageOptionError, match="takes DecimateOptions, got SdfOptions"):
        build_cages(V, F, 2, "decimate", options=SdfOptions())
    with pytest.raises(CageOptionError, match="not both"):
        build_cages(V, F, 2, "decimate", options=DecimateOptions(), decimator="qslim")


def _flags(parser_name: str) -> dict:
    from nestmg.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices[parser_name]
    return {a.dest: a for a in sub._actions if a.option_strings}


def test_cli_flags_are_the_option_fields():
    """Each field of the sizing, meshing, common cage and solver options is one flag of ``nestmg solve``
    with the field's default; every other flag of those groups is listed here."""
    from nestmg.cli import CAGE_FLAGS
    from nestmg.options import flag

    actions = _flags("solve")
    for cls in (SizingOptions, MeshingOptions, CageOptions, SolverOptions):
        for f in dataclasses.fields(cls):
            a = actions.pop(f.name)
            want = f"--no-{f.name.replace('_', '-')}" if f.default is True else flag(f.name)
            assert a.option_strings == [want], (f.name, a.option_strings)
            assert a.default == f.default, (f.name, a.default, f.default)
    for owners, field in CAGE_FLAGS.values():
        for owner in owners:
            assert field in {f.name for f in dataclasses.fields(getattr(cagegen, owner))}
    others = {"help", "help_all", "problem", "method", "element", "quality", "sj_floor", "relax", "json", "png",
              "out", "levels", "cage_time_budget", "cage_threads", "no_cache", "quiet"}
    assert set(actions) == others, set(actions) ^ others


#: what ``nestmg solve --help`` lists (besides -h and --help-all); every other flag is expert
EVERYDAY = {"--problem", "--method", "--element", "--json", "--png", "--out", "--levels", "--edge-length",
            "--max-tets", "--mesh-time-budget", "--mesher", "--repair", "--no-cache", "--quiet", "--accel",
            "--tol", "--maxiter", "--lam", "--poisson-ratio"}


def _listed(command: str, option: str, capsys) -> tuple[set[str], str]:
    """The flags ``nestmg COMMAND OPTION`` lists, and its whole text."""
    from nestmg.cli import build_parser

    with pytest.raises(SystemExit) as ei:
        build_parser().parse_args([command, option])
    assert ei.value.code == 0
    text = capsys.readouterr().out
    body = text[text.index("\noptions:"):]  # the groups, not the usage lines
    return {line.split()[0].rstrip(",") for line in body.splitlines() if line.startswith("  -")}, text


@pytest.mark.parametrize("command", ["solve", "cages", "demo", "compare"])
def test_help_lists_everyday_flags_and_help_all_every_flag(command, capsys):
    """``--help`` lists the everyday flags, ``--help-all`` every flag grouped by stage; the expert ones are
    the options fields marked ``expert`` (and ``--quality``, ``--cage-time-budget``, ``--cage-threads``)."""
    actions = _flags(command)
    every = {a.option_strings[0] for a in actions.values()}
    expert = {a.option_strings[0] for a in actions.values() if getattr(a, "expert", False)}
    short, text = _listed(command, "--help", capsys)
    assert short == every - expert and f"{len(expert)} expert flags not shown" in text
    assert not expert & set(text.split("\noptions:")[0].replace("[", " ").split())  # nor in the usage
    full, text = _listed(command, "--help-all", capsys)
    assert full == every and "expert flags not shown" not in text
    assert all(f"\n{stage}:\n" in text for stage in ("sizing", "meshing", "cages"))
    for cls in (SizingOptions, MeshingOptions, CageOptions, SolverOptions):
        for f in dataclasses.fields(cls):
            if f.name in actions:
                assert actions[f.name].expert is f.metadata["expert"], f.name
    if command == "solve":
        assert short - {"-h", "--help-all"} == EVERYDAY
        assert len(every - {"-h", "--help-all"}) == 47 and len(expert) == 28
    if command == "cages":
        assert short - {"-h", "--help-all"} == EVERYDAY & every
        assert len(every - {"-h", "--help-all"}) == 28 and len(expert) == 17


def test_cli_builds_the_same_objects():
    from nestmg.cli import _cage_options, _typed_options, build_parser

    args = build_parser().parse_args(["solve", "shape:torus", "--mesher", "tetgen", "--face-counts", "300",
                                      "80",
                                      "--mesh-time-budget", "0", "--accel", "cg", "--no-local", "--repair",
                                      "--method", "sdf", "--cage-time-budget", "60"])
    _typed_options(args)
    assert args.sizing == SizingOptions(face_counts=(300, 80), mesh_time_budget=None)
    assert args.meshing == MeshingOptions(mesher="tetgen")
    assert args.solver == SolverOptions(accel="cg", local=False)
    assert _cage_options(args, "sdf") == SdfOptions(repair=True, cage_time_budget=60.0)


#: What the scalar problems resolve to: MultigridSolver's default cycle (forward / backward Gauss-Seidel, two
#: sweeps on the fine level, coarse_nu left to the solver's rule; issue 31, one default)
_SCALAR_SOLVER_DEFAULTS = {"coarse": "galerkin", "smoothing": "robust", "smoother": "gauss_seidel",
                        "nu": 2, "coarse_nu": None, "local": True, "coarse_scaling": "auto", "cycle": "V",
                        "accel": None, "tol": 1e-8, "maxiter": 100, "lam": 1e-2, "poisson_ratio": 0.3}


@pytest.mark.parametrize("problem", [None, "poisson-dirichlet", "poisson-neumann", "diffusion-neumann"])
def test_solver_defaults_resolve_to_the_old_ones_for_scalar_problems(problem):
    """The V-cycle with two forward / backward Gauss–Seidel sweeps on the fine level, whatever the Poisson
    ratio."""
    o = SolverOptions()
    assert (o.smoother, o.nu, o.cycle) == (None, None, None)  # not set
    assert dataclasses.asdict(o.resolved(problem)) == _SCALAR_SOLVER_DEFAULTS
    assert dataclasses.asdict(SolverOptions(poisson_ratio=0.45).resolved(problem, 0.45)) == {
        **_SCALAR_SOLVER_DEFAULTS, "poisson_ratio": 0.45}
    done = SolverOptions(smoother="jacobi", nu=2, cycle="W")
    assert done.resolved(problem) is done


@pytest.mark.parametrize("problem", ["elasticity-clamped", "elasticity-free"])
def test_elasticity_resolves_to_the_f_cycle_with_forward_sweeps(problem):
    """Issue 32 item 2: the F-cycle, forward Gauss–Seidel (backward after the correction), two sweeps on the
    fine level (three from ν = 0.4, per tet: the largest ν) and four below; a given field wins, the others
    keep elasticity's defaults; the fast preset is the fast one."""
    for ratio, nu in ((0.3, 2), (0.39, 2), (0.4, 3), (0.45, 3)):  # the threshold is inclusive
        r = SolverOptions(poisson_ratio=ratio).resolved(problem)
        assert dataclasses.asdict(r) == {**_SCALAR_SOLVER_DEFAULTS, "nu": nu,
                                         "coarse_nu": 4, "cycle": "F", "poisson_ratio": ratio}
        assert SolverOptions().resolved(problem, ratio).nu == nu  # the problem's ν wins over the field's
    assert SolverOptions().resolved(problem, np.array([0.3, 0.45, 0.2])).nu == 3
    for given, want in (({"cycle": "V"}, ("gauss_seidel", 3, 4, "V")),
                        ({"nu": 1}, ("gauss_seidel", 1, 4, "F")),
                        ({"coarse_nu": 8}, ("gauss_seidel", 3, 8, "F")),
                        ({"smoother": "symmetric_gauss_seidel"}, ("symmetric_gauss_seidel", 3, 4, "F")),
                        ({"smoother": "symmetric_gauss_seidel", "nu": 1, "cycle": "V"},
                         ("symmetric_gauss_seidel", 1, 4, "V")),
                        ({"smoothing": "fast"}, ("gauss_seidel", 2, None, "V"))):
        r = SolverOptions(**given).resolved(problem, 0.45)
        assert (r.smoother, r.nu, r.coarse_nu, r.cycle) == want, given
    done = SolverOptions(smoother="jacobi", nu=2, coarse_nu=4, cycle="V")
    assert done.resolved(problem, 0.45) is done
    with pytest.raises(OptionError, match="preset"):
        SolverOptions(smoothing="fast", nu=1)
    with pytest.raises(OptionError, match="preset"):
        SolverOptions(smoothing="fast", smoother="symmetric_gauss_seidel")


def test_solvers_without_elasticity_keep_the_v_cycle_bit_for_bit():
    """A bare MultigridSolver and the scalar problems' solver run the V-cycle when given no cycle, with the
    old smoothers: residual histories identical to an explicit ``cycle="V"``."""
    from nestmg.problems import DEFAULT_SMOOTHERS, setup_problem
    from solvers import MultigridSolver
    from solvers.gallery import kuhn_cube_hierarchy

    meshes, P = kuhn_cube_hierarchy(8, 3)
    for name in ("poisson-neumann", "diffusion-neumann"):
        pr = setup_problem(meshes, P, name)
        ml = pr.multigrid()
        assert ml.cycle == "V"
        assert [L.presmoother.params["iterations"] for L in ml.levels[:-1]] == [
            s[1]["iterations"] for s in DEFAULT_SMOOTHERS]
        for accel in (None, "cg"):
            r0 = ml.solve(pr.b, accel=accel, return_info=True)[1]["residuals"]
            assert r0 == ml.solve(pr.b, accel=accel, cycle="V", return_info=True)[1]["residuals"]
        bare = MultigridSolver(pr.A, pr.P)
        assert bare.cycle == "V" and bare.cycle_complexity() == bare.cycle_complexity("V")
        x = np.random.default_rng(0).standard_normal(pr.A.shape[0])
        x -= x.mean()
        assert np.array_equal(bare.aspreconditioner() @ x, bare.aspreconditioner("V") @ x)
    with pytest.raises(Exception, match="cycle must be"):
        MultigridSolver(pr.A, pr.P, cycle="X")


def test_cli_cycle_flag_is_not_set_by_default_and_takes_any_case():
    from nestmg.cli import _typed_options, build_parser

    for argv, want in (([], SolverOptions()), (["--cycle", "w", "--nu", "2"], SolverOptions(nu=2, cycle="W")),
                       (["--cycle", "v"], SolverOptions(cycle="V")), (["--cycle", "none"], SolverOptions())):
        args = build_parser().parse_args(["solve", "shape:torus", *argv])
        _typed_options(args)
        assert args.solver == want, argv
    with pytest.raises(SystemExit):
        build_parser().parse_args(["solve", "shape:torus", "--cycle", "x"])


def test_hierarchy_records_its_options_and_keys_the_cache_on_them(tmp_path, monkeypatch):
    pytest.importorskip("tetgen")
    monkeypatch.setenv("NESTMG_CACHE", str(tmp_path))
    V, F = shapes.sphere(res=12)
    sizing, meshing = SizingOptions(face_counts=[150], edge_length=0.1), MeshingOptions(mesher="tetgen")
    h = build_hierarchy(V, F, 2, "decimate", sizing=sizing, meshing=meshing, progress=False)
    assert SizingOptions(**h.options["sizing"]) == sizing
    assert MeshingOptions(**h.options["meshing"]) == dataclasses.replace(meshing, tet_retries=0)  # resolved
    assert DecimateOptions(**h.options["cages"]) == DecimateOptions()
    json.dumps(h.to_dict())
    n_entries = len(list(tmp_path.glob("*.json")))
    h2 = build_hierarchy(V, F, 2, "decimate", sizing=sizing, meshing=meshing, progress=False)
    assert h2.cage_info.get("cached") and len(list(tmp_path.glob("*.json"))) == n_entries
    # another cage option: a new cage entry (the tet layers of the same surfaces may be reused)
    h3 = build_hierarchy(V, F, 2, "decimate", sizing=sizing, meshing=meshing, progress=False,
                         cages=DecimateOptions(decimator="shortest_edge"))
    assert not h3.cage_info.get("cached") and len(list(tmp_path.glob("*.json"))) > n_entries
    with pytest.raises(CageOptionError, match="takes cagegen.DecimateOptions, got NestedOptions"):
        build_hierarchy(V, F, 2, "decimate", cages=NestedOptions(), progress=False)
    with pytest.raises(NestmgInputError, match="meshing must be a nestmg.MeshingOptions"):
        build_hierarchy(V, F, 2, "decimate", meshing={"mesher": "tetgen"}, progress=False)
