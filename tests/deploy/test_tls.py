"""The HTTPS certificate: the generated one, and the operator's own files."""

from __future__ import annotations

import datetime
import os
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from fleetctl.deploy import operations as ops
from fleetctl.deploy.keys import SystemKeySource
from fleetctl.deploy.tls import (
    CERT_RELPATH,
    KEY_RELPATH,
    MAX_PEM_BYTES,
    cert_names,
    covers,
    self_signed,
)
from fleetctl.errors import ConfigError


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_generated_certificate(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="vpn.example.com:51820")
    cert = x509.load_pem_x509_certificate((fleet_dir / CERT_RELPATH).read_bytes())
    key = serialization.load_pem_private_key((fleet_dir / KEY_RELPATH).read_bytes(), None)
    assert isinstance(key, ec.EllipticCurvePrivateKey) and key.curve.name == "secp256r1"
    assert cert.public_key() == key.public_key()
    lifetime = cert.not_valid_after_utc - cert.not_valid_before_utc
    assert lifetime == datetime.timedelta(days=365)
    assert cert_names(fleet_dir / CERT_RELPATH) == (
        "localhost", "127.0.0.1", "::1", "vpn.example.com")
    assert stat.S_IMODE((fleet_dir / KEY_RELPATH).stat().st_mode) == 0o600
    assert stat.S_IMODE((fleet_dir / CERT_RELPATH).stat().st_mode) == 0o644
    assert stat.S_IMODE((fleet_dir / "keys").stat().st_mode) == 0o700


def test_no_endpoint_then_set_endpoint_regenerates_only_on_host_change(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    assert cert_names(fleet_dir / CERT_RELPATH) == ("localhost", "127.0.0.1", "::1")
    first = (fleet_dir / CERT_RELPATH).read_bytes()
    ops.render_fleet(fleet_dir)
    assert (fleet_dir / CERT_RELPATH).read_bytes() == first  # render keeps it
    result = ops.set_endpoint(fleet_dir, "203.0.113.7:51820")
    assert result.certificate_regenerated and result.previous is None
    assert cert_names(fleet_dir / CERT_RELPATH) == ("localhost", "127.0.0.1", "::1",
                                                    "203.0.113.7")
    second = (fleet_dir / CERT_RELPATH).read_bytes()
    result = ops.set_endpoint(fleet_dir, "203.0.113.7:51821")  # same host
    assert not result.certificate_regenerated
    assert (fleet_dir / CERT_RELPATH).read_bytes() == second


def test_render_makes_a_missing_certificate(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="h.example:1")
    (fleet_dir / CERT_RELPATH).unlink()
    ops.render_fleet(fleet_dir)
    assert cert_names(fleet_dir / CERT_RELPATH) == ("localhost", "127.0.0.1", "::1",
                                                    "h.example")


def test_render_makes_the_self_signed_certificate_again_before_it_ends(tmp_path: Path) -> None:
    """It is valid a year and nothing made it again: a year after `init` the page's
    certificate had expired, and `recordings --ca-file` and `foxglove-url` failed on it."""
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="h.example:1")
    cert_path = fleet_dir / CERT_RELPATH
    made_at = datetime.datetime.now(datetime.UTC) - datetime.timedelta(days=340)
    old = self_signed(cert_names(cert_path) or (), SystemKeySource(), now=lambda: made_at)
    cert_path.write_bytes(old.cert_pem)
    (fleet_dir / KEY_RELPATH).write_text(old.key_pem.reveal())
    ops.add_user(fleet_dir, "bob@example.org", "viewer")  # never restarts the server for it
    assert cert_path.read_bytes() == old.cert_pem
    outcome = ops.render_fleet(fleet_dir)
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    ends = cert.not_valid_after_utc - datetime.datetime.now(datetime.UTC)
    assert datetime.timedelta(days=364) < ends <= datetime.timedelta(days=365)
    assert cert_names(cert_path) == ("localhost", "127.0.0.1", "::1", "h.example")
    key = serialization.load_pem_private_key((fleet_dir / KEY_RELPATH).read_bytes(), None)
    assert cert.public_key() == key.public_key()
    assert [w for w in outcome.warnings if "self-signed" in w] == [
        f"the self-signed HTTPS certificate {cert_path} ends "
        f"{made_at - datetime.timedelta(minutes=5) + datetime.timedelta(days=365):%Y-%m-%d %H:%M}"
        " UTC: made again, valid for a year"]
    renewed = cert_path.read_bytes()
    ops.render_fleet(fleet_dir)  # a year ahead again: kept
    assert cert_path.read_bytes() == renewed


def _operator_files(tmp_path: Path) -> tuple[Path, Path]:
    made = self_signed(("fleet.example.org",), SystemKeySource())
    cert, key = tmp_path / "op" / "cert.pem", tmp_path / "op" / "key.pem"
    cert.parent.mkdir()
    cert.write_bytes(made.cert_pem)
    key.write_text(made.key_pem.reveal())
    key.chmod(0o640)  # a server key as Debian keeps it (group ssl-cert)
    return cert, key


def _use_tls(fleet_dir: Path, cert: str, key: str) -> None:
    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace("tls: null\n", f"tls:\n  cert: {cert}\n"
                                             f"  key: {key}\n"))


def test_operator_files_go_to_server_yaml_as_absolute_paths(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    cert, key = _operator_files(tmp_path)
    _use_tls(fleet_dir, "../op/cert.pem", str(key))  # relative to the fleet directory
    ops.render_fleet(fleet_dir)
    text = (fleet_dir / "server/server.yaml").read_text()
    assert f'tls_cert: "{cert.resolve()}"' in text and f'tls_key: "{key}"' in text
    generated = (fleet_dir / CERT_RELPATH).read_bytes()
    assert ops.set_endpoint(fleet_dir, "new.example:1").certificate_regenerated is False
    assert (fleet_dir / CERT_RELPATH).read_bytes() == generated


@pytest.mark.parametrize(
    ("break_it", "expected"),
    [
        (lambda c, k: c.unlink(), r"fleet\.yaml:\d+: tls\.cert: cannot read .*cert\.pem"),
        (lambda c, k: c.write_text("nope"), r"fleet\.yaml:\d+: tls\.cert: .*not a PEM cert"),
        (lambda c, k: k.write_text("nope"), r"fleet\.yaml:\d+: tls\.key: .*not an unencrypted"),
        (lambda c, k: k.write_text(self_signed(("x",), SystemKeySource()).key_pem.reveal()),
         r"fleet\.yaml:\d+: tls\.key: .*is not the key of the certificate"),
        (lambda c, k: (c.unlink(), c.symlink_to("/dev/zero")),
         r"fleet\.yaml:\d+: tls\.cert: .*cert\.pem: not a regular file"),
        (lambda c, k: (k.unlink(), os.mkfifo(k)),
         r"fleet\.yaml:\d+: tls\.key: .*key\.pem: not a regular file"),
        (lambda c, k: c.write_bytes(c.read_bytes() + b"\n" * MAX_PEM_BYTES),
         r"fleet\.yaml:\d+: tls\.cert: .*cert\.pem: larger than 1048576 bytes"),
        # Accepted at 0644: a private key anyone on the host could read.
        (lambda c, k: k.chmod(0o644), r"fleet\.yaml:\d+: tls\.key: .*key\.pem: readable or "
         r"writable by others \(mode 0644\): `chmod o-rwx` it"),
    ],
)
def test_bad_operator_files_change_nothing(tmp_path: Path, break_it: object,
                                           expected: str) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    cert, key = _operator_files(tmp_path)
    _use_tls(fleet_dir, str(cert), str(key))
    ops.render_fleet(fleet_dir)
    break_it(cert, key)  # type: ignore[operator]
    before = _snapshot(fleet_dir)
    with pytest.raises(ConfigError, match=expected) as info:
        ops.render_fleet(fleet_dir)
    assert "PRIVATE KEY" not in str(info.value)
    with pytest.raises(ConfigError, match=expected):
        ops.add_robot(fleet_dir, "r1")
    assert _snapshot(fleet_dir) == before


@pytest.mark.parametrize(("host", "covered"), [
    ("fleet.example.org", True), ("FLEET.example.org.", True), ("a.pages.example.org", True),
    ("pages.example.org", False), ("a.b.pages.example.org", False), ("vpn.example.com", False),
    ("192.0.2.7", True), ("[2001:db8::7]", True), ("2001:db8::8", False),
    ("localhost", False), ("127.0.0.1", False)])
def test_covers_checks_a_host_as_a_browser_does(tmp_path: Path, host: str,
                                                covered: bool) -> None:
    """The names of a certificate made here for other names than the endpoint's (as an
    operator's own `tls:` certificate may be)."""
    made = self_signed(("fleet.example.org", "*.pages.example.org", "192.0.2.7",
                        "2001:db8::7"), SystemKeySource())
    path = tmp_path / "cert.pem"
    path.write_bytes(made.cert_pem)
    names = cert_names(path)
    assert names is not None and covers(names, host) is covered
