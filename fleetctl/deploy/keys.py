"""WireGuard keys (X25519, base64) and user tokens.

Key material is produced by a :class:`KeySource`, so tests can inject a deterministic one
and golden files stay stable. Every secret is wrapped in :class:`~fleetctl.deploy.secrets.Secret`.
"""

from __future__ import annotations

import base64
import binascii
import secrets
from typing import Protocol

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey

from fleetctl.deploy.secrets import Secret
from fleetctl.errors import ConfigError
from fleetctl.tokens import hash_token

KEY_BYTES = 32  # X25519 keys and WireGuard preshared keys are both 32 bytes


class KeySource(Protocol):
    """Where new key material comes from."""

    def random_bytes(self, n: int) -> bytes:
        """Return *n* bytes suitable for a private key, preshared key or token."""
        ...


class SystemKeySource:
    """Key material from the operating system's CSPRNG (the default)."""

    def random_bytes(self, n: int) -> bytes:
        """Return *n* cryptographically secure random bytes."""
        return secrets.token_bytes(n)


def new_private_key(source: KeySource) -> Secret:
    """Return a new WireGuard private key, base64 (as ``wg genkey`` prints it)."""
    raw = X25519PrivateKey.from_private_bytes(source.random_bytes(KEY_BYTES)).private_bytes_raw()
    return Secret(base64.b64encode(raw).decode("ascii"))


def new_preshared_key(source: KeySource) -> Secret:
    """Return a new WireGuard preshared key: 32 random bytes, base64 (``wg genpsk``)."""
    return Secret(base64.b64encode(source.random_bytes(KEY_BYTES)).decode("ascii"))


def new_token(source: KeySource) -> Secret:
    """Return a new user token: 32 random bytes, URL-safe base64 without padding."""
    raw = source.random_bytes(KEY_BYTES)
    return Secret(base64.urlsafe_b64encode(raw).rstrip(b"=").decode("ascii"))


def token_sha256(token: Secret) -> str:
    """Return the hex SHA-256 of a token's UTF-8 bytes, as the auth map stores it."""
    return hash_token(token.reveal())


def decode_key(text: str, what: str) -> bytes:
    """Decode a base64 WireGuard key, checking that it is 32 bytes.

    Args:
        text: the base64 text (surrounding whitespace is ignored).
        what: names the key in the error (e.g. the file it came from).

    Raises:
        ConfigError: if *text* is not base64 of exactly 32 bytes. The message never
            contains the key itself.
    """
    try:
        raw = base64.b64decode(text.strip(), validate=True)
    except (binascii.Error, ValueError):
        raise ConfigError(f"{what}: not a base64 WireGuard key") from None
    if len(raw) != KEY_BYTES:
        raise ConfigError(f"{what}: a WireGuard key is {KEY_BYTES} bytes, got {len(raw)}")
    return raw


def public_key(private_key: Secret, what: str = "private key") -> str:
    """Return the base64 public key of a base64 private key (what ``wg pubkey`` prints).

    Raises:
        ConfigError: if the private key is malformed (see :func:`decode_key`).
    """
    raw = decode_key(private_key.reveal(), what)
    pub = X25519PrivateKey.from_private_bytes(raw).public_key().public_bytes_raw()
    return base64.b64encode(pub).decode("ascii")
