"""fleetctl as users install it: a wheel in a new venv, run outside the checkout.

The venv gets its dependencies from the wheelhouse `fleetctl build` made (no index), so the
test needs no network; without that wheelhouse it is skipped with the reason.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from fleetctl.deploy.selfwheel import fleetctl_wheel

REPO = Path(__file__).resolve().parents[2]
WHEELHOUSE = REPO / "build" / "docker" / "wheels" / "base"
ROS_WHEELHOUSE = WHEELHOUSE.parent / "ros"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not any(WHEELHOUSE.glob("*.whl")),
                       reason=f"no wheelhouse at {WHEELHOUSE} (made by `fleetctl build`)"),
]


def _run(argv: list[str], cwd: Path, env: dict[str, str] | None = None,
         ok: bool = True) -> subprocess.CompletedProcess[str]:
    res = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, check=False,
                         env={**os.environ, **(env or {})}, timeout=300)
    if ok:
        assert res.returncode == 0, f"{argv}: {res.stdout}\n{res.stderr}"
    return res


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("installed")
    wheel = fleetctl_wheel(root / "dist", REPO)
    names = zipfile.ZipFile(wheel).namelist()
    assert "fleetctl/_templates/wireguard/robot.conf.j2" in names
    assert "fleetctl/_images/server.Dockerfile" in names
    assert "fleetctl/_images/entrypoint.sh" in names
    # The message-wheel builder and every input of it (foxglove_msgs' is the wire's).
    for name in ("build.py", "compile.py", "generate.py", "packages.py", "stage.py",
                 "wheel.py", "msg/tf2_msgs/msg/TFMessage.msg", "msg/tf2_msgs/msg/TF2Error.msg"):
        assert f"fleetctl/_ros_msgs/{name}" in names
    assert "fleetctl/wire/msg/foxglove_msgs/msg/CompressedVideo.msg" in names
    env_dir = root / "venv"
    _run([sys.executable, "-m", "venv", str(env_dir)], root)
    _run([str(env_dir / "bin" / "pip"), "install", "-q", "--no-index", "--find-links",
          str(WHEELHOUSE), str(wheel)], root)
    return env_dir


def test_the_installed_wheel_runs_the_whole_fleet_life_cycle(venv: Path,
                                                             tmp_path: Path) -> None:
    work = tmp_path / "ops"  # outside the checkout: nothing can come from the source tree
    work.mkdir()
    fleetctl = str(venv / "bin" / "fleetctl")
    env = {"FLEET_DIR": str(work / "yard"), "PYTHONPATH": ""}
    _run([fleetctl, "init", str(work / "yard")], work)
    _run([fleetctl, "add-robot", "husky1"], work, env)
    res = _run([fleetctl, "export", "husky1"], work, env, ok=False)
    assert res.returncode != 0 and "endpoint" in res.stderr and "Traceback" not in res.stderr
    _run([fleetctl, "set-endpoint", "vpn.example.org:51820"], work, env)
    _run([fleetctl, "render"], work, env)
    _run([fleetctl, "export", "husky1", "--out", str(work / "husky1-bundle")], work, env)
    assert "Endpoint = vpn.example.org:51820" in (
        work / "husky1-bundle" / "wg0.conf").read_text()
    assert (work / "yard" / "server" / "server.yaml").is_file()
    # The bare wheel has no matplotlib: `e2e` says which extra before starting anything.
    res = _run([fleetctl, "e2e", "-s", "link", "--out", str(work / "report")], work, env,
               ok=False)
    assert res.returncode == 5 and "fleetctl[e2e]" in res.stderr and "Traceback" not in res.stderr
    assert not (work / "report").exists()


def test_the_installed_wheel_rebuilds_itself_for_images_and_bundles(venv: Path,
                                                                   tmp_path: Path) -> None:
    # `fleetctl build` and `export` ship fleetctl as a wheel: from an installation with no
    # checkout it is repacked from the installed files, and that wheel installs again.
    script = ("import sys; from pathlib import Path; "
              "from fleetctl.deploy.selfwheel import fleetctl_wheel, source_checkout; "
              "assert source_checkout() is None; print(fleetctl_wheel(Path(sys.argv[1])))")
    res = _run([str(venv / "bin" / "python"), "-c", script, str(tmp_path / "w")], tmp_path)
    repacked = Path(res.stdout.strip())
    names = zipfile.ZipFile(repacked).namelist()
    assert "fleetctl/_images/client.Dockerfile" in names
    assert not any(n.endswith(".pyc") or n.endswith("/INSTALLER") for n in names)
    again = tmp_path / "again"
    _run([sys.executable, "-m", "venv", str(again)], tmp_path)
    _run([str(again / "bin" / "pip"), "install", "-q", "--no-index", "--find-links",
          str(WHEELHOUSE), str(repacked)], tmp_path)
    _run([str(again / "bin" / "fleetctl"), "init", str(tmp_path / "f2")], tmp_path)
    # Same installation, same bytes: the image's code layer stays cached.
    second = _run([str(venv / "bin" / "python"), "-c", script, str(tmp_path / "w2")], tmp_path)
    assert Path(second.stdout.strip()).read_bytes() == repacked.read_bytes()
    build_help = _run([str(venv / "bin" / "fleetctl"), "build", "-h"], tmp_path)
    assert "--source" in build_help.stdout


@pytest.mark.skipif(not any(ROS_WHEELHOUSE.glob("*.whl")),
                    reason=f"no ROS wheelhouse at {ROS_WHEELHOUSE} (made by `fleetctl build`)")
def test_the_installed_wheel_builds_the_ros_message_wheels_for_the_client_image(
        venv: Path, tmp_path: Path) -> None:
    """`fleetctl build` from a plain `pip install fleetctl` skipped tf2_msgs ('no source
    checkout'), so `up --sim` robots and deployed ones sent no TF."""
    ctx = tmp_path / "ctx"  # a build context as prepare_context leaves it
    (ctx / "wheels").mkdir(parents=True)
    for name in ("base", "ros"):
        (ctx / "wheels" / name).symlink_to(WHEELHOUSE.parent / name)
    dest = ctx / "wheels" / "rosmsgs"
    script = ("import sys; from pathlib import Path; import importlib.util; "
              "from fleetctl.deploy.images import BuildConfig, ros_msg_wheels; "
              "assert importlib.util.find_spec('rosidl_adapter') is None; "
              "assert ros_msg_wheels(BuildConfig(source_dir=None), Path(sys.argv[1]))")
    res = _run([str(venv / "bin" / "python"), "-c", script, str(dest)], tmp_path,
               {"PYTHONPATH": ""})
    assert f"{venv}/lib/" in res.stdout and "/fleetctl/_ros_msgs/build.py" in res.stdout
    wheels = sorted(dest.glob("*.whl"))
    assert [w.name.split("-")[0] for w in wheels] == ["ros_foxglove_msgs", "ros_tf2_msgs"]
    # They load in a venv with the ROS wheels (the build venv is one): import, and
    # serialize through their C type supports as rclpy does when publishing.
    python = ctx / "rosmsgs-venv" / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-index",
          "--no-deps", *map(str, wheels)], tmp_path)
    check = ("import tf2_msgs.msg; import foxglove_msgs.msg; "
             "from rclpy.serialization import serialize_message as s; "
             "assert s(tf2_msgs.msg.TFMessage()) and s(foxglove_msgs.msg.CompressedVideo())")
    _run([str(python), "-c", check], tmp_path, {"PYTHONPATH": ""})
