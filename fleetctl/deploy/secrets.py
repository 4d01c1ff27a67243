"""A wrapper that keeps secrets out of reprs, logs and tracebacks."""

from __future__ import annotations

from typing import Final

_HIDDEN: Final = "<hidden>"


class Secret:
    """A secret string (a private key, preshared key or token).

    ``repr()`` and ``str()`` never show the value, so a secret that ends up in a log line,
    an f-string or a traceback's locals stays hidden. Call :meth:`reveal` where the value is
    really needed (writing a key file, printing a new token once).
    """

    __slots__ = ("_value",)

    def __init__(self, value: str) -> None:
        self._value = value

    def reveal(self) -> str:
        """Return the secret value."""
        return self._value

    def __repr__(self) -> str:
        return f"Secret({_HIDDEN})"

    def __str__(self) -> str:
        return _HIDDEN

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Secret) and other._value == self._value

    def __hash__(self) -> int:
        return hash(self._value)
