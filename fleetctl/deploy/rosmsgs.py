"""Build the ROS message wheels PyPI lacks (tf2_msgs, foxglove_msgs) for the client image.

The builder is ``scripts/ros_msgs/build.py``: in a checkout at that path, in an installed
fleetctl at ``fleetctl/_ros_msgs/build.py`` (``setup.py`` ships it with its ``.msg``
inputs). It must run under a Python with the ROS 2 wheels (the ``ros`` extra): this one when
it has them, else a venv made here from the image's own wheelhouses (``wheels/base`` and
``wheels/ros``, no index), kept beside them and reused while they are unchanged. So a plain
``pip install fleetctl`` builds a client image whose robots send TF, and the wheels link the
same ROS versions the image installs.

It also needs gcc, g++ and ``Python.h``: installed with apt when missing and running as root
(the base image's debootstrap already needs root), else a clear error naming the packages.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
import sysconfig
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from fleetctl.deploy.dockercli import Runner, check, subprocess_runner
from fleetctl.deploy.reqstamp import requirements_stamp, stamped_with, write_stamp
from fleetctl.errors import EnvironmentMissing

Progress = Callable[[str], None]

# Debian packages giving gcc, g++ and Python.h (g++ pulls gcc in).
BUILD_TOOL_PACKAGES = ("g++", "python3-dev")
VENV_DIR = "rosmsgs-venv"
BUILD_DIR = "rosmsgs-build"
_PACKAGE_DIR = Path(__file__).resolve().parents[1]


def missing_build_tools() -> list[str]:
    """The compilers and headers the builder needs that this machine lacks (empty: none)."""
    compilers = (os.environ.get("CC", "gcc"), os.environ.get("CXX", "g++"))
    missing = [tool for tool in compilers if shutil.which(tool) is None]
    include = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if not include.is_file():
        missing.append(str(include))
    return missing


def _has_ros_extra() -> bool:
    return importlib.util.find_spec("rosidl_adapter") is not None


def _is_root() -> bool:
    return os.geteuid() == 0


def _installed_version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def versions_differing(ros_house: Path,
                       installed_version: Callable[[str], str | None]) -> list[str]:
    """The ROS packages of the image's wheelhouse (*ros_house*) that this Python has in
    another version, or lacks: ``"ros_rcl 9.2.7 (image: 9.2.8)"``.

    Message wheels built against this Python's ROS must match the image's: a ROS package
    of another version may differ in its generated C (a typesupport symbol, a struct).
    """
    differing = []
    for wheel in sorted(ros_house.glob("ros_*.whl")):
        name, version = wheel.name.split("-")[:2]
        here = installed_version(name)
        if here != version:
            differing.append(f"{name} {here or 'missing'} (image: {version})")
    return differing


@dataclass(frozen=True)
class BuildHost:
    """What the build asks of this machine; unit tests pass made-up answers.

    Attributes:
        ros_extra: True when this Python has the ROS 2 wheels (no build venv needed when
            their versions are the image's).
        missing_tools: The compilers/headers still missing (see :func:`missing_build_tools`).
        is_root: True when apt may install what is missing.
        installed_version: A distribution's version in this Python, ``None`` if absent.
    """

    ros_extra: Callable[[], bool] = _has_ros_extra
    missing_tools: Callable[[], list[str]] = missing_build_tools
    is_root: Callable[[], bool] = _is_root
    installed_version: Callable[[str], str | None] = _installed_version


def builder_script(source_dir: Path | None, package_dir: Path | None = None) -> Path | None:
    """The builder: the checkout's, else the installed package's, else ``None``.

    Args:
        source_dir: The checkout being built, or ``None``.
        package_dir: The ``fleetctl`` package directory; ``None`` means this one. Its
            parent's ``scripts/ros_msgs`` is the last candidate: the checkout an editable
            install runs from, asked to build as if installed.
    """
    package_dir = package_dir or _PACKAGE_DIR
    roots = [source_dir / "scripts" / "ros_msgs"] if source_dir is not None else []
    roots += [package_dir / "_ros_msgs", package_dir.parent / "scripts" / "ros_msgs"]
    for root in roots:
        if (root / "build.py").is_file():
            return root / "build.py"
    return None


def ensure_build_tools(runner: Runner, progress: Progress, host: BuildHost) -> None:
    """Install gcc, g++ and Python's headers with apt when missing (needs root).

    Raises:
        EnvironmentMissing: missing and not root, or still missing after apt-get.
    """
    missing = host.missing_tools()
    if not missing:
        return
    packages = " ".join(BUILD_TOOL_PACKAGES)
    if not host.is_root():
        raise EnvironmentMissing(
            f"building tf2_msgs/foxglove_msgs for the client image needs "
            f"{', '.join(missing)}; run: sudo apt-get install {packages}")
    progress(f"ros message wheels: apt-get install {packages} (missing {', '.join(missing)})")
    res = runner(["apt-get", "install", "-y", "-qq", *BUILD_TOOL_PACKAGES], None, True)
    still = host.missing_tools()
    if res.returncode != 0 or still:
        # Python.h can stay missing after apt when this Python is not Debian's (pyenv, uv).
        raise EnvironmentMissing(
            f"apt-get install {packages} "
            + (f"failed: {res.stderr.strip()[-300:]}" if res.returncode else
               f"left {', '.join(still)} missing (is {sys.executable} Debian's Python? "
               "install its headers)"))


def ros_requirements_for_build(ros_reqs: Sequence[str]) -> list[str]:
    """The ROS packages of the ``ros`` extra: the builder needs nothing else (not av)."""
    return [req for req in ros_reqs if req.startswith("ros-")]


def build_venv(context: Path, ros_reqs: Sequence[str], runner: Runner,
               progress: Progress) -> Path:
    """The Python of a venv with the ROS wheels from ``context/wheels/{base,ros}``.

    Reused while the wheelhouses, the requirements and this Python are the same (its
    ``.inputs`` stamp); made again from scratch otherwise.

    Returns:
        The venv's ``bin/python``.

    Raises:
        FleetError: ``venv`` or ``pip install`` failed.
    """
    venv = context / VENV_DIR
    python = venv / "bin" / "python"
    houses = [context / "wheels" / name for name in ("base", "ros")]
    reqs = ros_requirements_for_build(ros_reqs)
    wheels = sorted(w.name for house in houses for w in house.glob("*.whl"))
    inputs = "\n".join([sys.version, requirements_stamp(reqs), *wheels])
    if python.exists() and stamped_with(venv, inputs):
        progress("ros message wheels: build venv up to date")
        return python
    shutil.rmtree(venv, ignore_errors=True)
    progress(f"ros message wheels: build venv {venv} from wheels/base and wheels/ros")
    # No pip inside (nor Debian's python3-venv for ensurepip): this pip installs into it.
    check(runner([sys.executable, "-m", "venv", "--without-pip", str(venv)], None, True),
          "ros message wheels: python -m venv")
    links = [arg for house in houses for arg in ("--find-links", str(house))]
    check(runner([sys.executable, "-m", "pip", "--python", str(python), "install", "-q",
                  "--no-index", *links, *reqs], None, True),
          "ros message wheels: pip install of the ROS wheels into the build venv")
    write_stamp(venv, inputs)
    return python


def build_ros_msg_wheels(source_dir: Path | None, dest: Path, ros_reqs: Sequence[str],
                         runner: Runner = subprocess_runner, progress: Progress = print,
                         host: BuildHost | None = None) -> bool:
    """Build tf2_msgs and foxglove_msgs wheels into *dest* (``<context>/wheels/rosmsgs``).

    Args:
        source_dir: The checkout being built, or ``None`` (the installed fleetctl).
        dest: Wheel directory; its parent holds the ``base`` and ``ros`` wheelhouses and
            the build venv and cache go beside that (``<context>/rosmsgs-*``).
        ros_reqs: The ``ros`` extra's requirements (for the build venv).
        runner: Runs the commands.
        progress: Gets one line per step.
        host: This machine's answers; ``None`` asks the machine.

    Returns:
        True when the wheels are in *dest*; False when the installation has no builder
        (*dest* then stays empty, the image is built without: its robots send no TF).

    Raises:
        EnvironmentMissing: compilers or headers missing and not installable.
        FleetError: the build venv or the build itself failed (its output is quoted).
    """
    host = host or BuildHost()
    dest.mkdir(parents=True, exist_ok=True)  # the Dockerfile's COPY needs it even empty
    script = builder_script(source_dir)
    if script is None:
        progress("ros message wheels: skipped (this fleetctl installation lacks "
                 "fleetctl/_ros_msgs; reinstall it): the client image has no tf2_msgs, "
                 "its robots send no TF")
        return False
    ensure_build_tools(runner, progress, host)
    context = dest.parent.parent
    python = Path(sys.executable)
    if not host.ros_extra():
        python = build_venv(context, ros_reqs, runner, progress)
    elif differing := versions_differing(context / "wheels" / "ros", host.installed_version):
        progress(f"ros message wheels: this Python's ROS packages are not the image's "
                 f"({', '.join(differing[:3])}{', ...' if len(differing) > 3 else ''}): "
                 "building in a venv of the image's wheels")
        python = build_venv(context, ros_reqs, runner, progress)
    progress(f"ros message wheels: tf2_msgs, foxglove_msgs ({script})")
    check(runner([str(python), str(script), "--no-install", "--wheel-dir", str(dest),
                  "--build-dir", str(context / BUILD_DIR)], None, True),
          f"ros message wheels ({script})")
    return True
