"""Unit tests of the ROS message-wheel build's choices: which builder, which Python, which
tools (a fake runner and made-up host answers; nothing is compiled)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

from fleetctl.deploy import rosmsgs
from fleetctl.deploy.dockercli import Completed
from fleetctl.errors import EnvironmentMissing

REPO = Path(__file__).resolve().parents[2]
ROS_REQS = ["ros-jazzy-rclpy[fastrtps]>=7,<8", "ros-jazzy-std-msgs>=5,<6", "av>=16,<20"]


class FakeRunner:
    """Records commands; ``python -m venv DIR`` leaves a ``DIR/bin/python`` as venv would."""

    def __init__(self, fail: str = "") -> None:
        self.calls: list[list[str]] = []
        self.fail = fail

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        self.calls.append(list(argv))
        if argv[1:3] == ["-m", "venv"]:
            python = Path(argv[-1]) / "bin" / "python"
            python.parent.mkdir(parents=True)
            python.write_text("")
        failed = bool(self.fail) and self.fail in argv
        return Completed(tuple(argv), 1 if failed else 0, "", "E: boom" if failed else "")


def host(ros_extra: bool = False, missing: Sequence[list[str]] = ([],),
         root: bool = False, versions: dict[str, str] | None = None) -> rosmsgs.BuildHost:
    """Answers in turn from *missing* (the last one repeats), as apt would change them;
    installed *versions* (by default those of :func:`context`'s wheelhouse)."""
    answers = list(missing)
    installed = {"ros_rclpy": "7.1"} if versions is None else versions
    return rosmsgs.BuildHost(
        ros_extra=lambda: ros_extra,
        missing_tools=lambda: answers.pop(0) if len(answers) > 1 else answers[0],
        is_root=lambda: root,
        installed_version=installed.get,
    )


def context(tmp_path: Path) -> Path:
    ctx = tmp_path / "ctx"
    for name, wheel in (("base", "numpy-2.0-cp311.whl"), ("ros", "ros_rclpy-7.1-cp311.whl")):
        (ctx / "wheels" / name).mkdir(parents=True)
        (ctx / "wheels" / name / wheel).write_text("")
    return ctx


def test_the_checkouts_builder_comes_first_then_the_packaged_one(tmp_path: Path) -> None:
    package = tmp_path / "site-packages" / "fleetctl"
    (package / "_ros_msgs").mkdir(parents=True)
    (package / "_ros_msgs" / "build.py").write_text("")
    assert rosmsgs.builder_script(REPO, package) == REPO / "scripts/ros_msgs/build.py"
    assert rosmsgs.builder_script(None, package) == package / "_ros_msgs/build.py"
    assert rosmsgs.builder_script(tmp_path / "old-checkout", package) == (
        package / "_ros_msgs/build.py")
    assert rosmsgs.builder_script(None, tmp_path / "bare" / "fleetctl") is None
    # An editable install asked to build as if installed: its checkout's builder.
    assert rosmsgs.builder_script(None) == REPO / "scripts/ros_msgs/build.py"


def test_a_python_with_the_ros_extra_builds_with_itself(tmp_path: Path) -> None:
    run, ctx = FakeRunner(), context(tmp_path)
    dest = ctx / "wheels" / "rosmsgs"
    assert rosmsgs.build_ros_msg_wheels(REPO, dest, ROS_REQS, run, lambda s: None,
                                        host(ros_extra=True))
    assert run.calls == [[sys.executable, str(REPO / "scripts/ros_msgs/build.py"),
                          "--no-install", "--wheel-dir", str(dest),
                          "--build-dir", str(ctx / "rosmsgs-build")]]


@pytest.mark.parametrize("versions", [{"ros_rclpy": "7.0"}, {}])
def test_a_python_whose_ros_is_not_the_images_builds_in_the_venv(
        tmp_path: Path, versions: dict[str, str]) -> None:
    """Message wheels built against another ROS version than the image's may not load
    there (generated C against other headers): the build venv, made from the image's
    wheelhouses, always matches."""
    run, ctx, said = FakeRunner(), context(tmp_path), []
    assert rosmsgs.build_ros_msg_wheels(REPO, ctx / "wheels" / "rosmsgs", ROS_REQS, run,
                                        said.append, host(ros_extra=True, versions=versions))
    venv = ctx / "rosmsgs-venv"
    assert [c[1:3] for c in run.calls[:2]] == [["-m", "venv"], ["-m", "pip"]]
    assert run.calls[2][0] == str(venv / "bin/python")
    here = versions.get("ros_rclpy", "missing")
    assert (f"ros message wheels: this Python's ROS packages are not the image's "
            f"(ros_rclpy {here} (image: 7.1)): building in a venv of the image's wheels"
            ) in said


def test_without_the_ros_extra_a_venv_from_the_wheelhouses_builds(tmp_path: Path) -> None:
    run, ctx, said = FakeRunner(), context(tmp_path), []
    dest = ctx / "wheels" / "rosmsgs"
    assert rosmsgs.build_ros_msg_wheels(None, dest, ROS_REQS, run, said.append, host())
    venv = ctx / "rosmsgs-venv"
    make, install, build = run.calls
    assert make == [sys.executable, "-m", "venv", "--without-pip", str(venv)]
    assert install == [sys.executable, "-m", "pip", "--python", str(venv / "bin/python"),
                       "install", "-q", "--no-index",
                       "--find-links", str(ctx / "wheels/base"),
                       "--find-links", str(ctx / "wheels/ros"),
                       "ros-jazzy-rclpy[fastrtps]>=7,<8", "ros-jazzy-std-msgs>=5,<6"]
    assert build[0] == str(venv / "bin/python") and build[2:4] == ["--no-install",
                                                                    "--wheel-dir"]
    assert dest.is_dir()
    # Same wheelhouses: the venv is reused, only the builder runs.
    run.calls.clear()
    rosmsgs.build_ros_msg_wheels(None, dest, ROS_REQS, run, said.append, host())
    assert [c[0] for c in run.calls] == [str(venv / "bin/python")]
    assert "ros message wheels: build venv up to date" in said
    # A new wheel in wheels/ros: made again.
    (ctx / "wheels" / "ros" / "ros_rclpy-7.2-cp311.whl").write_text("")
    run.calls.clear()
    rosmsgs.build_ros_msg_wheels(None, dest, ROS_REQS, run, said.append, host())
    assert [c[1:3] for c in run.calls[:2]] == [["-m", "venv"], ["-m", "pip"]]


def test_a_failed_venv_install_is_not_reused(tmp_path: Path) -> None:
    run, ctx = FakeRunner(fail="--no-index"), context(tmp_path)
    with pytest.raises(Exception, match=r"pip install of the ROS wheels .* failed .*E: boom"):
        rosmsgs.build_ros_msg_wheels(None, ctx / "wheels" / "rosmsgs", ROS_REQS, run,
                                     lambda s: None, host())
    assert not (ctx / "rosmsgs-venv" / ".inputs").exists()


def test_missing_compilers_without_root_name_the_packages(tmp_path: Path) -> None:
    run = FakeRunner()
    with pytest.raises(EnvironmentMissing, match=r"needs g\+\+, /usr/include/python3.11/"
                       r"Python.h; run: sudo apt-get install g\+\+ python3-dev"):
        rosmsgs.build_ros_msg_wheels(None, context(tmp_path) / "wheels" / "rosmsgs",
                                     ROS_REQS, run, lambda s: None,
                                     host(missing=[["g++", "/usr/include/python3.11/Python.h"]]))
    assert run.calls == []


def test_missing_compilers_as_root_are_installed_with_apt(tmp_path: Path) -> None:
    run, said = FakeRunner(), []
    assert rosmsgs.build_ros_msg_wheels(None, context(tmp_path) / "wheels" / "rosmsgs",
                                        ROS_REQS, run, said.append,
                                        host(missing=[["gcc", "g++"], []], root=True))
    assert run.calls[0] == ["apt-get", "install", "-y", "-qq", "g++", "python3-dev"]
    assert "apt-get install g++ python3-dev (missing gcc, g++)" in said[0]


@pytest.mark.parametrize(("fail", "message"), [
    ("-qq", r"apt-get install g\+\+ python3-dev failed: E: boom"),
    ("", r"left Python.h missing \(is .* Debian's Python\? install its headers\)"),
])
def test_apt_that_does_not_help_is_a_clear_error(tmp_path: Path, fail: str,
                                                 message: str) -> None:
    run = FakeRunner(fail=fail)
    with pytest.raises(EnvironmentMissing, match=message):
        rosmsgs.build_ros_msg_wheels(None, context(tmp_path) / "wheels" / "rosmsgs",
                                     ROS_REQS, run, lambda s: None,
                                     host(missing=[["Python.h"]], root=True))
    assert len(run.calls) == 1


def test_an_installation_without_the_builder_builds_the_image_without_tf(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rosmsgs, "_PACKAGE_DIR", tmp_path / "bare" / "fleetctl")
    run, said = FakeRunner(), []
    dest = tmp_path / "rosmsgs"
    assert not rosmsgs.build_ros_msg_wheels(None, dest, ROS_REQS, run, said.append, host())
    assert run.calls == [] and dest.is_dir()  # the Dockerfile's COPY needs the directory
    assert "lacks fleetctl/_ros_msgs" in said[0] and "robots send no TF" in said[0]
