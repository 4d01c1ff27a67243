"""How a person's token is stored: the one rule shared by the server and every writer.

The auth map never holds a token, only ``token_sha256``: the lowercase hex SHA-256 of the
token's UTF-8 bytes. The server hashes what a client presents and compares; ``fleetctl
add-user``, the demo and the e2e runs hash the tokens they hand out.
"""

from __future__ import annotations

import hashlib


def hash_token(token: str) -> str:
    """Return the hex SHA-256 of *token*'s UTF-8 bytes, as the auth map stores it."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()
