"""Read a small file whole (a config, a key, a token, a certificate) and nothing else.

``Path.read_text`` reads until the end of the file: a config or key path that names (or is a
symlink to) ``/dev/zero`` reads until memory runs out, and a FIFO without a writer blocks the
command forever. Every config, key and token read goes through :func:`read_small`, which
refuses anything but a regular file and stops after *limit* bytes.

The refusals are raised as :class:`OSError` with ``strerror`` set to the reason, so the
callers' existing ``except OSError`` clauses report them with the file and field they name.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

# Sizes: the largest of each kind of file that is still plausibly one. A fleet.yaml of
# thousands of robots is well under a MiB; keys and tokens are tens of bytes.
MAX_CONFIG_BYTES = 8 << 20
MAX_PEM_BYTES = 1 << 20
MAX_SECRET_BYTES = 64 << 10


def read_small(path: Path, limit: int, *, follow_symlinks: bool = True) -> bytes:
    """The whole content of the regular file *path*, at most *limit* bytes.

    Raises:
        OSError: The file cannot be opened (as ``open`` raises it), its path holds a NUL
            byte (``EINVAL``), is not a regular file (``EINVAL``, "not a regular file"), or
            is larger than *limit* (``EFBIG``).
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC  # NONBLOCK: a FIFO must not hang
    if not follow_symlinks:
        flags |= os.O_NOFOLLOW
    if "\0" in str(path):  # os.open raises ValueError, which no caller expects
        raise OSError(errno.EINVAL, "the path contains a NUL byte", str(path))
    fd = os.open(path, flags)
    with os.fdopen(fd, "rb") as stream:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        data = stream.read(limit + 1)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
    return data


def read_small_text(path: Path, limit: int = MAX_CONFIG_BYTES, *, encoding: str = "utf-8",
                    follow_symlinks: bool = True) -> str:
    """:func:`read_small`, decoded.

    Raises:
        OSError: As :func:`read_small`.
        UnicodeDecodeError: The content is not *encoding*.
    """
    return read_small(path, limit, follow_symlinks=follow_symlinks).decode(encoding)
