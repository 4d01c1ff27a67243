"""Process harness of the client's integration tests: JSON-line children read with deadlines."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[3]


class JsonProc:
    """A child process printing one JSON object per stdout line.

    Lines are read by a thread into a bounded queue; :meth:`wait_for` takes them with a
    deadline. stderr goes to *log_path* so a failure can show it.
    """

    def __init__(self, argv: list[str], env: dict[str, str], log_path: Path) -> None:
        self.log_path = log_path
        self._log = log_path.open("ab")
        self.process = subprocess.Popen(
            argv, cwd=REPO, env={**os.environ, **env}, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=self._log, start_new_session=True,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=100_000)
        self.received: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for raw in self.process.stdout:
            with contextlib.suppress(ValueError):
                self.lines.put(json.loads(raw))

    def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float,
                 what: str) -> dict[str, Any]:
        """Return the first line (in order) matching *predicate*; fail after *timeout_s*."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; "
                                     f"stderr:\n{self.stderr_tail()}")
            try:
                line = self.lines.get(timeout=min(remaining, 0.5))
            except queue.Empty:
                if self.process.poll() is not None and self.lines.empty():
                    raise AssertionError(f"process exited ({self.process.returncode}) "
                                         f"before {what}; stderr:\n{self.stderr_tail()}") from None
                continue
            self.received.append(line)
            if predicate(line):
                return line

    def drain(self) -> list[dict[str, Any]]:
        """Take every line read so far, without waiting."""
        taken: list[dict[str, Any]] = []
        with contextlib.suppress(queue.Empty):
            while True:
                taken.append(self.lines.get_nowait())
        self.received.extend(taken)
        return taken

    def signal(self, signum: int) -> None:
        """Send *signum* to the child's process group."""
        os.killpg(self.process.pid, signum)

    def stderr_tail(self, max_bytes: int = 3000) -> str:
        self._log.flush()
        return self.log_path.read_bytes()[-max_bytes:].decode("utf-8", errors="replace")

    def stop(self, grace_s: float = 5.0) -> int:
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self._reader.join(timeout=grace_s)
        self._log.close()
        return int(self.process.returncode)


def write_yaml(path: Path, data: Any) -> Path:
    """Write *data* to *path* as YAML, keys in the order given (a test's configs)."""
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def ros_helper(mode: str, args: list[str], domain_id: int, log_path: Path) -> JsonProc:
    """Start ``tests.client.ros.rosproc MODE ARGS`` in ROS domain *domain_id*."""
    argv = [sys.executable, "-m", "tests.client.ros.rosproc", mode, *args]
    return JsonProc(argv, {"ROS_DOMAIN_ID": str(domain_id)}, log_path)


def fleetctl_argv(*args: str) -> list[str]:
    """The command line of ``fleetctl ARGS`` with this interpreter."""
    return [sys.executable, "-m", "fleetctl.cli.main", *args]



@contextlib.contextmanager
def spun_bridge(context: Any, publish: dict[str, Any],
                send_video: Callable[[Any, bytes, bool], None] | None = None,
                send: Callable[[Any, bytes, int], None] | None = None) -> Any:
    """A real :class:`Bridge` of robot ``r1`` with the one *publish* entry, spun on its own
    thread in *context*, whose link drops what it is handed (``send_video`` gets video,
    ``send`` the other frames)."""
    from fleetctl.client.config import parse_client_config
    from fleetctl.client.ros.bridge import Bridge, LinkPort
    from fleetctl.client.ros.runner import status_encoder
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    codec = Codec(TypeRegistry.default())
    port = LinkPort(admit=lambda topic: True,
                    send=send or (lambda spec, frame, published_ns: None),
                    send_status=lambda frame: None, send_video=send_video)
    config = parse_client_config({"server_url": "ws://127.0.0.1:1/", "robot_name": "r1",
                                  "publish": [publish]}, source="test.yaml")
    bridge = Bridge(config, codec, codec.registry.typestore, port,
                    status_encoder(codec, "r1"), context=context)
    try:
        with spinning(bridge, context):
            yield bridge
    finally:
        bridge.destroy_node()


@contextlib.contextmanager
def spinning(node: Any, context: Any) -> Any:
    """The client's executor spinning *node* in a thread (yielded), stopped on exit."""
    from fleetctl.client.ros.executor import NodeExecutor

    executor = NodeExecutor(node, context)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        yield executor
    finally:
        executor.shutdown()
        spinner.join(5)
