"""fleetctl.deploy.reqstamp: the same requirements however they are spelled."""

from __future__ import annotations

from pathlib import Path

from fleetctl.deploy.images import installed_requirements, project_requirements
from fleetctl.deploy.reqstamp import requirements_stamp

ROOT = Path(__file__).resolve().parents[2]


def test_the_checkouts_and_the_installed_metadatas_requirements_stamp_alike() -> None:
    """pyproject says ``websockets>=13,<16``, the installed metadata ``websockets<16,>=13``:
    a wheel build after a checkout build downloaded every wheelhouse again."""
    assert project_requirements(ROOT / "pyproject.toml") != installed_requirements()
    for extras in ([], ["ros"], ["peers"], ["cluster"]):
        checkout = project_requirements(ROOT / "pyproject.toml", extras)
        installed = installed_requirements(extras)
        assert requirements_stamp(checkout) == requirements_stamp(installed), extras


def test_spelling_order_case_and_spaces_do_not_matter() -> None:
    assert requirements_stamp(["Web_Sockets >= 13, <16", "av>=16,<20"]) == requirements_stamp(
        ["av<20,>=16", "web-sockets (<16,>=13)"])
    assert requirements_stamp(["rclpy[fastrtps,b]>=7"]) == requirements_stamp(
        ["rclpy[b, fastrtps]>=7"])
    assert requirements_stamp(["x>=1; python_version < '3.12'"]) == requirements_stamp(
        ["x>=1;python_version<'3.12'"])


def test_a_changed_bound_or_a_new_requirement_is_a_different_stamp() -> None:
    stamp = requirements_stamp(["websockets>=13,<16"])
    assert requirements_stamp(["websockets>=13,<17"]) != stamp
    assert requirements_stamp(["websockets>=13,<16", "numpy"]) != stamp
    assert requirements_stamp(["websockets[x]>=13,<16"]) != stamp
    assert requirements_stamp(["websockets>=13,<16; sys_platform == 'linux'"]) != stamp
