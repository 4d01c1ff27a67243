"""The robot bundle (``fleetctl export``): files, modes, escaping, the README's blocks.

No Docker here; ``test_bundle_docker.py`` runs the README's blocks in a container.
"""

from __future__ import annotations

import io
import re
import shlex
import stat
import subprocess
import tarfile
import zipfile
from pathlib import Path

import pytest
import yaml

from fleetctl.client.ros.ddsbuffers import CLIENT_FASTDDS_TRANSPORTS
from fleetctl.deploy import bundle
from fleetctl.deploy.export import export_robot
from fleetctl.deploy.fleet import load_fleet

# The blocks the README must carry; test_bundle_docker.py runs the ROBOT_BLOCKS.
README_BLOCKS = (
    "packages", "tunnel-config", "tunnel-service", "tunnel-quick", "tunnel-check", "venv",
    "venv-check", "ros-wheels", "install-files", "socket-buffer", "client-service",
    "client-check",
    "client-foreground", "image-load", "container-run", "update-tunnel", "update-tunnel-quick",
    "update-venv", "update-files", "update-service", "update-container",
)
_BLOCK = re.compile(r"<!-- block: ([a-z0-9-]+) -->\n```sh\n(.*?)```\n", re.S)


def readme_blocks(text: str) -> dict[str, str]:
    """The README's marked shell blocks (``<!-- block: NAME -->`` before a ```sh fence)."""
    blocks: dict[str, str] = {}
    for name, body in _BLOCK.findall(text):
        assert name not in blocks, f"block {name!r} twice"
        blocks[name] = body
    return blocks


def fake_wheel(directory: Path) -> Path:
    """A stand-in for the fleetctl wheel (the real one takes seconds to build)."""
    path = directory / "fleetctl-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("fleetctl/__init__.py", "")
    return path


def set_robot_fields(fleet_dir: Path, name: str, **fields: object) -> None:
    """Edit robot *name* in fleet.yaml by hand (then export re-reads it)."""
    path = fleet_dir / "fleet.yaml"
    doc = yaml.safe_load(path.read_text())
    robot = next(r for r in doc["robots"] if r["name"] == name)
    robot.update(fields)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.fixture
def wheel(tmp_path: Path) -> Path:
    return fake_wheel(tmp_path)


@pytest.fixture
def exported(fleet_dir: Path, tmp_path: Path, wheel: Path) -> Path:
    return export_robot(fleet_dir, "husky1", tmp_path / "husky1-bundle", wheel=wheel).path


EXPECTED_MODES = {
    "wg0.conf": 0o600,
    "client.yaml": 0o644,
    "fleetctl.env": 0o644,
    "fleetctl-client.service": 0o644,
    "fleetctl-client": 0o755,
    "compose.yaml": 0o644,
    "README.md": 0o644,
    "fleetctl-0.1.0-py3-none-any.whl": 0o644,
}


def test_bundle_directory_files_and_modes(exported: Path, wheel: Path) -> None:
    assert stat.S_IMODE(exported.stat().st_mode) == 0o700
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in exported.iterdir()}
    assert modes == EXPECTED_MODES
    assert (exported / wheel.name).read_bytes() == wheel.read_bytes()


def test_bundle_tarball_modes_and_reproducible(fleet_dir: Path, tmp_path: Path,
                                               wheel: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = export_robot(fleet_dir, "husky1", tmp_path / "a" / "husky1.tar.gz", wheel=wheel)
    second = export_robot(fleet_dir, "husky1", tmp_path / "b" / "husky1.tar.gz", wheel=wheel)
    assert first.path.read_bytes() == second.path.read_bytes()
    assert stat.S_IMODE(first.path.stat().st_mode) == 0o600
    with tarfile.open(fileobj=io.BytesIO(first.path.read_bytes())) as tar:
        modes = {m.name: m.mode for m in tar.getmembers()}
    assert modes.pop("husky1") == 0o700
    assert modes == {f"husky1/{name}": mode for name, mode in EXPECTED_MODES.items()}


def test_env_file_from_fleet_yaml(fleet_dir: Path, tmp_path: Path, wheel: Path) -> None:
    set_robot_fields(fleet_dir, "jackal2", ros_domain_id=42,
                     rmw_implementation="rmw_cyclonedds_cpp")
    out = export_robot(fleet_dir, "jackal2", tmp_path / "b", wheel=wheel).path
    env = _assignments((out / "fleetctl.env").read_text())
    assert env == {"ROS_DOMAIN_ID": "42", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    # The image has only Fast DDS: the container routes say so and run it.
    compose = yaml.safe_load((out / "compose.yaml").read_text())
    service = compose["services"]["fleetctl-client"]
    assert service["environment"] == {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    readme = (out / "README.md").read_text()
    assert "the robot uses `rmw_cyclonedds_cpp` but the image has only Fast DDS" in readme
    assert "-e RMW_IMPLEMENTATION=rmw_fastrtps_cpp" in readme_blocks(readme)["container-run"]


def test_env_file_default_is_fast_dds_over_udp(exported: Path) -> None:
    env = _assignments((exported / "fleetctl.env").read_text())
    assert env == {"ROS_DOMAIN_ID": "0", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
                   "FASTDDS_BUILTIN_TRANSPORTS": CLIENT_FASTDDS_TRANSPORTS}


def _assignments(text: str) -> dict[str, str]:
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    return dict(ln.split("=", 1) for ln in lines)


def test_env_file_reads_the_same_in_sh(exported: Path) -> None:
    out = subprocess.run(
        ["sh", "-c", 'set -a; . "$1"; set +a; echo "$ROS_DOMAIN_ID/$RMW_IMPLEMENTATION"; '
         'echo "$FASTDDS_BUILTIN_TRANSPORTS"', "sh", str(exported / "fleetctl.env")],
        capture_output=True, text=True, check=True).stdout
    # The '?' of Fast DDS's option is no glob in an assignment.
    assert out == "0/rmw_fastrtps_cpp\nUDPv4?sockets_size=4194304\n"


def test_systemd_unit(exported: Path) -> None:
    text = (exported / "fleetctl-client.service").read_text()
    settings = _unit_settings(text)
    assert "wg-quick@fleet0.service" in settings["Unit"]["After"]
    assert "wg-quick@fleet0.service" in settings["Unit"]["Wants"]
    assert settings["Unit"]["StartLimitIntervalSec"] == "0"
    service = settings["Service"]
    assert service["ExecStart"] == "/usr/local/bin/fleetctl-client"
    assert service["EnvironmentFile"] == "/etc/fleetctl/fleetctl.env"
    assert service["Restart"] == "always"
    assert service["DynamicUser"] == "yes"  # an unprivileged user
    assert {"RestartSec", "RestartSteps", "RestartMaxDelaySec"} <= service.keys()
    assert settings["Install"]["WantedBy"] == "multi-user.target"


def _unit_settings(text: str) -> dict[str, dict[str, str]]:
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] = {}
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            current = sections.setdefault(line.strip("[]"), {})
            continue
        key, sep, value = line.partition("=")
        assert sep, f"not a setting: {line!r}"
        current[key] = value
    return sections


def test_wrapper_script(exported: Path, tmp_path: Path) -> None:
    script = exported / "fleetctl-client"
    text = script.read_text()
    assert text.startswith("#!/bin/bash\n")
    subprocess.run(["bash", "-n", str(script)], check=True)
    # Without ROS from apt it says so and runs the venv's fleetctl with the config.
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    fake = venv / "bin" / "fleetctl"
    fake.write_text('#!/bin/sh\necho "fleetctl $*"\n')
    fake.chmod(0o755)
    env = {"PATH": "/usr/bin:/bin", "FLEETCTL_VENV": str(venv),
           "FLEETCTL_ROS_SETUP": str(tmp_path / "no-ros" / "setup.bash")}
    res = subprocess.run([str(script), "--log-level", "DEBUG"], env=env, capture_output=True,
                         text=True, check=True)
    assert res.stdout == "fleetctl client --config /etc/fleetctl/client.yaml --log-level DEBUG\n"
    assert "not found: using the ROS 2 installed in" in res.stderr
    # With it, it is sourced first (what puts the apt rclpy on PYTHONPATH).
    setup = tmp_path / "ros" / "setup.bash"
    setup.parent.mkdir()
    setup.write_text('echo "sourced ROS_DOMAIN_ID=$ROS_DOMAIN_ID"\n')
    res = subprocess.run([str(script)], env={**env, "FLEETCTL_ROS_SETUP": str(setup),
                                             "ROS_DOMAIN_ID": "3"},
                         capture_output=True, text=True, check=True)
    assert res.stdout.splitlines()[0] == "sourced ROS_DOMAIN_ID=3"


def test_compose_file(exported: Path) -> None:
    doc = yaml.safe_load((exported / "compose.yaml").read_text())
    assert doc["version"] == "2.4"  # docker-compose v1 reads it, and the v2 plugin
    service = doc["services"]["fleetctl-client"]
    assert service["image"] == "fleetctl/client:0.1.0"
    assert service["network_mode"] == "host"
    assert service["env_file"] == ["fleetctl.env"]
    assert service["volumes"] == ["./client.yaml:/etc/fleetctl/robot/client.yaml:ro"]
    assert "environment" not in service


def test_readme_blocks(exported: Path) -> None:
    readme = (exported / "README.md").read_text()
    blocks = readme_blocks(readme)
    assert tuple(blocks) == README_BLOCKS
    for body in blocks.values():
        subprocess.run(["bash", "-n", "-c", body], check=True)  # each parses as written
    assert "sudo systemctl enable --now wg-quick@fleet0" in blocks["tunnel-service"]
    assert "install -D -m 0600 wg0.conf /etc/wireguard/fleet0.conf" in blocks["tunnel-config"]
    assert blocks["tunnel-quick"].strip() == "sudo wg-quick up fleet0"
    assert "ping -c 3 -W 2 10.8.0.1" in blocks["tunnel-check"]
    assert "python3 -m venv --system-site-packages /opt/fleetctl" in blocks["venv"]
    assert "pip install ./fleetctl-0.1.0-py3-none-any.whl" in blocks["venv"]
    assert "[ros]" not in blocks["venv"]  # rclpy comes from apt
    assert "source /opt/ros/jazzy/setup.bash" in blocks["venv-check"]
    assert "'ros-jazzy-rclpy[fastrtps]>=7,<8'" in blocks["ros-wheels"]
    assert "journalctl -u fleetctl-client" in blocks["client-check"]
    assert "net.core.rmem_max=4194304" in blocks["socket-buffer"]
    assert "docker load -i fleetctl-client-0.1.0.tar.gz" in blocks["image-load"]
    # The README must not say what the issue complained about.
    assert "pip install 'fleetctl[ros]'" not in readme
    args = shlex.split(blocks["container-run"].replace('"$PWD"', "/robot"))
    assert args[:2] == ["docker", "run"] and args[-1] == "fleetctl/client:0.1.0"
    assert "--network" in args and args[args.index("--network") + 1] == "host"
    assert args[args.index("--env-file") + 1] == "fleetctl.env"
    assert args[args.index("-v") + 1] == "/robot/client.yaml:/etc/fleetctl/robot/client.yaml:ro"


def test_readme_updates_a_robot_by_restarting_what_runs(exported: Path) -> None:
    """docs/robot.md and operator.md say to install a new export on the robot (another
    ros_domain_id, new keys, relay replicas), but the README had only the first install:
    its `systemctl enable --now` leaves a running tunnel and client as they are,
    `wg-quick up` fails on an interface that is up, pip keeps an installed fleetctl of the
    same version and `docker run --name fleetctl-client` fails on the existing container."""
    blocks = readme_blocks((exported / "README.md").read_text())
    assert blocks["update-tunnel"].splitlines() == [
        "sudo install -D -m 0600 wg0.conf /etc/wireguard/fleet0.conf",
        "sudo systemctl restart wg-quick@fleet0"]
    assert blocks["update-tunnel-quick"].splitlines() == [
        "sudo wg-quick down fleet0", "sudo wg-quick up fleet0"]
    wheel = "./fleetctl-0.1.0-py3-none-any.whl"
    assert blocks["update-venv"].splitlines() == [
        f"sudo /opt/fleetctl/bin/pip install --force-reinstall --no-deps {wheel}",
        f"sudo /opt/fleetctl/bin/pip install {wheel}"]
    assert blocks["update-files"] == blocks["install-files"].split("\n", 1)[1]
    assert blocks["update-service"].splitlines()[-1] == (
        "sudo systemctl restart fleetctl-client.service")
    remove, run = blocks["update-container"].splitlines()
    assert remove == "docker rm -f fleetctl-client"
    assert run == blocks["container-run"].strip()


def test_wg0_conf_starts_the_tunnel_the_way_the_readme_does(exported: Path) -> None:
    """Its own comment said `wg-quick up ./wg0.conf`: interface wg0, which the README says
    the robot may use already, and not the fleet0 the client's unit waits for."""
    from fleetctl.deploy.bundle import WIREGUARD_INTERFACE

    comments = "\n".join(line for line in (exported / "wg0.conf").read_text().splitlines()
                         if line.startswith("#"))
    assert "wg-quick up ./wg0.conf" not in comments
    assert f"/etc/wireguard/{WIREGUARD_INTERFACE}.conf" in comments
    assert f"systemctl enable --now wg-quick@{WIREGUARD_INTERFACE}" in comments
    readme = (exported / "README.md").read_text()
    assert f"systemctl enable --now wg-quick@{WIREGUARD_INTERFACE}" in readme


def test_free_text_is_escaped_per_format() -> None:
    from fleetctl.deploy.render import render_template

    # Fleet names are validated to [A-Za-z0-9._-]; the filters still hold on their own
    # (tests/security/test_deploy_templates.py renders every template with worse).
    unit = _unit_settings(render_template(
        "robot/fleetctl-client.service.j2", description="50% `lab` <b>x</b> [a](b)",
        interface="fleet0", env_file="/etc/fleetctl/fleetctl.env",
        wrapper="/usr/local/bin/fleetctl-client", state_dir="/var/lib/fleetctl"))
    assert unit["Unit"]["Description"] == "50%% `lab` <b>x</b> [a](b)"


def test_escaping_functions() -> None:
    from fleetctl.deploy.render import md_text, unit_value

    assert unit_value("a%b") == "a%%b"
    for bad in ("a\nExecStart=/bin/evil", "x\\", " x"):
        with pytest.raises(ValueError):
            unit_value(bad)
    with pytest.raises(ValueError, match="plain word"):
        unit_value("/a b", word=True)
    assert md_text("*x* # y") == r"\*x\* \# y"
    with pytest.raises(ValueError):
        md_text("x\n# y")
    with pytest.raises(ValueError, match="code span"):
        md_text("a`b", code=True)
    assert bundle.sh_quote("it's") == "'it'\"'\"'s'"
    assert bundle.env_value("ROS_DOMAIN_ID", 7) == "ROS_DOMAIN_ID=7"
    for bad in ("a b", "'x'", '"x"', "x\ny", "$HOME", "a;b", "`x`", "a\\b"):
        with pytest.raises(ValueError, match="would need quoting"):
            bundle.env_value("X", bad)
    with pytest.raises(ValueError, match="not an environment variable name"):
        bundle.env_value("x-y", "1")


def test_readme_needs_an_endpoint(fleet_dir: Path) -> None:
    fleet = load_fleet(fleet_dir)
    robot = fleet.robots[0]
    with pytest.raises(ValueError, match="endpoint"):
        bundle.robot_readme(type(fleet)(**{**fleet.__dict__, "endpoint": None}), robot,
                            wheel_name="w.whl")


def test_readme_names_every_relay_replica_the_client_yaml_lists(
        fleet_dir: Path, tmp_path: Path, wheel: Path) -> None:
    """With `relay_replicas: 2` the bundle's client.yaml lists ws://10.8.0.1:8080/ and
    :8081/, but its README said "server ws://10.8.0.1:8080/" and told the operator to
    look for `connected to ws://10.8.0.1:8080/`, which a client on the second replica
    never logs."""
    one = (export_robot(fleet_dir, "husky1", tmp_path / "one", wheel=wheel).path
           / "README.md").read_text()
    assert "robot client: server ws://10.8.0.1:8080/, bound to" in one
    assert "`connected to ws://10.8.0.1:8080/`" in one
    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace("robots:", "relay_replicas: 2\nrobots:", 1))
    two_dir = export_robot(fleet_dir, "husky1", tmp_path / "two", wheel=wheel).path
    urls = yaml.safe_load((two_dir / "client.yaml").read_text())["server_url"]
    assert urls == ["ws://10.8.0.1:8080/", "ws://10.8.0.1:8081/"]
    two = (two_dir / "README.md").read_text()
    assert ("robot client: servers ws://10.8.0.1:8080/, ws://10.8.0.1:8081/ (relay "
            "replicas: it fails over between them), bound to") in two
    assert "`connected to ws://10.8.0.1:8080/` (or another replica's URL)" in two
    assert "8080" not in re.sub(r"ws://10\.8\.0\.1:808[01]/", "", two)
