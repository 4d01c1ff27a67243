"""``fleetctl e2e`` end to end: the link calibration scenario through the real router."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from fleetctl.cli.main import main

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]


def test_link_scenario_writes_a_passing_report(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["e2e", "--scenario", "link", "--duration", "3", "--out", str(tmp_path)])
    out = capsys.readouterr()
    assert code == 0, out.out + out.err
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["ok"] is True
    (link,) = doc["scenarios"]
    assert {c["name"] for c in link["criteria"]} >= {"cut_drops_traffic",
                                                     "carried_at_4mbit_ratio"}
    assert "tc" in doc["environment"]
    assert (tmp_path / "link-0.png").is_file()
    assert "| link | pass |" in out.out


def test_bad_scenario_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["e2e", "--scenario", "bogus"]) == 2
    assert "unknown ['bogus']" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--wireguard", "sometimes"], "--wireguard must be auto, on or off"),
    (["--run-id", "Not-An-Id"], "--run-id: 1 to 8 of a-z, 0-9"),
])
def test_bad_options_are_usage_errors(argv: list[str], message: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["e2e", *argv]) == 2
    assert message in capsys.readouterr().err


def test_without_matplotlib_nothing_runs_and_the_extra_is_named(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        tmp_path: Path) -> None:
    import importlib.util

    from fleetctl.e2e import runner

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "matplotlib" else real(name, *a))
    monkeypatch.setattr(runner, "run", lambda *a, **k: pytest.fail("the run started"))
    assert main(["e2e", "--scenario", "link", "--out", str(tmp_path)]) == 5
    assert "pip install 'fleetctl[e2e]'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_an_out_that_is_a_file_is_one_line_before_anything_runs(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    assert main(["e2e", "--scenario", "link", "--out", str(afile)]) == 4
    err = capsys.readouterr().err
    assert err.strip() == (f"fleetctl: error: --out {afile}: exists and is not a directory "
                           "(give a new or existing directory for the report)")
    assert afile.read_text() == "mine\n"
    # A parent that is a file: the directory cannot be made (was a NotADirectoryError
    # traceback once the run had started).
    assert main(["e2e", "--scenario", "link", "--out", str(afile / "report")]) == 5
    assert "cannot make the report directory: Not a directory" in capsys.readouterr().err
