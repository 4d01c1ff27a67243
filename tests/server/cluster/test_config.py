"""The ``cluster:`` section of server.yaml."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.cluster.config import ClusterConfig, NatsCredentials
from fleetctl.server.config import parse_server_config


def parse(tmp_path: Path, cluster: Any) -> ClusterConfig | None:
    raw = {"auth_map": "auth.yaml", "cluster": cluster}
    return parse_server_config(raw, tmp_path / "server.yaml").cluster


def test_absent_is_one_process(tmp_path: Path) -> None:
    assert parse(tmp_path, None) is None


def test_full_section(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("s3cret\n")
    found = parse(tmp_path, {"name": "relay-a", "nats_urls": ["nats://10.0.0.1:4222"],
                             "credentials": {"user": "relay", "password_file": "pw"},
                             "publish_queue_frames": 100, "session_stream_bytes": 4096})
    assert found == ClusterConfig(
        name="relay-a", nats_urls=("nats://10.0.0.1:4222",),
        credentials=NatsCredentials(user="relay", password_file=tmp_path / "pw"),
        publish_queue_frames=100, session_stream_bytes=4096)
    assert found is not None and found.credentials is not None
    assert "s3cret" not in repr(found)  # only the path is kept
    assert found.credentials.read_password() == "s3cret"


@pytest.mark.parametrize(("cluster", "field"), [
    ({"nats_urls": ["nats://h:4222"]}, "cluster.name"),
    ({"name": "a.b", "nats_urls": ["nats://h:4222"]}, "cluster.name"),
    ({"name": "a"}, "cluster.nats_urls"),
    ({"name": "a", "nats_urls": []}, "cluster.nats_urls"),
    ({"name": "a", "nats_urls": ["http://h"]}, r"cluster.nats_urls\[0\]"),
    ({"name": "a", "nats_urls": ["nats://u:pw@h:4222"]}, r"cluster.nats_urls\[0\]"),
    # fuzzing: urlsplit raised ValueError (a traceback) for a bad bracketed host
    ({"name": "a", "nats_urls": ["nats://h:4222", "tls://[]::1]:4222"]},
     r"cluster.nats_urls\[1\]': 'tls://\[\]::1\]:4222' is not a nats://host:port URL"),
    ({"name": "a", "nats_urls": ["nats://[x"]}, r"cluster.nats_urls\[0\]"),
    ({"name": "a", "nats_urls": ["nats://h:99999"]}, r"cluster.nats_urls\[0\]"),
    ({"name": "a", "nats_urls": ["nats://h"], "extra": 1}, "cluster.extra"),
    ({"name": "a", "nats_urls": ["nats://h"], "credentials": {"user": "u"}},
     "cluster.credentials"),
    ({"name": "a", "nats_urls": ["nats://h"], "credentials": {"creds_file": "missing"}},
     "cluster.credentials.creds_file"),
    ({"name": "a", "nats_urls": ["nats://h"], "publish_queue_frames": 0},
     "cluster.publish_queue_frames"),
    ({"name": "a", "nats_urls": ["nats://h"], "connect_timeout_s": 10**400},  # OverflowError
     "cluster.connect_timeout_s"),
    ({"name": "a", "nats_urls": ["nats://h"], "connect_timeout_s": float("nan")},
     "cluster.connect_timeout_s"),
    ({"name": "a", "nats_urls": ["nats://h"], "state_replicas": 6}, "cluster.state_replicas"),
    ({"name": "a", "nats_urls": ["nats://h"], "state_replicas": 1.5},
     "cluster.state_replicas"),
    ({"name": "a", "nats_urls": ["nats://h"], "subject_prefix": "a>"},
     "cluster.subject_prefix"),
    ({"name": "a", "nats_urls": ["nats://h"], "session_stream_bytes": -1},
     "cluster.session_stream_bytes"),
    ({"name": "a", "nats_urls": ["nats://h"], "session_stream_bytes": "1G"},
     "cluster.session_stream_bytes"),
])
def test_bad_fields_named(tmp_path: Path, cluster: dict[str, Any], field: str) -> None:
    with pytest.raises(ConfigError, match=rf"server.yaml: .*'{field}"):
        parse(tmp_path, cluster)


def test_one_process_never_imports_nats(tmp_path: Path) -> None:
    code = ("import sys, asyncio\n"
            "from pathlib import Path\n"
            "from fleetctl.server.app import RelayServer\n"
            "from fleetctl.server.config import ServerConfig\n"
            "from tests.server.conftest import auth_map\n"
            "async def main():\n"
            f"    cfg = ServerConfig(listen_host='127.0.0.1', listen_port=0, "
            f"database=None, auth_map=Path({str(tmp_path / 'a.yaml')!r}))\n"
            "    async with RelayServer(cfg, auth_map()):\n"
            "        pass\n"
            "asyncio.run(main())\n"
            "assert not any(m == 'nats' or m.startswith('nats.') for m in sys.modules)\n")
    # 180 s: the child imports the relay and the test helpers (~3 s of CPU); a CI run at a
    # load of 20 on 2 cores gave it a tenth of a core and it passed 60 s.
    subprocess.run([sys.executable, "-c", code], check=True, timeout=180)
