"""``server_url`` as one URL or a list of replicas (issue 15)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fleetctl.client.config import parse_client_config
from fleetctl.client.serverurls import MAX_SERVER_URLS
from fleetctl.errors import ConfigError


def config(server_url: Any) -> Any:
    return parse_client_config({"server_url": server_url, "robot_name": "r1"},
                               source="client.yaml", base_dir=Path("."))


def test_one_url_is_the_whole_list() -> None:
    cfg = config("wss://relay:8443/")
    assert cfg.server_url == "wss://relay:8443/"
    assert cfg.server_urls == ("wss://relay:8443/",) and cfg.failover_urls == ()


def test_a_list_keeps_its_order() -> None:
    cfg = config(["wss://a:8443/", "wss://b:8443/", "wss://c:8443/"])
    assert cfg.server_url == "wss://a:8443/"
    assert cfg.server_urls == ("wss://a:8443/", "wss://b:8443/", "wss://c:8443/")


@pytest.mark.parametrize(("value", "field", "reason"), [
    (None, "server_url", "is required"),
    ([], "server_url", "empty list"),
    (["wss://a/", 5], "server_url[1]", "must be a string"),
    (["wss://a/", "http://b/"], "server_url[1]", "must be ws://"),
    (["wss://a/", "ws://b/"], "server_url", "mixes ws:// and wss://"),
    (["wss://a/", "wss://a/"], "server_url", "names 'wss://a/' twice"),
    ([f"wss://r{i}/" for i in range(MAX_SERVER_URLS + 1)], "server_url", "at most 8"),
    ("wss://a:99999/", "server_url", "must be ws://"),
    ({"url": "wss://a/"}, "server_url", "must be a string"),
])
def test_bad_urls_name_the_file_and_the_entry(value: Any, field: str, reason: str) -> None:
    with pytest.raises(ConfigError) as err:
        config(value)
    text = str(err.value)
    assert text.startswith(f"client.yaml: {field}: ") and reason in text, text
