"""The user docs: generated numbers match the committed JSON, pages are short and cite only what users have.

``benchmarks/doc_tables.py`` regenerates every measured table and number of ``README.md`` and ``docs/*.md``
from ``benchmarks/results/``; these tests fail when a page and its JSON disagree, when a page grows into a
session log (over ~300 lines: the history belongs in ``docs/history/``), or when a page links to a file
that is not in the repository.
"""

from __future__ import annotations

import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "doc_tables.py"
DOCS = ROOT / "docs"
USER_PAGES = sorted(p for p in DOCS.glob("*.md") if p.name != "corpus.md")
ALL_PAGES = [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]
MAX_LINES = 300
#: files of the developers' machine, not of the repository
NOT_SHIPPED = re.compile(r"ENVIRONMENT\.md|PAPERS_DIR|\.\./shared/")
LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.fixture(scope="module")
def doc_tables() -> dict:
    return runpy.run_path(str(SCRIPT))


def test_pages_match_the_committed_json():
    """Every generated block is what its JSON gives today (run ``python benchmarks/doc_tables.py`` to fix)."""
    p = subprocess.run([sys.executable, str(SCRIPT), "--check"], capture_output=True, text=True, cwd=ROOT,
                       timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr


def test_generators_read_committed_results_only(doc_tables):
    tracked = set(subprocess.run(["git", "ls-files", "benchmarks/results"], capture_output=True, text=True,
                                 cwd=ROOT).stdout.split())
    for name, (_fn, sources) in doc_tables["GENERATORS"].items():
        assert sources, name
        for rel in sources:
            path = ROOT / "benchmarks" / "results" / rel
            assert path.is_file(), (name, rel)
            if tracked:  # a git checkout: the file must be committed, not a local run
                assert f"benchmarks/results/{rel}" in tracked, (name, rel)


def test_every_block_is_generated_and_stale_text_is_replaced(doc_tables):
    render, gens = doc_tables["render"], doc_tables["GENERATORS"]
    used = set()
    for page in [ROOT / "README.md", *USER_PAGES]:
        _, found = render(page.read_text())
        used |= set(found)
    assert used == set(gens), f"generators used by no page: {set(gens) - used}"
    stale = "MG-PCG in <!-- n: presets.fast -->8 iterations<!-- /n --> at 1M tets"
    new, found = render(stale)
    assert found == ["presets.fast"] and "8 iterations" not in new and "iterations and" in new
    block = "<!-- table: presets.table -->\n| typed | by hand |\n<!-- /table -->"
    new, _ = render(block)
    assert "by hand" not in new and new.count("\n| ") >= 4
    with pytest.raises(SystemExit, match="unknown generated block"):
        render("<!-- n: no.such.table --><!-- /n -->")


@pytest.mark.parametrize("page", USER_PAGES, ids=[p.name for p in USER_PAGES])
def test_user_pages_are_short_and_cite_only_shipped_files(page):
    text = page.read_text()
    assert len(text.splitlines()) <= MAX_LINES, f"{page.name}: move the session history to docs/history/"
    assert not NOT_SHIPPED.search(text), NOT_SHIPPED.search(text).group(0)
    history = DOCS / "history" / page.name
    if history.exists():
        assert f"(history/{page.name})" in text, f"{page.name} does not link its history"


@pytest.mark.parametrize("page", ALL_PAGES, ids=[p.relative_to(ROOT).as_posix() for p in ALL_PAGES])
def test_relative_links_resolve(page):
    """A link to a file users do not have is a broken link: every relative target exists."""
    missing = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:|#", target):
            continue
        path = (page.parent / target.split("#")[0]).resolve()
        if not path.exists():
            missing.append(target)
    assert not missing, missing
