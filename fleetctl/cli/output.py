"""One renderer for every command's result: human text or ``--output json``.

Commands call library functions that return dataclasses; this module prints them. JSON
output is a stable, machine-readable form of the same result (dataclasses become
objects, paths/addresses/enums strings); secrets are shown as ``"<hidden>"`` unless the
command reveals one on purpose by putting the plain value into the result itself.
"""

from __future__ import annotations

import dataclasses
import enum
import ipaddress
import json
import re
import unicodedata
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import typer

from fleetctl.deploy.files import Change, ChangeKind
from fleetctl.deploy.secrets import Secret


class OutputFormat(enum.Enum):
    """How a command prints its result."""

    TEXT = "text"
    JSON = "json"


class AsciiInt:
    """Parse an integer option of ASCII digits in ``[low, high]`` (``int()`` and click's
    INT also take other scripts' digits, e.g. full-width ones)."""

    def __init__(self, low: int, high: int) -> None:
        self.low, self.high = low, high
        self.__name__ = "integer"  # how click names the type in messages

    def __call__(self, value: str | int) -> int:
        """Return the integer.

        Raises:
            typer.BadParameter: not ASCII digits, or out of range (usage, exit code 2).
        """
        if isinstance(value, int):
            return value
        if not re.fullmatch(r"[0-9]{1,9}", value):
            raise typer.BadParameter(f"{value[:40]!r} is not an integer (ASCII digits)")
        if not self.low <= int(value) <= self.high:
            raise typer.BadParameter(f"{value} is not in {self.low}..{self.high}")
        return int(value)


PORT = AsciiInt(1, 65535)
PORT_OR_ANY = AsciiInt(0, 65535)  # 0: any free port


def output_option() -> Any:
    """Return the shared ``--output/-o text|json`` option (use as a parameter default)."""
    return typer.Option(OutputFormat.TEXT, "--output", "-o", case_sensitive=False,
                        help="Print the result as text or as JSON.")


def fleet_option() -> Any:
    """Return the shared ``--fleet/-f DIR`` option, ``$FLEET_DIR`` else the current directory
    (use as a parameter default): every command that acts on a fleet takes it."""
    return typer.Option(Path("."), "--fleet", "-f", envvar="FLEET_DIR", show_default=False,
                        help="Fleet directory (default: $FLEET_DIR, else the current "
                        "directory).")


def to_jsonable(value: object) -> Any:
    """Convert a result into JSON-compatible data (recursively)."""
    if isinstance(value, Secret):
        return str(value)  # "<hidden>"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value)
    if isinstance(value, Path | ipaddress.IPv4Address | ipaddress.IPv4Network):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in value]
    if value is None or isinstance(value, str | int | float | bool):
        return value
    raise TypeError(f"cannot render {type(value).__name__} as JSON")


def emit(result: object, fmt: OutputFormat, text: Callable[[], str]) -> None:
    """Print *result* as JSON, or the text *text()* returns, to stdout."""
    if fmt is OutputFormat.JSON:
        typer.echo(json.dumps(to_jsonable(result), indent=2, sort_keys=True))
    else:
        typer.echo(text().rstrip("\n"))


def warn(line: str) -> None:
    """Print one warning line to stderr (``fleetctl: warning: ...``)."""
    typer.echo(f"fleetctl: warning: {line}", err=True)


def progress_line(line: str) -> None:
    """Print one progress line of a longer step to stderr (stdout stays the result)."""
    typer.echo(f"  {line}", err=True)


def display_width(text: str) -> int:
    """Terminal columns *text* takes: East Asian wide and full-width characters (kanji,
    most emoji) two, combining marks none, the rest one."""
    return sum(0 if unicodedata.combining(c) else
               2 if unicodedata.east_asian_width(c) in ("W", "F") else 1 for c in text)


def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """Return a plain text table with columns padded to their widest cell.

    Padded by terminal columns, not code points: e-mail addresses may be in any script
    (``a🤖@例え.jp``), and a wide character shifted every later column of its row.
    """
    cells = [[str(h) for h in headers], *[[str(c) for c in row] for row in rows]]
    widths = [max(display_width(row[i]) for row in cells) for i in range(len(headers))]
    return "\n".join(
        "  ".join(c + " " * (w - display_width(c))
                  for c, w in zip(row, widths, strict=True)).rstrip() for row in cells
    )


def changes_text(changes: Sequence[Change], root: Path, dry_run: bool) -> str:
    """Describe file changes, relative to *root*; unchanged files are only counted."""
    lines = []
    verb = "would " if dry_run else ""
    for c in changes:
        if c.kind is not ChangeKind.UNCHANGED:
            lines.append(f"  {verb}{c.kind.value} {_relative(c.path, root)}")
    unchanged = sum(1 for c in changes if c.kind is ChangeKind.UNCHANGED)
    if unchanged:
        lines.append(f"  {unchanged} file(s) already up to date")
    if not lines:
        lines.append("  nothing to do")
    return "\n".join(lines)


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)
