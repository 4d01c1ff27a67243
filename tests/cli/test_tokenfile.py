"""--token-file: read, stripped, and every bad file named without showing a token."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.cli.tokenfile import read_token_file
from fleetctl.errors import ConfigError


def test_no_file_is_no_token() -> None:
    assert read_token_file(None) is None


def test_the_token_is_stripped(tmp_path: Path) -> None:
    f = tmp_path / "t"
    f.write_text("  abc-123\n")
    assert read_token_file(f) == "abc-123"


@pytest.mark.parametrize(("mode", "warned"), [(0o600, False), (0o400, False), (0o640, True),
                                              (0o644, True)])
def test_a_token_file_others_may_read_is_warned_of(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], mode: int, warned: bool) -> None:
    f = tmp_path / "t"
    f.write_text("abc-123\n")
    f.chmod(mode)
    assert read_token_file(f) == "abc-123"
    err = capsys.readouterr().err
    assert (f"warning: --token-file {f}: other users may read it (mode {mode:04o}); "
            "chmod 600 it" in err) is warned
    assert "abc-123" not in err


@pytest.mark.parametrize(("content", "why"), [
    (None, "cannot read: No such file or directory"),
    (b"\n \n", "the file is empty"),
    (b"\xff\xfe", "not UTF-8 text"),
    (b"abc\ndef\n", "the token must be one line of printable ASCII without spaces"),
    (b"a b", "the token must be one line of printable ASCII without spaces"),
    ("t\u20acken".encode(), "the token must be one line of printable ASCII without spaces"),
])
def test_a_bad_file_is_named(tmp_path: Path, content: bytes | None, why: str) -> None:
    f = tmp_path / "token"
    if content is not None:
        f.write_bytes(content)
    with pytest.raises(ConfigError, match=f"--token-file {f}: {why}"):
        read_token_file(f)


def test_a_link_to_a_device_is_refused_unread(tmp_path: Path) -> None:
    f = tmp_path / "token"
    f.symlink_to("/dev/zero")
    with pytest.raises(ConfigError, match=f"--token-file {f}: cannot read: not a regular file"):
        read_token_file(f)
