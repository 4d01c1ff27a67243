"""Container health check of the fleetctl images (stdlib only; exit 0 healthy, 1 not).

FLEETCTL_HEALTH says what to check:
  http://...        an HTTP GET answering 2xx within 2 s (server /healthz, webviz /);
  process:WORD      a process whose command line contains WORD is running (robot client);
  forwarding        IPv4 forwarding is on (e2e router).
"""

from __future__ import annotations

import os
import sys
import urllib.request
from pathlib import Path


def _http(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2.0) as resp:
            return 200 <= int(resp.status) < 300
    except OSError:
        return False


def _process(word: str) -> bool:
    me = str(os.getpid())
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or proc.name == me:
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if word in cmdline and "healthcheck" not in cmdline:
            return True
    return False


def _forwarding() -> bool:
    return Path("/proc/sys/net/ipv4/ip_forward").read_text().strip() == "1"


def main() -> int:
    spec = os.environ.get("FLEETCTL_HEALTH", "")
    if spec.startswith(("http://", "https://")):
        ok = _http(spec)
    elif spec.startswith("process:"):
        ok = _process(spec.split(":", 1)[1])
    elif spec == "forwarding":
        ok = _forwarding()
    else:
        print(f"healthcheck: unknown FLEETCTL_HEALTH={spec!r}", file=sys.stderr)
        return 1
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
