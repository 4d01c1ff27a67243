"""Fixtures shared by the deploy tests: deterministic keys and a small fleet."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops


class SeededKeySource:
    """Deterministic key material (SHA-256 of seed and a counter), for golden files."""

    def __init__(self, seed: str = "fleetctl-test") -> None:
        self._seed = seed
        self._count = 0

    def random_bytes(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            self._count += 1
            out += hashlib.sha256(f"{self._seed}/{self._count}".encode()).digest()
        return out[:n]


@pytest.fixture
def seeded_keys() -> SeededKeySource:
    return SeededKeySource()


def make_fleet(root: Path, keys: SeededKeySource | None = None) -> Path:
    """Create the reference fleet: two robots and one user of each role."""
    keys = keys or SeededKeySource()
    fleet_dir = root / "fleet"
    ops.create_fleet(fleet_dir, endpoint="vpn.example.com:51820", name="campus", keys=keys)
    ops.add_robot(fleet_dir, "husky1", keys=keys)
    ops.add_robot(fleet_dir, "jackal2", ip="10.8.0.20", mtu_bytes=1380, keys=keys)
    ops.add_user(fleet_dir, "viewer@example.com", "viewer", keys=keys)
    ops.add_user(fleet_dir, "operator@example.com", "operator", keys=keys)
    ops.add_user(fleet_dir, "admin@example.com", "admin", keys=keys)
    return fleet_dir


@pytest.fixture
def fleet_dir(tmp_path: Path) -> Path:
    return make_fleet(tmp_path)
