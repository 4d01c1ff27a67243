"""Reading YAML config files: every failure names the file."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.errors import ConfigError
from fleetctl.yamlfile import read_yaml


def test_reads_a_document(tmp_path: Path) -> None:
    path = tmp_path / "a.yaml"
    path.write_text("listen_port: 8080\n")
    assert read_yaml(path, "server config") == {"listen_port": 8080}


def test_missing_file_names_file_and_role(tmp_path: Path) -> None:
    path = tmp_path / "missing.yaml"
    with pytest.raises(ConfigError, match=r"missing\.yaml: cannot read auth map: "):
        read_yaml(path, "auth map")


def test_bad_yaml_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("a: [\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML"):
        read_yaml(path, "client config")
