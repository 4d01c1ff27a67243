"""Entry point of the ``fleetctl`` command.

Each command group lives in its own module with a ``register(app)`` function; this module
only assembles them and turns :class:`~fleetctl.errors.FleetError` into a message on stderr
and an exit code (never a traceback).
"""

from __future__ import annotations

import importlib
import sys

import typer

from fleetctl import __version__
from fleetctl.errors import FleetError

# Order is the order of `fleetctl --help`.
_COMMAND_MODULES = (
    "fleetctl.cli.fleet",  # init, add-robot, remove-robot, add-user, set-user, list, ...
    "fleetctl.cli.server",  # server
    "fleetctl.cli.client",  # client
    "fleetctl.cli.webviz",  # webviz
    "fleetctl.cli.demo",  # demo
    "fleetctl.cli.deploy",  # build, up, down, status, logs
    "fleetctl.cli.foxglove",  # foxglove-url
    "fleetctl.cli.recordings",  # recordings list, recordings fetch
    "fleetctl.cli.replay",  # replay
    "fleetctl.cli.schema",  # schema export
    "fleetctl.cli.e2e",  # e2e
)


# `fleetctl --help` groups commands by what an operator is doing. foxglove-url, recordings
# and replay talk to a fleet that runs (with a user's token); schema is for whoever writes a
# decoder of the wire format, as e2e is for whoever checks the product.
_SETUP, _RUN, _DEPLOY = "Set up a fleet", "Run one component", "Deploy"
_USE, _DEVELOP = "Use a running fleet", "Develop and test"
_PANELS = {
    **dict.fromkeys(("init", "set-endpoint", "add-robot", "remove-robot", "add-user",
                     "set-user", "remove-user", "list", "list-fleet", "render", "export"), _SETUP),
    **dict.fromkeys(("server", "client", "webviz", "demo"), _RUN),
    **dict.fromkeys(("build", "up", "down", "status", "logs"), _DEPLOY),
    **dict.fromkeys(("foxglove-url", "recordings", "replay"), _USE),
    **dict.fromkeys(("schema", "e2e"), _DEVELOP),
}


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"fleetctl {__version__}")
        raise typer.Exit()


def build_app() -> typer.Typer:
    """Build the typer application with every command group registered."""
    app = typer.Typer(
        name="fleetctl",
        help="Communication, monitoring and tasking for fleets of ROS 2 robots.",
        no_args_is_help=True,
        context_settings={"help_option_names": ["-h", "--help"]},
        pretty_exceptions_enable=False,
        add_completion=False,
    )

    @app.callback()
    def _root(
        version: bool = typer.Option(
            False, "--version", callback=_version_callback, is_eager=True, help="Print the version."
        ),
    ) -> None:
        """Communication, monitoring and tasking for fleets of ROS 2 robots."""

    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(app)
    for info in app.registered_commands:
        name = info.name or (info.callback.__name__ if info.callback else "")
        info.rich_help_panel = info.rich_help_panel or _PANELS.get(name.replace("_", "-"))
    for group in app.registered_groups:
        group.rich_help_panel = group.rich_help_panel or _PANELS.get(group.name or "")
    return app


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; return the process exit code.

    Click handles usage errors itself (exit code 2, a message on stderr); a
    :class:`FleetError` is printed as one line on stderr with its own exit code.
    """
    try:
        app = build_app()  # imports every command group: ~2 s on a small robot computer
    except KeyboardInterrupt:  # Ctrl-C meanwhile: the shell's convention, no traceback
        return 130
    try:
        app(args=argv, prog_name="fleetctl")
    except FleetError as exc:
        typer.echo(f"fleetctl: error: {exc}", err=True)
        return int(exc.exit_code)
    except SystemExit as exc:  # click's standalone mode always ends in sys.exit
        code = exc.code
        if code is None or isinstance(code, int):
            return int(code or 0)
        typer.echo(str(code), err=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
