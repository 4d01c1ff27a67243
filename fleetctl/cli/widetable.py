"""A table whose last column is a list of names cut to the terminal's width.

``recordings list`` put every topic of a file in its TOPICS cell: with 20 topics every
row was hundreds of characters and wrapped into an unreadable block. The other columns
are short and fixed; the list is cut to what is left of the terminal's width (at least
:data:`MIN_LIST_WIDTH`), ending with ``+N more``; ``-o json`` and an ``--all-...`` flag
of the command give the full list.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence

from fleetctl.cli.output import table

MIN_LIST_WIDTH = 32  # a narrow terminal still shows a name or two
SEPARATOR = ", "


def terminal_columns() -> int:
    """The terminal's width in characters (``$COLUMNS`` first; 80 when not a terminal)."""
    return shutil.get_terminal_size((80, 24)).columns


def fit_names(names: Sequence[str], width: int, noun: str = "names") -> str:
    """*names* joined by ``", "`` in at most *width* characters where possible: as many
    as fit, then ``+N more``; ``N <noun>`` when not even the first fits; ``-`` for none."""
    full = SEPARATOR.join(names)
    if not names:
        return "-"
    if len(full) <= width:
        return full
    shown: list[str] = []
    for i, name in enumerate(names):
        rest = len(names) - i - 1
        if len(SEPARATOR.join([*shown, name]) + (f" +{rest} more" if rest else "")) > width:
            break
        shown.append(name)
    if not shown:
        return f"{len(names)} {noun}"
    return SEPARATOR.join(shown) + f" +{len(names) - len(shown)} more"


def table_with_names(headers: Sequence[str], rows: Sequence[Sequence[object]],
                     names: Sequence[Sequence[str]], width: int | None,
                     noun: str = "names") -> str:
    """A :func:`~fleetctl.cli.output.table` of *rows* plus a last column (the last of
    *headers*) holding each row's *names*, cut to fit *width* characters (``None``: not
    cut; see :func:`fit_names`)."""
    if width is None:
        return table(headers, [(*r, SEPARATOR.join(n) or "-") for r, n in
                               zip(rows, names, strict=True)])
    fixed = table(headers[:-1], rows).splitlines()
    room = max(width - max(len(line) for line in fixed) - 2, MIN_LIST_WIDTH)
    return table(headers, [(*r, fit_names(n, room, noun))
                           for r, n in zip(rows, names, strict=True)])
