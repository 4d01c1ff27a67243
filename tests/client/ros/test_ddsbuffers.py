"""When the client warns that large local messages are likely lost (ddsbuffers): the rule
with injected buffers, and a real Bridge taking a real 640x480 camera."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pytest

from fleetctl.client.ros.ddsbuffers import (
    WANTED_BUFFER_BYTES,
    LargeMessageCheck,
    receive_buffer_bytes,
)
from fleetctl.waiting import wait_until

DOMAIN_ID = 63  # the real bridge test below
IMAGE = 921_654  # a 640x480 rgb8 Image's CDR
SMALL_BUFFERS = (212_992, 212_992)


def _sysctl(tmp_path: Path, rmem_default: int, rmem_max: int) -> Path:
    (tmp_path / "rmem_default").write_text(f"{rmem_default}\n")
    (tmp_path / "rmem_max").write_text(f"{rmem_max}\n")
    return tmp_path


def test_buffer_is_rmem_default_without_sockets_size(tmp_path: Path) -> None:
    sysctl = _sysctl(tmp_path, 212_992, 4_194_304)
    assert receive_buffer_bytes({}, sysctl) == (212_992, 4_194_304)
    assert receive_buffer_bytes({"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}, sysctl) == (
        212_992, 4_194_304)


def test_sockets_size_is_capped_by_rmem_max(tmp_path: Path) -> None:
    env = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4?sockets_size=4194304"}
    assert receive_buffer_bytes(env, _sysctl(tmp_path, 212_992, 212_992)) == (
        212_992, 212_992)
    assert receive_buffer_bytes(env, _sysctl(tmp_path, 212_992, 8_388_608)) == (
        4_194_304, 8_388_608)


def test_unreadable_sysctl_is_unknown(tmp_path: Path) -> None:
    assert receive_buffer_bytes({}, tmp_path / "missing") == (None, None)


def test_one_warning_for_a_large_image_with_a_small_buffer(
        caplog: pytest.LogCaptureFixture) -> None:
    check = LargeMessageCheck({}, lambda: SMALL_BUFFERS)
    with caplog.at_level(logging.WARNING, "fleetctl.client.ros.ddsbuffers"):
        check.seen("/scan", 3_000)
        assert not caplog.records
        check.seen("/camera/image_raw", IMAGE)
        check.seen("/camera/image_raw", IMAGE)
    assert check.warned
    [record] = caplog.records
    text = record.getMessage()
    assert "/camera/image_raw" in text and "921654 bytes" in text
    assert "net.core.rmem_max=4194304" in text and "sockets_size=4194304" in text


def test_no_warning_with_a_big_enough_buffer() -> None:
    check = LargeMessageCheck({}, lambda: (WANTED_BUFFER_BYTES, WANTED_BUFFER_BYTES))
    check.seen("/camera/image_raw", IMAGE)
    assert not check.warned


def test_shared_memory_carries_up_to_512_kib_unless_udp_only() -> None:
    shm = LargeMessageCheck({}, lambda: SMALL_BUFFERS)
    shm.seen("/camera/image_raw", 230_454)  # 320x240 rgb8 fits a 512 KiB segment
    assert not shm.warned
    udp = LargeMessageCheck({"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}, lambda: SMALL_BUFFERS)
    udp.seen("/camera/image_raw", 230_454)
    assert udp.warned


@pytest.mark.parametrize("rmw", ["rmw_cyclonedds_cpp", "rmw_zenoh_cpp"])
def test_other_rmws_are_not_checked(rmw: str) -> None:
    check = LargeMessageCheck({"RMW_IMPLEMENTATION": rmw}, lambda: SMALL_BUFFERS)
    check.seen("/camera/image_raw", IMAGE)
    assert not check.warned


@pytest.mark.ros
def test_a_real_bridge_checks_a_real_cameras_images(ros: tuple[Any, Any]) -> None:
    pytest.importorskip("rclpy")
    from fleetctl.client.ros.simcamera import SimCamera
    from tests.client.ros.harness import spun_bridge

    context, peer = ros
    raw_camera = {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image"}
    with spun_bridge(context, raw_camera) as bridge:
        SimCamera(peer, "/camera/image_raw", 15.0, 640, 480)
        # Two: local_in counts a message before its check; the executor handles one at a
        # time, so the first message's check is done when the second is counted.
        wait_until(lambda: bridge.stats.local_in >= 2, 30.0, describe="two camera images")
        # What this machine gives the client's socket decides (CI: the kernel's default).
        buffer, _ = receive_buffer_bytes(os.environ)
        expect = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith(
            "rmw_fastrtps") and (buffer is None or buffer < WANTED_BUFFER_BYTES)
        assert bridge.large_messages.warned == expect
