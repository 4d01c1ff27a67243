"""Keys: X25519 as WireGuard's own tools see it, and secrets that stay hidden."""

from __future__ import annotations

import base64
import shutil
import subprocess

import pytest

from fleetctl.deploy.keys import (
    SystemKeySource,
    decode_key,
    new_preshared_key,
    new_private_key,
    new_token,
    public_key,
    token_sha256,
)
from fleetctl.deploy.secrets import Secret
from fleetctl.errors import ConfigError

needs_wg = pytest.mark.skipif(shutil.which("wg") is None, reason="wireguard-tools not installed")


@needs_wg
def test_public_key_matches_wg_pubkey() -> None:
    for _ in range(5):
        private = new_private_key(SystemKeySource())
        wg = subprocess.run(["wg", "pubkey"], input=private.reveal().encode(),
                            capture_output=True, check=True)
        assert wg.stdout.decode().strip() == public_key(private)


@needs_wg
def test_wg_genkey_private_key_is_accepted() -> None:
    genkey = subprocess.run(["wg", "genkey"], capture_output=True, check=True).stdout.decode()
    wg_pub = subprocess.run(["wg", "pubkey"], input=genkey.encode(), capture_output=True,
                            check=True).stdout.decode().strip()
    assert public_key(Secret(genkey.strip())) == wg_pub


def test_keys_are_32_bytes_base64() -> None:
    src = SystemKeySource()
    for secret in (new_private_key(src), new_preshared_key(src)):
        assert len(base64.b64decode(secret.reveal(), validate=True)) == 32
    assert new_private_key(src) != new_private_key(src)


def test_secret_hidden_in_repr_str_and_format() -> None:
    token = new_token(SystemKeySource())
    value = token.reveal()
    assert value not in repr(token)
    assert value not in str(token)
    assert value not in f"{token} {[token]} {({'k': token})}"


def test_token_hash_is_hex_sha256() -> None:
    assert token_sha256(Secret("test")) == (
        "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08")


@pytest.mark.parametrize("text", ["not base64!", base64.b64encode(b"short").decode()])
def test_malformed_key_error_does_not_echo_key(text: str) -> None:
    with pytest.raises(ConfigError) as info:
        decode_key(text, "keys/server.key")
    assert "keys/server.key" in str(info.value)
    assert text not in str(info.value)
