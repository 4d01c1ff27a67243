"""Shared fixtures of the wire tests."""

from __future__ import annotations

import pytest

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.registry import TypeRegistry


@pytest.fixture(scope="session")
def codec() -> Codec:
    """The process-wide default codec (types are immutable, so sharing is safe)."""
    return default_codec()


@pytest.fixture(scope="session")
def registry(codec: Codec) -> TypeRegistry:
    """The default registry."""
    return codec.registry
