"""Errors of the wire format."""

from __future__ import annotations


class WireError(ValueError):
    """A frame or message cannot be encoded or decoded.

    Raised for malformed, truncated or hostile frames, unknown or malformed type names, and
    messages that do not fit their type. The message says what is wrong and where (type,
    field, byte offset), so it can go straight into an error frame or a log line.
    """
