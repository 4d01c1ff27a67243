"""TLS server contexts of the relay's listeners, with errors a user can act on."""

from __future__ import annotations

import ssl
from pathlib import Path

from fleetctl.errors import ConfigError


def server_context(cert: Path, key: Path) -> ssl.SSLContext:
    """Return a TLS server context holding the certificate chain *cert* and its *key*.

    Args:
        cert: PEM certificate (chain) file.
        key: PEM private key file (unencrypted: the server cannot ask for a passphrase).

    Raises:
        ConfigError: Either file cannot be read, is not PEM, or the key does not match the
            certificate; the message names both files and what ssl said. The caller
            prefixes the config file and field.
    """
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        # An empty password makes an encrypted key fail here instead of prompting on a tty.
        context.load_cert_chain(cert, key, password="")
    except OSError as exc:  # ssl.SSLError is an OSError too
        reason = getattr(exc, "reason", None) or exc.strerror or str(exc)
        raise ConfigError(
            f"ssl cannot load the certificate {cert} with the key {key}: {reason} "
            "(expected a PEM certificate and its matching, unencrypted PEM private key)"
        ) from None
    return context
