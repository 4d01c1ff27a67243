"""fleetctl.cli.output: the plain-text table."""

from __future__ import annotations

import unicodedata
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.cli.output import display_width, table


def _columns(line: str) -> int:
    """Terminal columns *line* takes (wide characters two, combining marks none)."""
    return sum(0 if unicodedata.combining(c) else
               2 if unicodedata.east_asian_width(c) in ("W", "F") else 1 for c in line)


def test_display_width_counts_terminal_columns() -> None:
    assert display_width("bob@example.com") == 15
    assert display_width("a🤖@例え.jp") == 11  # the robot and the two kanji take two each
    assert display_width("e\u0301") == 1  # e + combining acute: one column


def test_columns_line_up_with_wide_characters(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """E-mail addresses of any script are accepted (`a🤖@例え.jp`), but `list` padded
    them by code points: every ROLE after one sat one column per wide character off."""
    fleet = tmp_path / "fleet"
    assert main(["init", str(fleet)]) == 0
    for email in ("a🤖@例え.jp", "bob@example.com", "\uff5a\uff45\uff4e@example.jp"):
        assert main(["add-user", email, "--role", "viewer", "--fleet", str(fleet)]) == 0
    capsys.readouterr()
    assert main(["list", "--fleet", str(fleet)]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = lines[lines.index(next(x for x in lines if x.startswith("USER"))):]
    starts = {_columns(row[:row.rindex("viewer" if "viewer" in row else "ROLE")])
              for row in rows}
    assert len(starts) == 1, rows
    text = table(["A", "B"], [("例え", "x"), ("ab", "y")])
    assert [_columns(row[:-1]) for row in text.splitlines()] == [6, 6, 6]
