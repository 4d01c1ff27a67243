"""Reading small files whole: a device, a FIFO or a huge file is refused, never read."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from fleetctl.smallfile import read_small, read_small_text


def test_reads_a_regular_file_up_to_the_limit(tmp_path: Path) -> None:
    f = tmp_path / "k"
    f.write_bytes(b"x" * 16)
    assert read_small(f, 16) == b"x" * 16
    assert read_small_text(f, 16) == "x" * 16


def test_a_file_over_the_limit_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "k"
    f.write_bytes(b"x" * 17)
    with pytest.raises(OSError, match="larger than 16 bytes") as info:
        read_small(f, 16)
    assert info.value.errno == errno.EFBIG


def test_a_path_with_a_nul_byte_is_an_os_error(tmp_path: Path) -> None:
    # YAML's "\0" escape puts one in a config's path: os.open raised ValueError
    with pytest.raises(OSError, match="the path contains a NUL byte") as info:
        read_small_text(tmp_path / "a\0b")
    assert info.value.errno == errno.EINVAL


def test_a_link_to_a_device_is_refused_without_reading(tmp_path: Path) -> None:
    link = tmp_path / "fleet.yaml"
    link.symlink_to("/dev/zero")
    with pytest.raises(OSError, match="not a regular file") as info:
        read_small(link, 1 << 30)  # a limit the machine could not hold: nothing is read
    assert info.value.errno == errno.EINVAL and info.value.filename == str(link)


def test_a_fifo_without_a_writer_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "token"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="not a regular file"):
        read_small(fifo, 64)


def test_a_link_is_refused_when_links_are_not_followed(tmp_path: Path) -> None:
    target = tmp_path / "t"
    target.write_text("secret")
    link = tmp_path / "l"
    link.symlink_to(target)
    assert read_small(link, 64) == b"secret"
    with pytest.raises(OSError) as info:
        read_small(link, 64, follow_symlinks=False)
    assert info.value.errno == errno.ELOOP


def test_text_that_is_not_the_encoding_raises_the_decode_error(tmp_path: Path) -> None:
    f = tmp_path / "k"
    f.write_bytes(b"\xff")
    with pytest.raises(UnicodeDecodeError):
        read_small_text(f, 64, encoding="ascii")
