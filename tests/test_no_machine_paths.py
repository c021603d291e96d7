"""No path of one machine in the project's files: scripts take their inputs as arguments.

Benchmarks, docs and tests must run on any checkout (benchmarks/README.md): a mesh folder, an output
folder or a temporary file is a command-line argument, a placeholder in a docstring (``ZOO_DIR``,
``OUT``) or the ``tempfile`` module / pytest's ``tmp_path`` -- never a literal such as a quoted
``/work/...``, ``/root/...``, ``/home/...``, ``/tmp/...`` or a ``../shared/...`` folder next to the
checkout. Every tracked text file is read (``git ls-files``; without git, the tree minus ``.git``);
``benchmarks/results/`` is recorded data (a JSON may keep the command that produced it) and is skipped.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve().relative_to(ROOT).as_posix()
SKIPPED = ("benchmarks/results/",)  # recorded data: kept as produced
#: an absolute machine path used as a literal (quoted) in code, docs and configuration
QUOTED_ABSOLUTE = re.compile(r"""['"]/(work|root|home|tmp)/""")
QUOTED_SUFFIXES = (".py", ".md", ".toml", ".sh", ".cfg", ".ini", ".yml", ".yaml", ".rst", ".txt")
#: a folder beside the checkout, in any text file
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
    return rel != THIS and not rel.startswith(SKIPPED)


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary or missing file."""
    try:
        data = path.read_bytes()
    except OSError:  # listed by git but deleted in the work tree
        return None
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", "replace")


def _is_script(rel: str, text: str) -> bool:
    return rel.endswith(QUOTED_SUFFIXES) or text.startswith("#!")


def machine_paths() -> list[str]:
    hits = []
    for rel in sorted(project_files()):
        if not _checked(rel):
            continue
        text = _text(ROOT / rel)
        if text is None:
            continue
        quoted = _is_script(rel, text)
        for k, line in enumerate(text.splitlines(), start=1):
            if SIBLING_FOLDER.search(line) or (quoted and QUOTED_ABSOLUTE.search(line)):
                hits.append(f"{rel}:{k}: {line.strip()[:160]}")
    return hits


def test_patterns():
    assert QUOTED_ABSOLUTE.search('ap.add_argument("--tmp", default=Path("/tmp/user_mesh.msh"))')
    assert QUOTED_ABSOLUTE.search("ZOO = Path('/work/shared/data/meshes')")
    assert QUOTED_ABSOLUTE.search('cache = "/home/me/.cache"') and QUOTED_ABSOLUTE.search('"/root/x"')
    assert SIBLING_FOLDER.search("python benchmarks/pipeline.py ../shared/data/meshes --meshes bunny.off")
    assert not QUOTED_ABSOLUTE.search("out = tmp_path / 'run'; p = Path('benchmarks/results/x.json')")
    assert not QUOTED_ABSOLUTE.search('open("/proc/self/status")')


def test_files_are_listed():
    files = set(project_files())
    assert {"README.md", "pyproject.toml"} <= files
    assert not any(f.startswith(".git/") for f in files)


def test_no_machine_paths():
    hits = machine_paths()
    assert not hits, ("machine paths (pass them as arguments; placeholders such as ZOO_DIR / OUT in "
                      "docstrings; tempfile or tmp_path for temporary files):\n" + "\n".join(hits))
