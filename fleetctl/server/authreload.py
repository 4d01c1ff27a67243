"""Live reload of ``auth.yaml``: on SIGHUP and when the file changes.

The file is polled with ``stat`` (inode, device, mtime in ns, size) every
:data:`POLL_INTERVAL_S`: deployments replace it by atomic rename, and in Docker it lives in
a bind-mounted directory, where inotify events from the host are not guaranteed. A rename
changes the inode; an in-place edit changes mtime or size. A half-written file (an editor
writing in place) fails validation and is retried on its next change.

A new map is applied only when it is valid; otherwise one error line names the file and
the field and the previous map stays in force.
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import Callable
from pathlib import Path

from fleetctl.errors import ConfigError
from fleetctl.server.authmap import AuthMap, load_auth_map
from fleetctl.server.metrics import Metrics

log = logging.getLogger("fleetctl.server")

# Why 0.25 s: a removed token must be refused within 1 s; one stat per poll is cheap.
POLL_INTERVAL_S = 0.25

FileStamp = tuple[int, int, int, int]
"""``(st_ino, st_dev, st_mtime_ns, st_size)`` of a file."""


def file_stamp(path: Path) -> FileStamp | None:
    """Return what identifies *path*'s current content, or ``None`` if it cannot be stat'd."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_dev, st.st_mtime_ns, st.st_size


class AuthReloader:
    """Reloads the auth map file into a running relay.

    Args:
        path: The auth map file.
        apply: Installs a valid new map; returns ``(connections kept, connections closed)``
            (:meth:`fleetctl.server.relay.RelayCore.reload_auth`).
        metrics: Counts reloads and failures.
        poll_interval_s: Seconds between two checks of the file.
    """

    def __init__(self, path: Path, apply: Callable[[AuthMap], tuple[int, int]],
                 metrics: Metrics, poll_interval_s: float = POLL_INTERVAL_S) -> None:
        self.path = path
        self.poll_interval_s = poll_interval_s
        self._apply = apply
        self._metrics = metrics
        # The map in force was read from this version of the file (or given by the caller).
        self._stamp = file_stamp(path)

    def reload(self, reason: str) -> bool:
        """Read the file now and apply it if valid.

        Args:
            reason: Why (``SIGHUP``, ``file changed``), for the log line.

        Returns:
            Whether the new map is in force (``False``: the previous one stays).
        """
        # Stamp before reading: a change made while we read is seen by the next poll.
        self._stamp = file_stamp(self.path)
        try:
            auth = load_auth_map(self.path)
        except ConfigError as exc:
            self._metrics.auth_reload_failures += 1
            log.error("auth map not reloaded (%s), the previous one stays in force: %s",
                      reason, exc)
            return False
        kept, closed = self._apply(auth)
        self._metrics.auth_reloads += 1
        log.info("auth map reloaded from %s (%s): %d identities; %d connections "
                 "re-authorized, %d closed", self.path, reason, len(auth.identities), kept,
                 closed)
        return True

    def poll(self) -> bool:
        """Reload if the file changed since it was last read; return whether it changed."""
        if file_stamp(self.path) == self._stamp:
            return False
        self.reload("file changed")
        return True

    async def watch(self) -> None:
        """Poll until cancelled; a failure of one reload never stops the watching."""
        while True:  # periodic poll, not synchronization
            await asyncio.sleep(self.poll_interval_s)
            try:
                self.poll()
            except Exception:
                log.exception("auth map reload failed")
