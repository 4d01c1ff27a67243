"""Says once when large local messages are likely to be lost before the client sees them.

A DDS sample larger than what its transport carries whole (Fast DDS's shared-memory segment
is 512 KiB; over UDP any sample over ~64 KB) crosses as UDP fragments into the reader's
socket buffer. Best-effort camera topics lose the whole sample when one fragment does not
fit, and the kernel's default buffer (``net.core.rmem_default``, 208 KiB on most Linux
machines) holds less than one 640x480 rgb8 image. Measured here (2026-12-06, a 921 KB
15 Hz camera, three busy processes beside it, `FASTDDS_BUILTIN_TRANSPORTS=UDPv4` as
fleetctl.env sets it): 43 % of the frames reached a subscriber with the default buffer,
all of them with a 4 MiB one (``UDPv4?sockets_size=4194304``), which the kernel grants only
up to ``net.core.rmem_max``. The robot's camera driver cannot be told from here, so the
client says what it found, once, when the first such message arrives (docs/robot.md,
"Large messages: camera images and clouds").
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path

__all__ = ["CLIENT_FASTDDS_TRANSPORTS", "WANTED_BUFFER_BYTES", "LargeMessageCheck",
           "receive_buffer_bytes"]

log = logging.getLogger(__name__)

# What the robot bundle asks for (fleetctl.env) and what docs/robot.md tells to allow.
WANTED_BUFFER_BYTES = 4 * 1024 * 1024
# The client's Fast DDS transports where it runs beside a robot's nodes (fleetctl.env's
# FASTDDS_BUILTIN_TRANSPORTS, the demo's clients): UDP only, since shared memory fails
# silently across users and containers, with the buffer above. ("DEFAULT?sockets_size"
# was tried: it kept losing 70 % of a loaded 640x480 camera.)
CLIENT_FASTDDS_TRANSPORTS = f"UDPv4?sockets_size={WANTED_BUFFER_BYTES}"
# Fast DDS carries a sample this large through shared memory when that transport is on.
FASTDDS_SHM_SEGMENT_BYTES = 512 * 1024
# Past this a sample over UDP is several fragments that must all fit the buffer at once.
UDP_LARGE_BYTES = 128 * 1024
_SOCKETS_SIZE = re.compile(r"[?&]sockets_size=(\d+)(?:&|$)")


def _read_int(path: Path) -> int | None:
    try:
        return int(path.read_text(encoding="ascii").strip())
    except (OSError, ValueError):
        return None


def receive_buffer_bytes(env: Mapping[str, str], sysctl: Path = Path("/proc/sys/net/core")
                         ) -> tuple[int | None, int | None]:
    """(this process's DDS receive buffer in bytes, ``net.core.rmem_max``); None: unknown.

    Fast DDS asks for ``sockets_size`` from ``FASTDDS_BUILTIN_TRANSPORTS`` when given, which
    the kernel caps at rmem_max; otherwise the socket keeps ``net.core.rmem_default``.
    """
    rmem_max = _read_int(sysctl / "rmem_max")
    asked = _SOCKETS_SIZE.search(env.get("FASTDDS_BUILTIN_TRANSPORTS", ""))
    if asked is None:
        return _read_int(sysctl / "rmem_default"), rmem_max
    wanted = int(asked.group(1))
    return (wanted if rmem_max is None else min(wanted, rmem_max)), rmem_max


class LargeMessageCheck:
    """``seen(topic, size)`` for every local message; logs at most one warning.

    Args:
        env: The environment (``RMW_IMPLEMENTATION``, ``FASTDDS_BUILTIN_TRANSPORTS``);
            other RMWs than Fast DDS are not checked.
        buffers: ``() -> (receive buffer, rmem_max)``, read at the first large message.
    """

    def __init__(self, env: Mapping[str, str] | None = None,
                 buffers: Callable[[], tuple[int | None, int | None]] | None = None) -> None:
        env = os.environ if env is None else env
        self._env = dict(env)
        self._buffers = buffers or (lambda: receive_buffer_bytes(self._env))
        rmw = env.get("RMW_IMPLEMENTATION", "")
        # Only Fast DDS (the default RMW) is measured and takes sockets_size; Cyclone's
        # buffer is set in its own XML, rmw_zenoh carries samples over TCP.
        self._done = bool(rmw) and not rmw.startswith("rmw_fastrtps")
        shm_on = not env.get("FASTDDS_BUILTIN_TRANSPORTS")
        self.threshold = FASTDDS_SHM_SEGMENT_BYTES if shm_on else UDP_LARGE_BYTES
        self.warned = False

    def seen(self, topic: str, size: int) -> None:
        """Note a local message of *size* bytes on *topic* (cheap after the first check)."""
        if self._done or size <= self.threshold:
            return
        self._done = True
        buffer, rmem_max = self._buffers()
        if buffer is not None and buffer >= WANTED_BUFFER_BYTES:
            return
        self.warned = True
        log.warning(
            "%s: local messages of %d bytes cross DDS as UDP fragments, and this client's "
            "receive buffer is %s bytes (net.core.rmem_max %s): a busy moment loses whole "
            "messages before the client sees them. Allow %d bytes: sysctl -w "
            "net.core.rmem_max=%d, with FASTDDS_BUILTIN_TRANSPORTS=UDPv4?sockets_size=%d "
            "for the client (the robot bundle's fleetctl.env sets it); docs/robot.md, "
            "'Large messages'", topic, size, "unknown" if buffer is None else buffer,
            "unknown" if rmem_max is None else rmem_max, WANTED_BUFFER_BYTES,
            WANTED_BUFFER_BYTES, WANTED_BUFFER_BYTES)
