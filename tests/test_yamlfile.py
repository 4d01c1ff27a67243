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
    with pytest.raises(ConfigError, match=r"bad\.yaml:2: not valid YAML"):
        read_yaml(path, "client config")


def test_a_syntax_error_is_one_line_with_the_file_and_its_line(tmp_path: Path) -> None:
    path = tmp_path / "server.yaml"
    path.write_text("listen_host: 127.0.0.1\nlisten_port: [1\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(path, "server config")
    message = str(info.value)
    assert message.startswith(f"{path}:3: not valid YAML: ")
    assert "\n" not in message and "<unicode string>" not in message


def test_deep_nesting_is_a_config_error_not_a_recursion_crash(tmp_path: Path) -> None:
    path = tmp_path / "auth.yaml"
    path.write_text("robots: " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(ConfigError, match=r"auth\.yaml: not valid YAML: nested too deeply"):
        read_yaml(path, "auth map")


@pytest.mark.parametrize(
    ("line", "problem"),
    [  # fuzzing: PyYAML's constructors raised ValueError, KeyError or AttributeError
        ("limits: !!int 2ateee2ater!", "'2ateee2ater!' is not a valid !!int value"),
        ("ok: !!bool t3- @", "'t3- @' is not a valid !!bool value"),
        ("at: !!timestamp x", "'x' is not a valid !!timestamp value"),
        ("rate: !!float fast", "'fast' is not a valid !!float value"),
        ("? !!float x\n: 1", "'x' is not a valid !!float value"),
    ],
)
def test_a_tagged_value_of_another_type_is_a_config_error(tmp_path: Path, line: str,
                                                          problem: str) -> None:
    path = tmp_path / "server.yaml"
    path.write_text(f"listen_port: 8080\n{line}\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(path, "server config")
    assert str(info.value) == f"{path}:2: not valid YAML: {problem}"
