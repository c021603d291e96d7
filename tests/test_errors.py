"""One error root: every exception the three packages raise on purpose derives from ``NestmgError``.

The root lives in :mod:`solvers.errors` (``solvers`` imports neither ``cagegen`` nor ``nestmg``, so it is the
one place all three can import it from); ``cagegen.errors`` and ``nestmg`` re-export it.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cagegen
import cagegen.errors
import nestmg
from nestmg import shapes
import solvers
import solvers.errors

ROOT = Path(__file__).resolve().parents[1]


def _public_exceptions(package) -> list[type]:
    """Public exception classes defined in ``package``'s modules (those that import without extras)."""
    found = []
    for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        try:
            mod = importlib.import_module(info.name)
        except ImportError:  # an optional dependency (petsc4py, pygel3d, tetgen...) is missing
            continue
        for name, obj in vars(mod).items():
            if (inspect.isclass(obj) and issubclass(obj, Exception) and not issubclass(obj, Warning)
                    and obj.__module__ == mod.__name__ and not name.startswith("_")):
                found.append(obj)
    return found


def test_solvers_imports_no_cage_or_pipeline_code():
    """``solvers`` stays pure linear algebra: no module imports cagegen or nestmg, statically or at run time."""
    pattern = re.compile(r"^\s*(from|import)\s+(cagegen|nestmg)\b", re.M)
    offenders = [p.name for p in (ROOT / "solvers").rglob("*.py") if pattern.search(p.read_text())]
    assert not offenders, offenders
    code = ("import pkgutil, importlib, sys, solvers\n"
            "for m in pkgutil.walk_packages(solvers.__path__, 'solvers.'):\n"
            "    try: importlib.import_module(m.name)\n"
            "    except ImportError: pass\n"
            "print(sorted(k for k in sys.modules if k.split('.')[0] in ('cagegen', 'nestmg')))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300,
                         cwd=ROOT, check=True).stdout
    assert out.strip() == "[]", out


def test_nestmg_imports_only_public_cagegen_names():
    """nestmg reaches cagegen through public modules and names only (no ``cagegen._geometry``, no
    ``from cagegen.x import _private``): what it needs is exported (``cagegen.bbox_diagonal``, ...)."""
    private = re.compile(r"\bcagegen(\.\w+)*\._\w+|from\s+cagegen[\w.]*\s+import\s+\(?\s*_\w+"
                         r"|from\s+cagegen[\w.]*\s+import\s+[^\n]*,\s*_\w+")
    offenders = [f"{p.name}: {m.group(0)}" for p in (ROOT / "nestmg").rglob("*.py")
                 for m in private.finditer(p.read_text())]
    assert not offenders, offenders
    assert private.search("from cagegen._geometry import bbox_diagonal")
    assert private.search("from cagegen.nested.backend import push_out, _envelope_target")
    for name in ("as_mesh_arrays", "bbox_diagonal", "in_temp_dir"):
        assert name in cagegen.__all__ and getattr(cagegen, name).__doc__


def test_solver_errors_derive_from_the_root():
    classes = _public_exceptions(solvers)
    assert solvers.SolverError in classes and solvers.errors.DivergenceError in classes
    for cls in classes:
        assert issubclass(cls, solvers.errors.NestmgError), cls
    assert issubclass(solvers.SolverError, RuntimeError)  # kept: an except RuntimeError still catches it
    assert issubclass(solvers.SolverInputError, ValueError)


def test_nestmg_errors_derive_from_the_root():
    classes = _public_exceptions(nestmg)
    assert nestmg.NestmgInputError in classes and nestmg.TetMeshError in classes
    for cls in classes:
        assert issubclass(cls, nestmg.NestmgError), cls
    assert issubclass(nestmg.NestmgInputError, ValueError)


def test_build_hierarchy_input_errors_are_nestmg_errors():
    """Bad arguments raise NestmgInputError (a NestmgError and a ValueError) before any work."""
    V, F = shapes.sphere(res=6)
    for call, match in ((lambda: nestmg.build_hierarchy(V, F, 1), "levels must be >= 2"),
                        (lambda: nestmg.SizingOptions(fine_level="coarse"),
                         "SizingOptions.fine_level: must be one"),
                        (lambda: nestmg.build_hierarchy(V, F, 3,
                                                        sizing=nestmg.SizingOptions(same_domain_levels=5)),
                         "same_domain_levels"),
                        (lambda: nestmg.build_hierarchy(V, F, 3, sizing={"max_tets": 5}), "sizing must be a"),
                        (lambda: nestmg.SolverOptions(tol=float("nan")), r"SolverOptions.tol: must be > 0")):
        with pytest.raises(nestmg.NestmgInputError, match=match) as ei:
            call()
        assert isinstance(ei.value, ValueError) and isinstance(ei.value, nestmg.NestmgError)
    with pytest.raises(nestmg.NestmgInputError, match="unknown problem"):
        nestmg.setup_problem([(V, np.zeros((0, 4), dtype=np.int64))], [], "heat")
    with pytest.raises(nestmg.NestmgInputError, match="unknown shape"):
        shapes.shape_sdf("teapot")


def test_one_root_across_the_three_packages():
    assert cagegen.NestmgError is solvers.NestmgError is nestmg.NestmgError
    assert issubclass(solvers.SolverError, cagegen.NestmgError)
    outside = [f"{c.__module__}.{c.__name__}" for c in (*_public_exceptions(cagegen), *_public_exceptions(nestmg),
                                                       *_public_exceptions(solvers))
               if not issubclass(c, solvers.errors.NestmgError)]
    assert not outside, f"exceptions outside the root NestmgError: {outside}"
    try:
        solvers.MultigridSolver(np.eye(3), [], nullspace="affine")
    except cagegen.NestmgError as exc:  # one except clause for every package
        assert isinstance(exc, solvers.SolverInputError)


def _all_exception_classes(package) -> list[type]:
    """Every exception class defined in ``package``'s importable modules, private ones included."""
    found = []
    for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        try:
            mod = importlib.import_module(info.name)
        except ImportError:
            continue
        found += [obj for obj in vars(mod).values() if inspect.isclass(obj) and issubclass(obj, Exception)
                  and not issubclass(obj, Warning) and obj.__module__ == mod.__name__]
    return found


def test_every_exception_class_of_the_three_packages_derives_from_the_root():
    """Walk the three packages' exception classes: each derives from ``NestmgError``, except a private
    control-flow signal that its own module raises and catches (it never reaches a caller)."""
    classes = [c for pkg in (cagegen, nestmg, solvers) for c in _all_exception_classes(pkg)]
    names = {f"{c.__module__}.{c.__name__}" for c in classes}
    assert {"cagegen.errors.CageTypeError", "solvers.errors.SolverError", "nestmg.errors.NestmgInputError",
            "nestmg.options.OptionError", "cagegen.options.OptionFieldError"} <= names
    assert issubclass(nestmg.OptionError, nestmg.NestmgError) and issubclass(cagegen.CageOptionError,
                                                                                solvers.NestmgError)
    outside = []
    for c in classes:
        if issubclass(c, solvers.errors.NestmgError):
            continue
        src = Path(inspect.getsourcefile(c)).read_text()
        if not (c.__name__.startswith("_") and re.search(rf"except\s*\(?[^:]*\b{c.__name__}\b", src)):
            outside.append(f"{c.__module__}.{c.__name__}")
    assert not outside, f"exceptions outside the root NestmgError: {outside}"


def test_no_bare_builtin_exception_is_raised_on_purpose():
    """A deliberate ``raise`` uses a class of the root (``NestmgInputError``, ``CageError``,
    ``SolverError``...), never a bare ``ValueError`` / ``RuntimeError`` / ``TypeError``."""
    builtin = re.compile(r"\braise\s+(ValueError|RuntimeError|TypeError|KeyError|IndexError|Exception|OSError"
                         r"|NotImplementedError|FileNotFoundError|ImportError|MemoryError|LookupError)\b")
    offenders = [f"{p.relative_to(ROOT)}:{i}" for pkg in ("cagegen", "nestmg", "solvers")
                 for p in sorted((ROOT / pkg).rglob("*.py"))
                 for i, line in enumerate(p.read_text().splitlines(), 1)
                 if builtin.search(line.split("#")[0])]
    assert not offenders, offenders
    assert builtin.search("        raise RuntimeError(str(e)) from None")


def test_the_former_bare_raises_are_errors_of_the_root():
    with pytest.raises(cagegen.CageTypeError, match="progress must be") as ei:
        cagegen.build_cages(*shapes.sphere(res=6), 3, method="decimate", progress=3)
    assert isinstance(ei.value, TypeError) and isinstance(ei.value, cagegen.NestmgError)
    from nestmg.curved_fit import reference_inverse  # noqa: PLC0415
    V, T = np.vstack([np.zeros(3), np.eye(3)]), np.array([[0, 1, 2, 3]])
    assert reference_inverse(V, T, "straight").shape == (1, 3, 3)
    with pytest.raises(nestmg.NestmgInputError, match="reference must be"):
        reference_inverse(V, T, "curved")
