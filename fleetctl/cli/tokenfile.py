"""``--token-file``: the one way a command reads a Bearer token.

A token on the command line would land in shell history and ``ps``; commands take the path of
a file holding it instead (what ``fleetctl add-user`` writes, 0600).
"""

from __future__ import annotations

import os
import re
import stat
import sys
from pathlib import Path

from fleetctl.errors import ConfigError
from fleetctl.smallfile import MAX_SECRET_BYTES, read_small_text

_TOKEN = re.compile(r"[\x21-\x7e]+")


def read_token_file(token_file: Path | None) -> str | None:
    """The token in *token_file* without surrounding whitespace; ``None`` when no file is given.

    Raises:
        ConfigError: the file cannot be read or holds nothing (the message names the option
            and the file, never the token).
    """
    if token_file is None:
        return None
    try:
        token = read_small_text(token_file, MAX_SECRET_BYTES).strip()
    except OSError as exc:
        raise ConfigError(f"--token-file {token_file}: cannot read: "
                          f"{exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"--token-file {token_file}: not UTF-8 text") from None
    if not token:
        raise ConfigError(f"--token-file {token_file}: the file is empty")
    if not _TOKEN.fullmatch(token):
        # It goes into an HTTP header (Authorization: Bearer ...), where a line break or a
        # non-ASCII character cannot go (http.client raised ValueError on it).
        raise ConfigError(f"--token-file {token_file}: the token must be one line of "
                          "printable ASCII without spaces")
    _warn_if_others_may_read(token_file)
    return token


def _warn_if_others_may_read(token_file: Path) -> None:
    """A warning on stderr when users other than the owner may read *token_file*.

    Not refused, unlike the fleet's keys: people write token files themselves (a shell
    redirect under the usual umask makes them 0644), and a command that worked yesterday
    should not stop; the warning says how to close it.
    """
    try:
        mode = os.stat(token_file).st_mode
    except OSError:
        return
    if mode & (stat.S_IRGRP | stat.S_IROTH):
        print(f"warning: --token-file {token_file}: other users may read it (mode "
              f"{stat.S_IMODE(mode):04o}); chmod 600 it", file=sys.stderr)
