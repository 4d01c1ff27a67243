"""``fleetctl schema``: the wire format's schemas (``.fbs`` for flatc, JSON layouts)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import typer

from fleetctl.cli.output import OutputFormat, emit, output_option
from fleetctl.errors import ConflictError, ExitCode, FleetError
from fleetctl.wire.errors import WireError
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe, export_fbs


@dataclass(frozen=True)
class ExportResult:
    """What ``schema export`` wrote.

    Attributes:
        out_dir: The export directory.
        files: The ``.fbs`` files written, sorted.
    """

    out_dir: Path
    files: list[Path]


class UnknownTypeError(FleetError):
    """A message type given on the command line is unknown or malformed."""

    exit_code = ExitCode.USAGE


def _registry(from_ros: bool) -> TypeRegistry:
    registry = TypeRegistry.default()
    if from_ros:
        try:
            registry.from_rclpy()
        except WireError as exc:
            raise FleetError(f"installed ROS message definitions: {exc}") from exc
    return registry


def export(out_dir: Path, types: list[str] | None, *, from_ros: bool = False) -> ExportResult:
    """Write ``.fbs`` files for *types* (None: all known) and their dependencies.

    Exit codes as for ``fleetctl export --out`` (docs/operator.md): a path that is there
    and not a directory is a conflict (4), one that cannot be written an environment
    error (5).

    Raises:
        UnknownTypeError: A type is unknown or malformed.
        ConflictError: *out_dir* exists and is not a directory.
        FleetError: (exit code 5) The directory cannot be written.
    """
    registry = _registry(from_ros)
    if os.path.lexists(out_dir) and not out_dir.is_dir():
        raise ConflictError(f"{out_dir}: exists and is not a directory (give a new or "
                            "existing directory to write the .fbs files into)")
    try:
        files = export_fbs(registry, types or None, out_dir)
    except WireError as exc:
        raise UnknownTypeError(f"--type: {exc}") from exc
    except OSError as exc:
        raise FleetError(f"{out_dir}: cannot write schemas: {exc.strerror or exc}",
                         exit_code=ExitCode.ENVIRONMENT) from exc
    return ExportResult(out_dir, files)


def register(app: typer.Typer) -> None:
    """Add the ``schema`` command group to *app*."""
    schema_app = typer.Typer(help="Wire-format schemas: .fbs files for flatc, JSON layouts.",
                             no_args_is_help=True)

    @schema_app.command("export")
    def export_command(
        out_dir: Path = typer.Argument(..., help="Directory to write the .fbs files into."),
        types: list[str] = typer.Option(
            None, "--type", "-t",
            help="Message type (pkg/msg/Name or pkg/Name); repeat for more. Default: all.",
        ),
        from_ros: bool = typer.Option(
            False, "--from-ros", help="Also load the .msg files of installed ROS packages."
        ),
        output: OutputFormat = output_option(),
    ) -> None:
        """Write FlatBuffers schemas (flatc -I DIR accepts them) for message types."""
        result = export(out_dir, types, from_ros=from_ros)
        emit(result, output, lambda: f"wrote {len(result.files)} .fbs files to {out_dir}")

    @schema_app.command("describe")
    def describe_command(
        type_name: str = typer.Argument(..., help="Message type, e.g. sensor_msgs/msg/LaserScan."),
        from_ros: bool = typer.Option(
            False, "--from-ros", help="Also load the .msg files of installed ROS packages."
        ),
    ) -> None:
        """Print the JSON layout (vtable slots, kinds) a decoder of TYPE needs."""
        try:
            layout = describe(_registry(from_ros), type_name)
        except WireError as exc:
            raise UnknownTypeError(str(exc)) from exc
        typer.echo(json.dumps(layout, indent=2))

    @schema_app.command("types")
    def types_command(
        from_ros: bool = typer.Option(
            False, "--from-ros", help="Also load the .msg files of installed ROS packages."
        ),
        output: OutputFormat = output_option(),
    ) -> None:
        """List the known message types."""
        names = _registry(from_ros).names()
        emit(names, output, lambda: "\n".join(names))

    app.add_typer(schema_app, name="schema")
