"""malloc tuning: applied on glibc, idempotent."""

from __future__ import annotations

import platform

import pytest

from fleetctl.client import memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_tune_malloc_applies_once_on_glibc() -> None:
    assert memory.tune_malloc()
    assert memory.tune_malloc()  # second call: already done


def test_tune_malloc_without_glibc_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, "_done", False)
    monkeypatch.setattr("ctypes.util.find_library", lambda name: "libnonexistent.so.9")
    assert memory.tune_malloc() is False
    assert memory._done is False
