"""The xdist groups of scripts/test.sh, on a tiny suite run by a real ``pytest -n 2``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytest_plugins = ["pytester"]


def test_an_own_worker_module_runs_alone_and_the_rest_serially_on_the_other(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", str(REPO))  # the subprocess imports tests.xdistgroups
    pytester.makeini("[pytest]\nmarkers =\n    own_worker: a worker of its own\n")
    pytester.makepyfile(
        test_alone="import pytest\npytestmark = pytest.mark.own_worker\n"
        + "".join(f"def test_a{i}(): pass\n" for i in range(4)),
        test_rest_one="".join(f"def test_b{i}(): pass\n" for i in range(4)),
        test_rest_two="".join(f"def test_c{i}(): pass\n" for i in range(4)))
    result = pytester.runpytest_subprocess(
        "-p", "tests.xdistgroups", "-n", "2", "--dist", "loadgroup", "-v")
    result.assert_outcomes(passed=12)
    ran = re.findall(r"\[(gw\d)\] .*PASSED (\S+)::(test_\w+)@(\S+)", result.stdout.str())
    workers = {group: {w for w, _, _, g in ran if g == group} for _, _, _, group in ran}
    assert set(workers) == {"test_alone", "suite"}, ran
    assert all(len(w) == 1 for w in workers.values()) and len(set.union(*workers.values())) == 2
    rest = [name for _, _, name, group in ran if group == "suite"]
    assert rest == [f"test_b{i}" for i in range(4)] + [f"test_c{i}" for i in range(4)]
