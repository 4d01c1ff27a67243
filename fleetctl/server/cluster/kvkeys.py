"""Names as JetStream KV key tokens (the shared registry's and latched messages' keys).

KV keys allow ``A-Z a-z 0-9 - _ = / .``, with ``.`` separating tokens. A robot name, an
identity name or a topic may hold anything else, so each becomes one token: ``A-Z a-z 0-9
_ -`` stay, every other UTF-8 byte is ``=HH``. ``=`` itself is escaped, so the mapping is
one-to-one, and ``/`` and ``.`` never appear in a token: callers use them as separators.
"""

from __future__ import annotations

_HEX = frozenset("0123456789ABCDEF")  # as key_token writes them
_SAFE = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")


def key_token(name: str) -> str:
    """*name* as one KV key token."""
    return "".join(c if c in _SAFE else "".join(f"={b:02X}" for b in c.encode())
                   for c in name)


def from_key_token(token: str) -> str:
    """The inverse of :func:`key_token`.

    Raises:
        ValueError: Not a token :func:`key_token` makes.
        UnicodeDecodeError: Its bytes are not UTF-8.
    """
    out = bytearray()
    i = 0
    while i < len(token):
        if token[i] == "=":
            hex_digits = token[i + 1:i + 3]
            if len(hex_digits) != 2 or not set(hex_digits) <= _HEX:
                raise ValueError(f"bad escape in key token {token!r}")
            out.append(int(hex_digits, 16))
            i += 3
        elif token[i] in _SAFE:
            out += token[i].encode()
            i += 1
        else:
            raise ValueError(f"bad key token {token!r}")
    return out.decode()
