"""Compile one generated message package into the libraries a Jazzy wheel ships.

The layout copies the ros-jazzy message wheels (e.g. ros-geometry-msgs):

- ``<prefix>/lib/lib<pkg>__rosidl_generator_c.so`` (structs, init/fini, type hash),
  ``__rosidl_typesupport_fastrtps_c.so`` (CDR), ``__rosidl_typesupport_introspection_c.so``,
  ``__rosidl_typesupport_c.so`` (the dispatcher rmw asks; it dlopens the other two by name
  from ``LD_LIBRARY_PATH``, which ros_wheels_bootstrapper sets to ``<prefix>/lib``) and
  ``__rosidl_generator_py.so`` (Python <-> C conversion);
- ``site-packages/<pkg>/<pkg>_s__<typesupport>.so``: the Python extension modules that
  ``rosidl_generator_py.import_type_support`` imports.

No RPATH, like the wheels: the libraries are found through ``LD_LIBRARY_PATH``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from generate import (
    FASTRTPS_C,
    GENERATOR_C,
    GENERATOR_PY,
    INTROSPECTION_C,
    TYPESUPPORT_C,
    Generated,
)

# The Python-facing type supports, in the order rosidl_generator_py emits entry points.
PY_TYPESUPPORTS = (TYPESUPPORT_C, FASTRTPS_C, INTROSPECTION_C)


class BuildError(RuntimeError):
    """A compiler or linker call failed; the message holds the command and its output."""


@dataclass(frozen=True)
class Toolchain:
    """Compilers and the include/library directories of the venv's ROS wheels.

    Attributes:
        prefix: the venv (``sys.prefix``): ``include/<pkg>/`` and ``lib/`` of the wheels.
        cc: C compiler command.
        cxx: C++ compiler command.
        jobs: parallel compiler processes.
    """

    prefix: Path
    cc: str = os.environ.get("CC", "gcc")
    cxx: str = os.environ.get("CXX", "g++")
    jobs: int = os.cpu_count() or 1

    def include_flags(self, extra: Sequence[Path]) -> list[str]:
        """-I flags: the generated roots, the wheels' ROS include dirs, Python, numpy.

        Only ``include/<pkg>`` dirs in ROS's ``include/<pkg>/<pkg>/`` layout are added:
        others (flatbuffers has a ``string.h``) would shadow system headers.
        """
        include = self.prefix / "include"
        wheel_dirs = sorted(p for p in include.iterdir() if (p / p.name).is_dir())
        dirs = [*extra, include, *wheel_dirs, Path(sysconfig.get_paths()["include"])]
        dirs.append(Path(_numpy_include()))
        return [f"-I{d}" for d in dirs]


def _numpy_include() -> str:
    # rosidl_generator_py's C converters include numpy/ndarrayobject.h unconditionally.
    import numpy

    return str(numpy.get_include())


@dataclass(frozen=True)
class Target:
    """One shared object to link.

    Attributes:
        output: the .so path.
        objects: object files in it.
        libs: ``-l`` names, in link order.
        cxx: link with the C++ driver (some objects are C++).
        python_ext: may leave Python symbols undefined (they come from the interpreter).
    """

    output: Path
    objects: list[Path]
    libs: list[str]
    cxx: bool
    python_ext: bool = False


def referenced_packages(package: str, gen: Generated) -> list[str]:
    """Every package whose types the definitions reach, directly or through other types.

    The type description code calls each referenced type's description functions, so the
    generator_c library links ``std_msgs`` for ``TFMessage`` although the .msg names only
    ``geometry_msgs``. The type description JSON lists them all.
    """
    found: set[str] = set()
    for path in gen.json_files:
        description = json.loads(path.read_text())["type_description_msg"]
        for ref in description["referenced_type_descriptions"]:
            found.add(ref["type_name"].split("/", 1)[0])
    found.discard(package)
    return sorted(found)


def build_package(tools: Toolchain, package: str, gen: Generated, stage: Path) -> list[Path]:
    """Compile and link one package into ``stage/lib`` and ``stage/site/<package>``.

    Args:
        tools: compilers and the venv.
        package: ROS package name.
        gen: the generated sources.
        stage: output root.

    Returns:
        Every shared object written.

    Raises:
        BuildError: a compiler or linker failed.
    """
    roots = [gen.root / name for name in (GENERATOR_C, TYPESUPPORT_C, FASTRTPS_C,
                                          INTROSPECTION_C, GENERATOR_PY)]
    flags = tools.include_flags(roots)
    obj_dir = gen.root / "obj"
    jobs = [
        (src, obj_dir / src.relative_to(gen.root).with_suffix(src.suffix + ".o"))
        for name in gen.sources
        for src in gen.sources[name]
    ]
    with ThreadPoolExecutor(max_workers=tools.jobs) as pool:
        list(pool.map(lambda job: _compile(tools, flags, *job), jobs))
    objects = {src: obj for src, obj in jobs}
    targets = _targets(package, referenced_packages(package, gen), gen, objects, stage)
    for target in targets:
        _link(tools, target, stage / "lib")
    return [t.output for t in targets]


def _targets(
    package: str, deps: Sequence[str], gen: Generated, objects: dict[Path, Path], stage: Path
) -> list[Target]:
    """The link targets, in dependency order (a library before those linking it)."""
    lib, site = stage / "lib", stage / "site" / package

    def objs(name: str, keep: str = "") -> list[Path]:
        return [objects[s] for s in gen.sources[name] if keep in s.name]

    def own(kind: str) -> str:
        return f"{package}__{kind}"

    def of_deps(kind: str) -> list[str]:
        return [f"{dep}__{kind}" for dep in deps]

    base = ["rosidl_runtime_c", "rcutils"]
    py_objs = [objects[s] for s in gen.sources[GENERATOR_PY] if ".ep." not in s.name]
    targets = [
        Target(lib / f"lib{own(GENERATOR_C)}.so", objs(GENERATOR_C),
               [*of_deps(GENERATOR_C), *base], cxx=False),
        Target(lib / f"lib{own(INTROSPECTION_C)}.so", objs(INTROSPECTION_C),
               [own(GENERATOR_C), *of_deps(INTROSPECTION_C), *of_deps(GENERATOR_C),
                "rosidl_typesupport_introspection_c", *base], cxx=False),
        Target(lib / f"lib{own(FASTRTPS_C)}.so", objs(FASTRTPS_C),
               [own(GENERATOR_C), *of_deps(FASTRTPS_C), *of_deps(GENERATOR_C),
                "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "fastcdr",
                "rmw", "rosidl_dynamic_typesupport", *base], cxx=True),
        Target(lib / f"lib{own(TYPESUPPORT_C)}.so", objs(TYPESUPPORT_C),
               [own(GENERATOR_C), *of_deps(TYPESUPPORT_C), *of_deps(GENERATOR_C),
                "rosidl_typesupport_c", *base], cxx=True),
        Target(lib / f"lib{own(GENERATOR_PY)}.so", py_objs,
               [own(TYPESUPPORT_C), own(GENERATOR_C), *of_deps(GENERATOR_PY),
                *of_deps(GENERATOR_C), *base], cxx=False, python_ext=True),
    ]
    for ts in PY_TYPESUPPORTS:
        targets.append(Target(
            site / f"{package}_s__{ts}.so", objs(GENERATOR_PY, f".ep.{ts}."),
            [own(GENERATOR_PY), own(ts), own(TYPESUPPORT_C), own(GENERATOR_C), "rmw", *base],
            cxx=False, python_ext=True,
        ))
    return targets


def _compile(tools: Toolchain, flags: list[str], src: Path, obj: Path) -> None:
    obj.parent.mkdir(parents=True, exist_ok=True)
    argv = [tools.cxx, "-std=c++17"] if src.suffix == ".cpp" else [tools.cc, "-std=c11"]
    # -w: warnings in generated code are rosidl's to fix; errors still stop the build.
    _run([*argv, "-O2", "-fPIC", "-DNDEBUG", "-w", *flags, "-c", str(src), "-o", str(obj)])


def _link(tools: Toolchain, target: Target, stage_lib: Path) -> None:
    target.output.parent.mkdir(parents=True, exist_ok=True)
    lib_dirs = [f"-L{stage_lib}", f"-L{tools.prefix / 'lib'}"]
    # -z defs turns a missing -l into a link error here instead of an ImportError at
    # runtime; Python's own symbols are resolved by the interpreter, so not for those.
    checks = [] if target.python_ext else ["-Wl,-z,defs"]
    # Libraries carry their file name as soname, as the wheels' do; extension modules none.
    soname = [f"-Wl,-soname,{target.output.name}"] if target.output.parent == stage_lib else []
    _run([
        tools.cxx if target.cxx else tools.cc, "-shared", "-o", str(target.output),
        *map(str, target.objects), *lib_dirs, "-Wl,--as-needed", *checks, *soname,
        *(f"-l{name}" for name in target.libs),
    ])


def _run(argv: list[str]) -> None:
    proc = subprocess.run(argv, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise BuildError(f"{' '.join(argv)}\n{proc.stdout}{proc.stderr}")
    if proc.stderr.strip():
        print(proc.stderr.strip(), file=sys.stderr)
