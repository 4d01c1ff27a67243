"""One long-lived process in the router that cuts and restores the link on request.

Why not a ``docker exec`` per cut: each one starts a process through dockerd, containerd
and runc, and a Python interpreter in the router, and tears them down again. On the
2-core hosts the e2e runs on, that work runs in the 40-150 ms after the routes change (the
exec returns that much later), which is exactly when every stack recovers. One
``docker exec -i`` opened at the first cut and kept for the run leaves a single
``ip -batch`` in the router per cut, so the harness's own process starts stay out of the
measured window. (An A/B on 2026-12-05, 15 trials each way, could not show a difference in
recovery: docs/e2e.md.)

Protocol (one line each way): ``<verb> <cidr>...`` in (``replace`` or ``del``);
``<mark_ns> <blackhole routes left, space-separated>`` out, or ``error <message>``.
"""

from __future__ import annotations

import contextlib
import select
import subprocess

from fleetctl.errors import FleetError

# Runs in the router (python3 + iproute2): every blackhole route of a request added or
# removed by one `ip -batch` (microseconds apart), the clock read as soon as it returns,
# then the routes left. A failed addition is an error reply; removing a route that is
# gone is not (-force goes on), and the caller checks what is left.
AGENT_SCRIPT = (
    "import subprocess, sys, time\n"
    "for line in sys.stdin:\n"
    "    verb, *halves = line.split()\n"
    "    batch = ''.join(f'route {verb} blackhole {h}\\n' for h in halves)\n"
    "    ran = subprocess.run(['ip', '-force', '-batch', '-'], input=batch, text=True,\n"
    "                         capture_output=True)\n"
    "    mark = time.time_ns()\n"
    "    if verb != 'del' and ran.returncode != 0:\n"
    "        msg = (ran.stderr or 'ip -batch failed').replace(chr(10), ' ')\n"
    "        print('error', msg, flush=True)\n"
    "        continue\n"
    "    left = subprocess.run(['ip', 'route', 'show', 'type', 'blackhole'], text=True,\n"
    "                          capture_output=True).stdout\n"
    "    print(mark, left.replace(chr(10), ' '), flush=True)\n"
)

REPLY_TIMEOUT_S = 30.0  # a busy host's route change takes milliseconds; this is a hang


class CutAgent:
    """The agent in *container*, started on the first :meth:`change`.

    Args:
        container: The router's container name.
        argv_prefix: How to run a command in it (default ``docker exec -i <container>``;
            the tests use ``ip netns exec <namespace>``).
    """

    def __init__(self, container: str, argv_prefix: list[str] | None = None) -> None:
        self.container = container
        self._prefix = (["docker", "exec", "-i", container] if argv_prefix is None
                        else argv_prefix)
        self._proc: subprocess.Popen[str] | None = None

    def change(self, verb: str, halves: list[str]) -> tuple[int, str]:
        """Apply ``ip route <verb> blackhole`` to each of *halves*; returns the router's
        clock when it was done (ns since the epoch) and the blackhole routes left.

        Raises:
            FleetError: the agent could not start, reported an error, died or hung.
        """
        if verb not in ("replace", "del") or not halves or any(" " in h for h in halves):
            raise ValueError(f"bad cut request: {verb} {halves}")
        proc = self._start()
        assert proc.stdin is not None and proc.stdout is not None
        try:
            proc.stdin.write(f"{verb} {' '.join(halves)}\n")
            proc.stdin.flush()
        except OSError as exc:
            # A broken pipe: the agent is gone already (which of the write or the read
            # finds out depends on how fast it died), said as the read would say it.
            reason = "it exited" if isinstance(exc, BrokenPipeError) else str(exc)
            raise FleetError(f"cut agent in {self.container}: {reason}; "
                             f"{self._end_with_output()}") from exc
        ready, _, _ = select.select([proc.stdout], [], [], REPLY_TIMEOUT_S)
        line = proc.stdout.readline() if ready else ""
        if not line:
            reason = "no reply" if not ready else "it exited"
            raise FleetError(f"cut agent in {self.container}: {reason}; "
                             f"{self._end_with_output()}")
        word, _, rest = line.rstrip("\n").partition(" ")
        if word == "error":
            raise FleetError(f"blackhole routes {verb} in {self.container}: {rest}")
        return int(word), rest

    def close(self) -> None:
        """End the agent (its stdin closes; killed if it does not exit)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.stdin is not None:
            with contextlib.suppress(OSError):
                proc.stdin.close()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def _start(self) -> subprocess.Popen[str]:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        self._proc = subprocess.Popen(
            [*self._prefix, "python3", "-u", "-c", AGENT_SCRIPT],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        return self._proc

    def _end_with_output(self) -> str:
        """Kill a failed agent; what it wrote to stderr (the last 500 characters)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return "no error output"
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        err = proc.stderr.read() if proc.stderr is not None else ""
        return (err or "no error output").strip()[-500:]
