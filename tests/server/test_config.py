from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.config import ServerLimits, load_server_config


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "server.yaml"
    path.write_text(text)
    return path


def test_full_config_paths_are_relative_to_file(tmp_path: Path) -> None:
    cfg = load_server_config(write(tmp_path, """
listen_host: 127.0.0.1
listen_port: 9000
auth_map: auth.yaml
database: fleet.db
trusted_proxies: [10.0.0.1, 192.168.0.0/16]
no_drop_topics: ["/.*/events"]
limits: {max_frame_bytes: 1024, robot_offline_after_s: 2}
"""))
    assert cfg.listen_port == 9000
    assert cfg.auth_map == tmp_path / "auth.yaml"
    assert cfg.database == tmp_path / "fleet.db"
    assert len(cfg.trusted_proxies) == 2
    assert cfg.limits.max_frame_bytes == 1024
    assert cfg.limits.robot_offline_after_s == 2.0
    assert cfg.limits.outbound_no_drop_messages == 1024
    assert cfg.limits.session_expiry_s == 3600.0
    assert cfg.limits.session_mailbox_messages == 10000


def test_latched_and_keyframe_limits(tmp_path: Path) -> None:
    path = tmp_path / "server.yaml"
    path.write_text("auth_map: auth.yaml\nlimits: {latched_bytes: 4096, "
                    "latched_message_bytes: 1024, keyframe_request_interval_s: 0.5}\n")
    limits = load_server_config(path).limits
    assert (limits.latched_bytes, limits.latched_message_bytes) == (4096, 1024)
    assert limits.keyframe_request_interval_s == 0.5
    defaults = ServerLimits()
    assert defaults.latched_bytes == 64 * 1024 * 1024
    assert defaults.keyframe_request_interval_s == 0.25


def test_session_limits(tmp_path: Path) -> None:
    cfg = load_server_config(write(tmp_path, """
auth_map: auth.yaml
limits: {session_expiry_s: 60, session_mailbox_messages: 5, session_mailbox_bytes: 4096,
         max_sessions_per_identity: 2}
"""))
    assert cfg.limits.session_expiry_s == 60.0 and cfg.limits.session_mailbox_messages == 5
    assert cfg.limits.session_mailbox_bytes == 4096
    assert cfg.limits.max_sessions_per_identity == 2


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("auth_map: a.yaml\nlisten_port: 70000", "listen_port"),
        ("listen_port: 1", "auth_map"),
        ("auth_map: a.yaml\ntls_cert: c.pem", "tls_cert"),
        ("auth_map: a.yaml\ntrusted_proxies: [nope]", "trusted_proxies[0]"),
        ("auth_map: a.yaml\nno_drop_topics: ['a(b']", "no_drop_topics[0]"),
        ("auth_map: a.yaml\nlimits: {max_frame_bytes: -1}", "limits.max_frame_bytes"),
        ("auth_map: a.yaml\nlimits: {bogus: 1}", "limits.bogus"),
        ("auth_map: a.yaml\nlimits: {session_expiry_s: 0}", "limits.session_expiry_s"),
        ("auth_map: a.yaml\nlimits: {session_mailbox_bytes: 1.5}",
         "limits.session_mailbox_bytes"),
        ("auth_map: a.yaml\nlimits: {latched_bytes: 0}", "limits.latched_bytes"),
        # an integer no float holds: math.isfinite raised OverflowError
        (f"auth_map: a.yaml\nlimits: {{robot_offline_after_s: 1{'0' * 400}}}",
         "limits.robot_offline_after_s' must be a positive number"),
        # YAML's "\0" escape: open(), ssl and sqlite3 raised ValueError at start
        ('auth_map: "a.yaml\\0"', "'auth_map' must be a path without a NUL byte"),
        ('auth_map: a.yaml\ndatabase: "f\\0.db"', "'database' must be a path without"),
        ('auth_map: a.yaml\nweb: {tls_cert: "c.pem\\0", tls_key: k.pem}', "'web.tls_cert'"),
        ('auth_map: a.yaml\nrecording: {directory: "r\\0", rules: [{topic: a}]}',
         "'recording.directory' is required (a path string without a NUL byte)"),
        ("auth_map: a.yaml\nlimits: {keyframe_request_interval_s: -1}",
         "limits.keyframe_request_interval_s"),
        ("auth_map: a.yaml\nlimits: {auth_timeout_s: .nan}", "limits.auth_timeout_s"),
        ("auth_map: a.yaml\nlimits: {max_control_requests_per_s: .inf}",
         "limits.max_control_requests_per_s"),
        ("auth_map: a.yaml\nlisten_prot: 1", "listen_prot"),
        # fuzzing: keys of mixed types (a number or null beside names) were sorted: TypeError
        ("auth_map: a.yaml\n~: 1\nh2leetctl: ge", "unknown field None"),
        ("auth_map: a.yaml\n1: 2\nzz: 3", "unknown field 1"),
        ("auth_map: a.yaml\nlimits: {1: 2, zz: 3}", "limits.1"),
        ("auth_map: a.yaml\nweb: {1: 2, zz: 3}", "web.1"),
        ("auth_map: a.yaml\nrecording: {directory: r, rules: [{topic: a, 1: 2, zz: 3}]}",
         "recording.rules[0].1"),
        ("- just a list", "top level"),
        ("a: [", "not valid YAML"),
    ],
)
def test_bad_config_names_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_server_config(path)
    assert str(path) in str(err.value)
    assert field in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_server_config(tmp_path / "nope.yaml")


def test_a_bad_no_drop_regex_is_one_error_line_and_no_re2_log(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "auth_map: a.yaml\nno_drop_topics: ['((']")
    with pytest.raises(ConfigError, match=r"no_drop_topics\[0\]': bad RE2 regex"):
        load_server_config(path)
    # RE2's default options log the parse error to stderr (absl) before ours.
    assert "((" not in capfd.readouterr().err
