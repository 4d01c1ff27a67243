"""``server_url`` in client.yaml: one relay URL, or a list of replicas' URLs (issue 15).

A list is tried in order: the robot connects to the first, stays on a replica while it
works, and fails over to the others when it stops answering (the transport's dial gives
the current replica a head start, :func:`fleetctl.client.dialer.dial_first`). One name
behind a load balancer is a one-element list.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from websockets.exceptions import InvalidURI
from websockets.uri import parse_uri

from fleetctl.client.configfields import Ctx

# At most this many replicas: the list is dialed in turn, and a longer one is a typo.
MAX_SERVER_URLS = 8
_URL_RE = re.compile(r"^wss?://[^\s/]+(/\S*)?$")


def parse_server_urls(ctx: Ctx, top: Mapping[str, Any]) -> tuple[str, ...]:
    """The URLs of ``server_url`` (a string or a non-empty list of strings), checked.

    Every URL is ``ws://`` or ``wss://`` with a host; a list does not mix the two (a
    replica reached without TLS would get the token in clear) and names no URL twice.

    Raises:
        ConfigError: Naming ``server_url`` and, for a list, the entry.
    """
    if "server_url" not in top or top["server_url"] is None:
        raise ctx.error("", "server_url", "is required")
    raw = top["server_url"]
    items = raw if isinstance(raw, list) else [raw]
    if not items:
        raise ctx.error("", "server_url", "an empty list: give at least one URL")
    if len(items) > MAX_SERVER_URLS:
        raise ctx.error("", "server_url",
                        f"{len(items)} URLs; at most {MAX_SERVER_URLS} replicas")
    urls: list[str] = []
    for i, item in enumerate(items):
        field = f"server_url[{i}]" if isinstance(raw, list) else "server_url"
        urls.append(_check_url(ctx, field, item))
    schemes = {u.split(":", 1)[0] for u in urls}
    if len(schemes) > 1:
        raise ctx.error("", "server_url", "mixes ws:// and wss://: every replica must use "
                        "TLS or none (the token would go in clear to some)")
    seen = {u for u in urls}
    if len(seen) != len(urls):
        twice = next(u for u in urls if urls.count(u) > 1)
        raise ctx.error("", "server_url", f"names {twice!r} twice")
    return tuple(urls)


def _check_url(ctx: Ctx, field: str, value: object) -> str:
    if not isinstance(value, str):
        raise ctx.error("", field, f"must be a string, got {type(value).__name__}")
    reason = f"must be ws://HOST[:PORT]/ or wss://..., got {value!r}"
    if not _URL_RE.match(value):
        raise ctx.error("", field, reason)
    try:
        parse_uri(value)
    except (InvalidURI, ValueError) as exc:  # ValueError: urllib's port out of range
        raise ctx.error("", field, f"{reason}: {exc}") from exc
    return value
