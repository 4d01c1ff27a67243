"""Reaching a fleet server from the CLI: the TLS context of ``--ca-file``, and why a
connection failed, in the user's terms.

Shared by the commands that talk to a running fleet (``recordings``, ``foxglove-url``,
``replay``): each said its TLS failures its own way, or (``replay``) not at all.
"""

from __future__ import annotations

import ssl
from pathlib import Path

from websockets.exceptions import InvalidMessage

from fleetctl.errors import ConfigError

# OpenSSL's verify codes for a certificate that does not name the host or IP address asked
# for (X509_V_ERR_HOSTNAME_MISMATCH, X509_V_ERR_IP_ADDRESS_MISMATCH).
HOST_MISMATCH_CODES = frozenset({62, 64})


def ca_context(ca_file: Path | None) -> ssl.SSLContext | None:
    """A TLS context that trusts *ca_file*; ``None`` for no file (the system's CAs).

    Raises:
        ConfigError: The file cannot be read or holds no PEM certificate.
    """
    if ca_file is None:
        return None
    try:
        return ssl.create_default_context(cafile=str(ca_file))
    except OSError as exc:  # ssl.SSLError too: not PEM certificates
        raise ConfigError(f"--ca-file {ca_file}: cannot load a CA bundle from it: "
                          f"{exc.strerror or getattr(exc, 'reason', None) or exc}") from None


def why_unreachable(reason: object, scheme: str = "https") -> str:
    """Why a request or connection failed: a TLS handshake with a plain port, a plain
    request to a TLS port, or a certificate not trusted, is not "cannot reach it".

    Args:
        reason: The exception (or ``URLError.reason``) of the failed attempt.
        scheme: The URL's scheme (``http``, ``https``, ``ws``, ``wss``).
    """
    if (isinstance(reason, ssl.SSLCertVerificationError)
            and reason.verify_code in HOST_MISMATCH_CODES):
        # The CA is trusted; another --ca-file would not help (an operator's certificate
        # for the endpoint's name, asked for by `localhost` on the server host).
        return (f"its certificate is not for this host ({reason.verify_message}): use a "
                "host name or address it names in the URL (`fleetctl up` prints the page "
                "on the fleet endpoint's host)")
    if isinstance(reason, ssl.SSLCertVerificationError):
        # The usual first try against `fleetctl up`: its certificate is self-signed.
        return (f"its certificate is not trusted ({reason.verify_message}): give the CA "
                "that signed it with --ca-file (a fleet's own self-signed certificate is "
                "FLEET/server/tls/cert.pem)")
    if isinstance(reason, ssl.SSLError):
        return ("no TLS server answered there (a plain ws:// or http:// port? use the TLS "
                f"port, e.g. the web listener): {reason}")
    if ((scheme == "http" and isinstance(reason, ConnectionResetError))
            or (scheme == "ws" and isinstance(reason, InvalidMessage))):
        # A TLS listener (`fleetctl up`'s HTTPS port) hangs up on a plain request without
        # a word (http.client.RemoteDisconnected; websockets' "did not receive a valid
        # HTTP response").
        return (f"the server closed the connection without an answer (a TLS port? use "
                f"https:// or wss://): {reason}")
    if type(reason) is TimeoutError and not str(reason):
        # Accepted, then silence: a plain relay port waits for an HTTP line that a TLS
        # ClientHello never ends.
        plain = (" (a plain ws:// port? use the TLS port, e.g. the web listener)"
                 if scheme in ("wss", "https") else "")
        return f"the connection was accepted but the handshake got no answer in time{plain}"
    return f"cannot reach it: {reason}"
