"""``benchmarks/archive/restructure_ab.py``: its fingerprints tell changed behaviour from unchanged.

The script is how issue 28 shows "behaviour unchanged" step by step; a digest blind to dtype or shape, or a
comparison blind to a changed leaf, would turn a changed result into a false "identical".
"""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "archive" / "restructure_ab.py"
_spec = importlib.util.spec_from_file_location("_restructure_ab", SCRIPT)
ab = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ab)


def _run(commit: str) -> dict:
    case = {"cages_tetwild_gap": {"surfaces": "a1", "certified": True, "faces": [10, 4]},
            "hierarchy_tetgen": {"P": "b2", "certified": True,
                                 "solves": {"poisson-neumann/cg": {"factor": 0.1234, "iterations": 7}}},
            "seconds": 3.0}
    return {"commit": commit, "command": "python benchmarks/archive/restructure_ab.py run ZOO_DIR",
            "cases": {"bunny.off/nested": case, "spot.obj/nested": copy.deepcopy(case)}}


def test_digest_sees_values_dtype_and_shape():
    a = np.arange(6, dtype=np.int64)
    assert ab.digest(a) == ab.digest(a.copy())
    assert ab.digest(a) != ab.digest(a.astype(np.int32))
    assert ab.digest(a) != ab.digest(a.reshape(2, 3))
    b = a.astype(float)
    c = b.copy()
    c[3] = np.nextafter(c[3], 10.0)  # one ulp
    assert ab.digest(b) != ab.digest(c)
    assert ab.digest(a, b) != ab.digest(b, a)


def test_compare_names_the_changed_leaf_and_ignores_seconds(tmp_path):
    before, after = _run("1111111aaaa"), _run("2222222bbbb")
    after["cases"]["bunny.off/nested"]["seconds"] = 99.0
    after["cases"]["spot.obj/nested"]["hierarchy_tetgen"]["solves"]["poisson-neumann/cg"]["iterations"] = 8
    paths = [tmp_path / "b.json", tmp_path / "a.json"]
    for p, r in zip(paths, (before, after)):
        p.write_text(json.dumps(r))
    out = tmp_path / "ab.json"
    ab.main(["compare", str(paths[0]), str(paths[1]), "--step", "abc1234", "--out", str(out)])
    v = json.loads(out.read_text())
    assert v["verdict"]["bunny.off/nested"] == "identical"
    assert v["verdict"]["spot.obj/nested"] == \
        "different: hierarchy_tetgen/solves/poisson-neumann/cg/iterations"
    assert v["all_identical"] is False
    assert ab.table([out]).splitlines()[2] == \
        "| abc1234 | 1111111 -> 2222222 | identical | different (hierarchy_tetgen/solves) |"


def test_a_recorded_failure_is_compared_like_a_hash():
    def fails():
        raise RuntimeError("Internal TetGen error within `split_subface`.\nsecond line")

    rec = ab._guarded(fails)
    assert rec == {"error": "RuntimeError: Internal TetGen error within `split_subface`."}
    assert ab._differences({"h": rec}, {"h": {"P": "b2"}}) == ["h/P", "h/error"]


def test_runs_of_one_commit_merge_and_of_two_are_refused(tmp_path):
    a, b = _run("1111111aaaa"), _run("1111111aaaa")
    b["cases"] = {"bunny.off/decimate": b["cases"]["bunny.off/nested"]}
    c = _run("2222222bbbb")
    for name, r in (("a", a), ("b", b), ("c", c)):
        (tmp_path / f"{name}.json").write_text(json.dumps(r))
    merged = ab.merge_runs(f"{tmp_path / 'a.json'},{tmp_path / 'b.json'}")
    assert sorted(merged["cases"]) == ["bunny.off/decimate", "bunny.off/nested", "spot.obj/nested"]
    with pytest.raises(SystemExit, match="different commits"):
        ab.merge_runs(f"{tmp_path / 'a.json'},{tmp_path / 'c.json'}")
