"""``fleetctl status``'s recording line: the snippet it runs in the server container, run
here against real relays (the ``docker exec`` prefix stripped, ``FLEETCTL_HEALTH`` as the
container sets it)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from fleetctl.deploy.dockercli import Completed, Runner
from fleetctl.deploy.statusrecordings import RecordingSummary, exec_error, server_recordings
from fleetctl.server.app import RelayServer
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from tests.server.conftest import client, make_server, wait_for  # noqa: F401 (fixture)
from tests.support import string_frame

DEADLINE_S = 30.0


def in_container(health_urls: list[str]) -> Runner:
    """Runs ``docker exec --user fleetctl ID python3 -c ...`` as the container would."""

    def run(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        assert list(argv[:5]) == ["docker", "exec", "--user", "fleetctl", "server-id"]
        command = [sys.executable if argv[5] == "python3" else argv[5], *argv[6:]]
        res = subprocess.run(command, capture_output=True, text=True, timeout=30, check=False,
                             env={**os.environ, "FLEETCTL_HEALTH": " ".join(health_urls)})
        return Completed(list(argv), res.returncode, res.stdout, res.stderr)

    return run


def health(srv: RelayServer) -> str:
    return f"http://127.0.0.1:{srv.port}/healthz"


async def test_every_replicas_recordings_are_summed(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    config = RecordingConfig(tmp_path / "rec", (RecordingRule(".*"),), flush_interval_s=0.05)
    async with make_server(recording=config) as srv, \
            make_server(database=tmp_path / "plain.db") as plain, \
            client(srv, source="127.0.0.2") as husky1:
        recorder = srv.recorder
        assert recorder is not None
        await husky1.send(string_frame("/husky1/chat", "hello", seq=1))
        await wait_for(lambda: recorder.snapshot()["messages"] == 1, DEADLINE_S)
        summary, note = await asyncio.to_thread(
            server_recordings, "server-id", in_container([health(srv), health(plain)]))
        assert note == ""
        assert isinstance(summary, RecordingSummary) and summary.files == 1
        assert summary.writing == (Path(str(recorder.current_path)).name,)
        assert summary.text().startswith("recording: 1 file(s), ")
        # A fleet without a recording section: every relay says it records nothing.
        assert await asyncio.to_thread(server_recordings, "server-id",
                                       in_container([health(plain)])) == (
            None, "off (no recording section in fleet.yaml)")
        stopped = [health(srv), health(plain)]
    # No relay answers (both stopped): unknown, and why.
    summary, note = await asyncio.to_thread(server_recordings, "server-id",
                                            in_container(stopped))
    assert summary is None and note.startswith("unknown (no replica answered:")
    assert server_recordings(None, in_container([])) == (
        None, "unknown (the server container is not running)")


def test_a_failed_exec_names_the_container_as_docker_ps_does() -> None:
    full = "3f2a" + "0" * 60  # Docker's message; `docker ps -q` gave the first 12
    said = f"Error response from daemon: Container {full} is restarting, wait until it runs\n"
    assert exec_error(said, full[:12]) == ("Error response from daemon: Container "
                                           "3f2a00000000 is restarting, wait until it runs")
    assert exec_error("", full[:12]) == "the server did not answer"


def test_a_server_config_without_recording_is_off_without_asking(tmp_path: Path) -> None:
    """Each `status` asked GET /recordings of a server that records nothing, and each 404
    was a "connection rejected (404 Not Found)" line in the server's log."""
    asked: list[Sequence[str]] = []

    def runner(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        asked.append(argv)
        return Completed(tuple(argv), 0, '{"off": true}', "")

    config = tmp_path / "server.yaml"
    config.write_text("listen_port: 8080\nrecording: null\n")
    assert server_recordings("server-id", runner, config) == (
        None, "off (no recording section in fleet.yaml)")
    config.write_text("listen_port: 8080\n")
    assert server_recordings("server-id", runner, config)[1].startswith("off (")
    assert asked == []
    # One that records, or one that cannot be read: the server is asked.
    for text in ("recording:\n  directory: /var/lib/fleetctl/recordings\n", "[not: closed"):
        config.write_text(text)
        assert server_recordings("server-id", runner, config)[1].startswith("off (")
    server_recordings("server-id", runner, tmp_path / "missing.yaml")
    assert len(asked) == 3
