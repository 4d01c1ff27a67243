"""How a person's token is stored: the one rule shared by the server and every writer.

The auth map never holds a token, only ``token_sha256``: the lowercase hex SHA-256 of the
token's UTF-8 bytes. The server hashes what a client presents and compares; ``fleetctl
add-user``, the demo and the e2e runs hash the tokens they hand out.

A token a client presents is untrusted text: it may be anything a header or a JSON string
can carry (lone surrogates, ``\\xff`` read from a header). Only printable ASCII of a sane
length can be a token (:func:`is_wellformed_token`); everything else is a bad token, never
an exception.
"""

from __future__ import annotations

import hashlib

# Why a cap: tokens handed out are ~24-43 characters; hashing megabytes buys nothing.
MAX_TOKEN_CHARS = 1024


def hash_token(token: str) -> str:
    """Return the hex SHA-256 of *token*'s UTF-8 bytes, as the auth map stores it.

    Raises:
        UnicodeEncodeError: *token* holds lone surrogates (check it with
            :func:`is_wellformed_token` first when it comes from a client).
    """
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def is_wellformed_token(token: object) -> bool:
    """Whether *token* can be a token at all: a non-empty string of at most
    :data:`MAX_TOKEN_CHARS` printable ASCII characters (``!`` to ``~``)."""
    return (isinstance(token, str) and 0 < len(token) <= MAX_TOKEN_CHARS
            and token.isascii() and token.isprintable() and " " not in token)
