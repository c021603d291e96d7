"""No path of one machine in the project's files: scripts take their inputs as arguments.

Benchmarks, docs and tests must run on any checkout (benchmarks/README.md): a mesh folder, an output
folder or a temporary file is a command-line argument, a placeholder (``ZOO_DIR``, ``OUT``, see below) or
the ``tempfile`` module / pytest's ``tmp_path`` -- never ``/work/...``, ``/root/...``, ``/home/...``,
``/tmp/...`` or a ``../shared/...`` folder next to the checkout, quoted or not. Every tracked text file is
read (``git ls-files``; without git, the tree minus ``.git``): code, docs, README, TOML, shell scripts and
the recorded JSON of ``benchmarks/results/`` alike.

Placeholders used in recorded commands and results: ``ZOO_DIR`` (the folder of input meshes), ``OUT``
(an output or scratch folder), ``CACHE_DIR`` (``$NESTMG_CACHE``), ``CHECKOUT`` (a checkout of this
repository, or a copy of it at another commit), ``SCRATCH`` (a folder of derived inputs),
``PYTHON_PREFIX`` (the Python installation).
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve().relative_to(ROOT).as_posix()
#: an absolute machine path, quoted or not: ``/work``, ``/root``, ``/home``, ``/tmp`` (alone or followed
#: by more path) where a path starts -- not inside a longer word or path (``docs/tmp``, ``a.tmp``)
ABSOLUTE = re.compile(r"(?<![\w.-])/(work|root|home|tmp|Users)\b")
#: a folder beside the checkout
SIBLING_FOLDER = re.compile(r"\.\./shared/")
#: folders never walked without git (not the project's files)
UNTRACKED_DIRS = {".git", "__pycache__", ".pytest_cache", ".hypothesis", ".ruff_cache", "build", "dist",
                  ".venv", "venv", "node_modules", "bench_out", "out", "nestmg-demo"}


def project_files() -> list[str]:
    """Tracked files (``git ls-files``), or every file of the tree when git is not available."""
    try:
        p = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, timeout=60, check=False)
    except (OSError, subprocess.SubprocessError):
        p = None
    if p is not None and p.returncode == 0 and p.stdout:
        return [f for f in p.stdout.decode("utf-8", "surrogateescape").split("\0") if f]
    files = []
    for d, dirs, names in os.walk(ROOT):
        dirs[:] = [x for x in dirs if x not in UNTRACKED_DIRS and not x.endswith(".egg-info")]
        files += [(Path(d) / n).relative_to(ROOT).as_posix() for n in names]
    return files


def _checked(rel: str) -> bool:
    return rel != THIS


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary or missing file."""
    try:
        data = path.read_bytes()
    except OSError:  # listed by git but deleted in the work tree
        return None
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", "replace")


def machine_paths() -> list[str]:
    hits = []
    for rel in sorted(project_files()):
        if not _checked(rel):
            continue
        text = _text(ROOT / rel)
        if text is None:
            continue
        for k, line in enumerate(text.splitlines(), start=1):
            if SIBLING_FOLDER.search(line) or ABSOLUTE.search(line):
                hits.append(f"{rel}:{k}: {line.strip()[:160]}")
    return hits


def test_patterns():
    # quoted, in code
    assert ABSOLUTE.search('ap.add_argument("--tmp", default=Path("/tmp/user_mesh.msh"))')
    assert ABSOLUTE.search("ZOO = Path('/work/shared/data/meshes')")
    assert ABSOLUTE.search('cache = "/home/me/.cache"') and ABSOLUTE.search('"/root/x"')
    # unquoted: recorded commands in docs and JSON, prose
    assert ABSOLUTE.search("python benchmarks/cages.py /work/shared/data/meshes --out /tmp/run1")
    assert ABSOLUTE.search('"command": "NESTMG_CACHE=/tmp/cache python x.py"')
    assert ABSOLUTE.search("PYTHONPATH=/tmp/base nice python run.py") and ABSOLUTE.search("copies in `/tmp`")
    assert ABSOLUTE.search("the scripts stayed in /tmp, not committed") and ABSOLUTE.search("file:///tmp/x")
    assert SIBLING_FOLDER.search("python benchmarks/pipeline.py ../shared/data/meshes --meshes bunny.off")
    # not machine paths
    assert not ABSOLUTE.search("out = tmp_path / 'run'; p = Path('benchmarks/results/x.json')")
    assert not ABSOLUTE.search('open("/proc/self/status")') and not ABSOLUTE.search("#!/usr/bin/env bash")
    assert not ABSOLUTE.search("docs/tmp/x, a.tmp/y, nestmg-demo/work/z, input/output and/or https://x.org/home/")
    assert not ABSOLUTE.search("python benchmarks/cages.py ZOO_DIR --out OUT/run1 (NESTMG_CACHE=CACHE_DIR)")


def test_files_are_listed():
    files = set(project_files())
    assert {"README.md", "pyproject.toml"} <= files
    assert not any(f.startswith(".git/") for f in files)


def test_no_machine_paths():
    hits = machine_paths()
    assert not hits, ("machine paths (pass them as arguments; placeholders such as ZOO_DIR / OUT in "
                      "docstrings; tempfile or tmp_path for temporary files):\n" + "\n".join(hits))
