"""The project's exception hierarchy.

Every error a user can cause is a :class:`FleetError` with a message that names the file
and the field (or the peer and the frame) at fault. The CLI prints it to stderr and exits
with :attr:`FleetError.exit_code`; it never shows a traceback for one.
"""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    """Process exit codes of the ``fleetctl`` command."""

    OK = 0
    FAILURE = 1  # a check or an e2e pass criterion failed
    USAGE = 2  # typer/click usage errors use 2 as well
    CONFIG = 3  # a config, fleet.yaml or auth map is missing or invalid
    CONFLICT = 4  # a name, address or file already exists
    ENVIRONMENT = 5  # a tool or capability the command needs is missing
    RUNTIME = 6  # a component failed while running
    RETRY_LATER = 7  # the server refuses for now and said when to come back (HTTP 429)


class FleetError(Exception):
    """An error caused by input or environment, reported without a traceback."""

    exit_code: ExitCode = ExitCode.FAILURE

    def __init__(self, message: str, *, exit_code: ExitCode | None = None) -> None:
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = exit_code


class ConfigError(FleetError):
    """A configuration file is missing or invalid; the message names file and field."""

    exit_code = ExitCode.CONFIG


class ConflictError(FleetError):
    """Something that must be unique already exists."""

    exit_code = ExitCode.CONFLICT


class EnvironmentMissing(FleetError):
    """A tool, kernel feature or package the command needs is not available."""

    exit_code = ExitCode.ENVIRONMENT


class RetryLater(FleetError):
    """The server refused for now and asked to come back later (today: too many failed
    logins from this address, docs/security.md); nothing is wrong with the request
    itself, unless its token is.

    Attributes:
        retry_after_s: Seconds the server asked to wait, or ``None`` when it did not say.
    """

    exit_code = ExitCode.RETRY_LATER

    def __init__(self, message: str, retry_after_s: float | None) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s
