"""Run the rosidl generators of the venv's Jazzy wheels on one package's .msg files.

This is what ``rosidl_generate_interfaces()`` does in CMake, minus CMake: .msg -> .idl
(rosidl_adapter), the RIHS01 type descriptions (rosidl_generator_type_description), then the
C structs (rosidl_generator_c), the C type supports (fastrtps_c, introspection_c, and the
typesupport_c dispatcher) and the Python classes (rosidl_generator_py). The C++ generators
are not run: rclpy uses only the C type supports.

The generators are called through the Python classes behind ``rosidl generate`` rather than
the ``rosidl`` command, because the wheels register every entry point twice (dist-info and
egg-info) and the command then refuses to run.
"""

from __future__ import annotations

import os
import pathlib
import sys
from dataclasses import dataclass
from pathlib import Path

# get_package_share_directory() finds the generators' templates through the ament index,
# which the wheels install under the venv prefix; nothing sets it in a plain venv.
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)

from rosidl_adapter.msg import convert_msg_to_idl
from rosidl_cli.command.hash.api import generate_type_hashes
from rosidl_cli.command.helpers import (
    build_type_description_tuples,
    generate_visibility_control_file,
    generator_arguments_file,
    legacy_generator_arguments,
)
from rosidl_generator_c import generate_c
from rosidl_generator_py.cli import GeneratePython
from rosidl_typesupport_c.cli import GenerateCTypesupport
from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
from rosidl_typesupport_introspection_c.cli import (
    GenerateIntrospectionCTypesupport,
)

# Output roots, named as rosidl's CMake names them (each holds <pkg>/msg/...).
GENERATOR_C = "rosidl_generator_c"
TYPESUPPORT_C = "rosidl_typesupport_c"
FASTRTPS_C = "rosidl_typesupport_fastrtps_c"
INTROSPECTION_C = "rosidl_typesupport_introspection_c"
GENERATOR_PY = "rosidl_generator_py"


@dataclass(frozen=True)
class Generated:
    """Where one package's generated sources are.

    Attributes:
        root: the package's generation directory; ``root/<GENERATOR_C>`` etc. are include
            roots (they hold ``<pkg>/msg/*.h``).
        idl_files: the translated ``msg/*.idl`` files.
        json_files: the type descriptions (``msg/*.json``, with the RIHS01 hashes).
        sources: per output root, the generated .c/.cpp files to compile.
        py_files: the generated Python modules (``msg/__init__.py``, ``msg/_*.py``).
    """

    root: Path
    idl_files: list[Path]
    json_files: list[Path]
    sources: dict[str, list[Path]]
    py_files: list[Path]


def generate(
    package: str, msg_files: list[Path], out: Path, include_share: list[Path]
) -> Generated:
    """Generate the C and Python sources of one message package.

    Args:
        package: ROS package name.
        msg_files: the package's .msg files.
        out: empty directory to write into.
        include_share: ``share`` directories holding the dependencies' ``<pkg>/msg/*.idl``.

    Returns:
        The generated files, by kind.

    Raises:
        Exception: whatever the generators raise on an invalid definition (they name the file).
    """
    idl_root = out / "idl"
    (idl_root / "msg").mkdir(parents=True, exist_ok=True)
    for msg in msg_files:
        convert_msg_to_idl(msg.parent.parent, package, Path("msg") / msg.name, idl_root / "msg")
    idl_tuples = [f"{idl_root}:msg/{msg.stem}.idl" for msg in msg_files]
    includes = [str(p) for p in include_share]
    json_files = _type_descriptions(package, idl_tuples, includes, out / "type_description")
    _generate_c(package, idl_tuples, includes, msg_files, json_files, out / GENERATOR_C / package)
    for name, ext in (
        (FASTRTPS_C, GenerateFastRTPSCTypesupport("fastrtps_c")),
        (INTROSPECTION_C, GenerateIntrospectionCTypesupport("introspection_c")),
        (TYPESUPPORT_C, GenerateCTypesupport("c")),
        (GENERATOR_PY, GeneratePython("py")),
    ):
        ext.generate(package, idl_tuples, includes, out / name / package)
    return Generated(
        root=out,
        idl_files=sorted((idl_root / "msg").glob("*.idl")),
        json_files=sorted(json_files),
        sources={
            name: sorted(
                p for p in (out / name).rglob("*") if p.suffix in (".c", ".cpp")
            )
            for name in (GENERATOR_C, FASTRTPS_C, INTROSPECTION_C, TYPESUPPORT_C, GENERATOR_PY)
        },
        py_files=sorted((out / GENERATOR_PY / package).rglob("*.py")),
    )


def _type_descriptions(
    package: str, idl_tuples: list[str], includes: list[str], out: Path
) -> list[Path]:
    """Write ``msg/<Type>.json`` type descriptions with their RIHS01 hashes."""
    groups = generate_type_hashes(
        package_name=package, interface_files=idl_tuples, include_paths=includes, output_path=out
    )
    return [Path(p) for p in _flatten(groups)]


def _flatten(items: object) -> list[str]:
    # generate_type_hashes returns a list of paths or of lists of paths, depending on how
    # many hash extensions are registered.
    if isinstance(items, str | pathlib.PurePath):
        return [str(items)]
    if isinstance(items, list | tuple):
        return [p for item in items for p in _flatten(item)]
    raise TypeError(f"unexpected type hash result {items!r}")


def _generate_c(
    package: str,
    idl_tuples: list[str],
    includes: list[str],
    msg_files: list[Path],
    json_files: list[Path],
    out: Path,
) -> None:
    """rosidl_generator_c, as CMake calls it.

    ``rosidl generate`` would embed the .idl text as each type's source; CMake embeds the
    .msg text (``ros_interface_files``), which is what ``get_type_description_sources``
    then serves. Doing it the CMake way keeps the generated code the same as apt's.
    """
    templates = Path(sys.prefix) / "share" / "rosidl_generator_c" / "resource"
    generate_visibility_control_file(
        package_name=package,
        template_path=templates / "rosidl_generator_c__visibility_control.h.in",
        output_path=out / "msg" / "rosidl_generator_c__visibility_control.h",
    )
    with generator_arguments_file(
        **legacy_generator_arguments(
            package_name=package,
            interface_files=idl_tuples,
            include_paths=includes,
            templates_path=templates,
            output_path=out,
        ),
        type_description_tuples=build_type_description_tuples(
            idl_tuples, [str(p) for p in json_files]
        ),
        ros_interface_files=[str(p) for p in msg_files],
    ) as arguments_file:
        generate_c(arguments_file)
