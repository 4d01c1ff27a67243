"""``fleetctl status``'s recording line: what the deployed server has recorded.

Asked from inside the server container, as ``/robots`` is: ``GET /recordings`` answers a
loopback caller without a token and lists every file. With replicas the server container
is their shared network namespace and ``FLEETCTL_HEALTH`` names each replica's health URL:
each replica is asked, since each records its own senders' frames into its own volume.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy.dockercli import Runner
from fleetctl.smallfile import MAX_CONFIG_BYTES, read_small_text
from fleetctl.yamlfile import safe_load

# Prints {"recordings": [...]} with every answering replica's files, {"off": true} when
# none records, or exits non-zero naming why no replica answered.
_SNIPPET = (
    "import json,os,sys,urllib.error,urllib.request\n"
    "files,off,err=[],0,None\n"
    "urls=os.environ['FLEETCTL_HEALTH'].split()\n"
    "for h in urls:\n"
    "    try:\n"
    "        files+=json.load(urllib.request.urlopen(h.rsplit('/',1)[0]+'/recordings',"
    "timeout=3))['recordings']\n"
    "    except urllib.error.HTTPError as e:\n"
    "        off+=e.code==404; err=e\n"
    "    except (OSError,ValueError,KeyError) as e: err=e\n"
    "if off==len(urls): print(json.dumps({'off':True}))\n"
    "elif err is not None and not files: sys.exit(f'no replica answered: {err}')\n"
    "else: print(json.dumps({'recordings':files}))\n"
)


OFF_NOTE = "off (no recording section in fleet.yaml)"


def _records_nothing(config: Path) -> bool:
    """True when *config* (a server.yaml) certainly has no recording section; an unreadable
    or odd one is left to the server to answer."""
    try:
        document = safe_load(read_small_text(config, MAX_CONFIG_BYTES))
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError):
        return False
    return isinstance(document, dict) and document.get("recording") is None


@dataclass(frozen=True)
class RecordingSummary:
    """The deployed server's recordings.

    Attributes:
        files: Recording files (every replica's).
        bytes: Their size together.
        writing: Names of the files being written now.
    """

    files: int
    bytes: int
    writing: tuple[str, ...]

    def text(self) -> str:
        """One line for the status report."""
        now = f", writing {', '.join(self.writing)}" if self.writing else ""
        return f"recording: {self.files} file(s), {self.bytes / 1e6:.1f} MB{now}"


def exec_error(stderr: str, container: str) -> str:
    """The last line of a failed ``docker exec`` in *container* (``docker ps``'s short
    id), Docker's 64-character form of the id ("Container <id> is restarting") shortened
    to it."""
    last = (stderr.strip().splitlines() or ["the server did not answer"])[-1]
    short = container[:12]
    return re.sub(rf"\b{re.escape(short)}[0-9a-f]{{52}}\b", short, last)


def server_recordings(server_id: str | None, runner: Runner,
                      deployed_config: Path | None = None,
                      ) -> tuple[RecordingSummary | None, str]:
    """``(summary, note)``: the summary, or ``None`` and why (``off`` when the fleet
    records nothing, fleet.yaml having no ``recording:`` section).

    *deployed_config* is the server.yaml the running server loaded
    (``FLEET/.compose/server/server.yaml``; a change restarts the server with it): without
    a ``recording`` section in it the server is not asked, as each ``GET /recordings`` it
    answers 404 is a "connection rejected (404 Not Found)" line in its log, one per
    ``status`` (a monitoring check running it every minute filled the log).
    """
    if server_id is None:
        return None, "unknown (the server container is not running)"
    if deployed_config is not None and _records_nothing(deployed_config):
        return None, OFF_NOTE
    res = runner(["docker", "exec", "--user", "fleetctl", server_id, "python3", "-c",
                  _SNIPPET], None, True)
    if res.returncode != 0:
        return None, f"unknown ({exec_error(res.stderr, server_id)})"
    try:
        data: Any = json.loads(res.stdout)
        if data.get("off"):
            return None, OFF_NOTE
        files = data["recordings"]
        return RecordingSummary(len(files), sum(int(f["bytes"]) for f in files),
                                tuple(f["name"] for f in files if not f["complete"])), ""
    except (ValueError, KeyError, TypeError, AttributeError):
        return None, "unknown (the server's /recordings is not a recordings list)"
