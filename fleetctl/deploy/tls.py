"""The certificate of the one HTTPS port people use (the web page and ``wss://``).

Either the operator's own files (``tls: {cert, key}`` in fleet.yaml), checked here, or a
self-signed certificate fleetctl makes: EC P-256, valid one year, for ``localhost``,
``127.0.0.1``, ``::1`` and the endpoint's host. The certificate is public
(``server/tls/cert.pem``, 0644); its key is a secret (``keys/tls.key``, 0600, written like
every key file). A browser warns about a self-signed certificate until the operator
installs their own.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import ipaddress
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from fleetctl.deploy.files import Plan
from fleetctl.deploy.keys import KeySource
from fleetctl.deploy.keystore import KEYS_DIR, plan_secret_file
from fleetctl.deploy.secrets import Secret
from fleetctl.deploy.yamlnodes import FleetInvalid
from fleetctl.smallfile import MAX_PEM_BYTES, read_small

CERT_RELPATH = "server/tls/cert.pem"
KEY_RELPATH = f"{KEYS_DIR}/tls.key"
VALIDITY = datetime.timedelta(days=365)
# `render` makes the self-signed certificate again this long before it ends.
RENEW_BEFORE = datetime.timedelta(days=30)
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")

Clock = Callable[[], datetime.datetime]


def _utc_now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


@dataclass(frozen=True)
class SelfSigned:
    """A generated certificate (PEM) and its private key (PEM, kept secret)."""

    cert_pem: bytes
    key_pem: Secret


def san_names(endpoint_host: str | None) -> tuple[str, ...]:
    """Return the names a generated certificate is for, in a fixed order."""
    names = list(LOCAL_NAMES)
    host = endpoint_host.strip("[]") if endpoint_host else None
    if host and host not in names:
        names.append(host)
    return tuple(names)


def _general_name(name: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _private_key(source: KeySource) -> ec.EllipticCurvePrivateKey:
    # From the injected source (not the library's own RNG), so tests control key material;
    # reduced into [1, n-1] of P-256 (64 bytes make the modulo bias negligible).
    order = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551
    value = int.from_bytes(source.random_bytes(64), "big") % (order - 1) + 1
    return ec.derive_private_key(value, ec.SECP256R1())


def self_signed(names: tuple[str, ...], source: KeySource, now: Clock = _utc_now) -> SelfSigned:
    """Make a self-signed EC P-256 certificate for *names*, valid from now for a year."""
    key = _private_key(source)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, names[-1])])
    start = now() - datetime.timedelta(minutes=5)  # tolerate a slightly slow client clock
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject).issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(int.from_bytes(source.random_bytes(16), "big") >> 1 or 1)
        .not_valid_before(start).not_valid_after(start + VALIDITY)
        .add_extension(x509.SubjectAlternativeName([_general_name(n) for n in names]),
                       critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    return SelfSigned(cert.public_bytes(serialization.Encoding.PEM), Secret(key_pem.decode()))


def cert_names(cert_path: Path) -> tuple[str, ...] | None:
    """Return the SAN names of the certificate at *cert_path*; ``None`` if unreadable."""
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except (OSError, ValueError, x509.ExtensionNotFound):
        return None
    return tuple(str(n.value) for n in san)


def covers(names: tuple[str, ...], host: str) -> bool:
    """Whether a certificate for SAN *names* (as :func:`cert_names` returns them) is valid
    for *host* as a browser checks it (RFC 6125 section 6.4): an IP address against the IP
    entries, a name against the DNS entries without regard to case, ``*`` only as the whole
    left-most label, standing for exactly one label.

    Args:
        host: the URL's host; an IPv6 address may be in brackets.
    """
    host = host.strip("[]")
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return any(_dns_match(name, host) for name in names)
    for name in names:
        with contextlib.suppress(ValueError):
            if ipaddress.ip_address(name) == ip:
                return True
    return False


def _dns_match(pattern: str, host: str) -> bool:
    pattern, host = pattern.lower().rstrip("."), host.lower().rstrip(".")
    if pattern.startswith("*."):
        first, dot, rest = host.partition(".")
        return bool(first) and bool(dot) and rest == pattern[2:]
    return pattern == host


def expires_soon(cert_path: Path, now: Clock = _utc_now) -> datetime.datetime | None:
    """When the certificate at *cert_path* ends, if within :data:`RENEW_BEFORE` of *now*
    (or already past); ``None`` when later, or when it cannot be read."""
    try:
        end = x509.load_pem_x509_certificate(cert_path.read_bytes()).not_valid_after_utc
    except (OSError, ValueError):
        return None
    return end if end - now() <= RENEW_BEFORE else None


def plan_self_signed(plan: Plan, fleet_dir: Path, cert: SelfSigned) -> None:
    """Add writing a generated certificate (0644) and its key (0600, ``keys/``) to *plan*."""
    plan.write(fleet_dir / CERT_RELPATH, cert.cert_pem)
    plan_secret_file(plan, fleet_dir / KEY_RELPATH, cert.key_pem.reveal())


def check_operator_files(cert_path: Path, key_path: Path) -> None:
    """Check the operator's certificate and key: readable, PEM, and a matching pair.

    Raises:
        FleetInvalid: naming ``tls.cert`` or ``tls.key``; never showing key material.
    """
    try:
        cert = x509.load_pem_x509_certificate(_read(cert_path, "cert"))
    except ValueError:
        raise FleetInvalid(("tls", "cert"), f"{cert_path}: not a PEM certificate") from None
    key_pem = _read(key_path, "key")
    with contextlib.suppress(OSError):  # _read just read it: a race at most
        mode = stat.S_IMODE(key_path.stat().st_mode)
        if mode & 0o007:
            # As ssh refuses such a private key; group read stays allowed, as Debian's
            # ssl-cert group keeps server keys 0640.
            raise FleetInvalid(("tls", "key"), f"{key_path}: readable or writable by others "
                               f"(mode {mode:04o}): `chmod o-rwx` it if nobody else could "
                               "read it, otherwise replace the key")
    try:
        key = serialization.load_pem_private_key(key_pem, password=None)
    except (ValueError, TypeError):
        raise FleetInvalid(("tls", "key"), f"{key_path}: not an unencrypted PEM private "
                           "key") from None
    spki = serialization.PublicFormat.SubjectPublicKeyInfo
    if (key.public_key().public_bytes(serialization.Encoding.DER, spki)
            != cert.public_key().public_bytes(serialization.Encoding.DER, spki)):
        raise FleetInvalid(("tls", "key"), f"{key_path} is not the key of the certificate "
                           f"{cert_path}")


def _read(path: Path, field_name: str) -> bytes:
    # A PEM certificate chain or key is a few KiB: a device or FIFO such as /dev/zero must
    # not be read until memory runs out (read_small refuses it).
    try:
        return read_small(path, MAX_PEM_BYTES)
    except OSError as exc:
        if exc.errno == errno.EFBIG:
            raise FleetInvalid(("tls", field_name),
                               f"{path}: larger than {MAX_PEM_BYTES} bytes, not a PEM file"
                               ) from None
        if exc.errno == errno.EINVAL:
            raise FleetInvalid(("tls", field_name), f"{path}: not a regular file") from None
        raise FleetInvalid(("tls", field_name),
                           f"cannot read {path}: {exc.strerror or type(exc).__name__}") from None
