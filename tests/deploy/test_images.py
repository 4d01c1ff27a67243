"""Unit tests of image building: commands, mirror detection, layer order (no Docker)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import pytest

from fleetctl.deploy import images
from fleetctl.deploy.dockercli import Completed, require_docker
from fleetctl.deploy.rosmsgs import BuildHost
from fleetctl.errors import ConfigError, EnvironmentMissing, ExitCode, FleetError

REPO = Path(__file__).resolve().parents[2]


def test_detect_mirror_reads_deb822_and_one_line_sources(tmp_path: Path) -> None:
    deb822 = tmp_path / "debian.sources"
    deb822.write_text(
        "Types: deb\nURIs: http://security.example/debian-security\nSuites: bookworm-security\n\n"
        "Types: deb\nURIs: http://mirror.example/debian/\nSuites: bookworm bookworm-updates\n"
    )
    assert images.detect_mirror([deb822]) == "http://mirror.example/debian"
    one = tmp_path / "sources.list"
    one.write_text("# comment\ndeb http://ftp.example/debian bookworm main\n")
    assert images.detect_mirror([tmp_path / "absent", one]) == "http://ftp.example/debian"
    with pytest.raises(EnvironmentMissing, match="--mirror"):
        images.detect_mirror([tmp_path / "absent"])


def test_debootstrap_command_is_minbase_with_python_and_tc() -> None:
    argv = images.debootstrap_argv(Path("/r"), "http://m/debian", "bookworm",
                                   images.BASE_PACKAGES)
    assert argv[:2] == ["debootstrap", "--variant=minbase"]
    assert argv[-3:] == ["bookworm", "/r", "http://m/debian"]
    included = argv[2].removeprefix("--include=").split(",")
    assert {"python3", "python3-venv", "iproute2", "wireguard-go"} <= set(included)


def test_project_requirements_split_base_and_ros() -> None:
    base = images.project_requirements(REPO / "pyproject.toml")
    ros = images.project_requirements(REPO / "pyproject.toml", ["ros"])
    assert any(r.startswith("websockets") for r in base)
    assert ros[: len(base)] == base
    assert any(r.startswith("ros-jazzy-rclpy") for r in ros[len(base):])


def test_project_requirements_names_the_file_on_error(tmp_path: Path) -> None:
    bad = tmp_path / "pyproject.toml"
    bad.write_text("[tool.x]\n")
    with pytest.raises(FleetError, match=str(bad)):
        images.project_requirements(bad)


def test_build_command_has_base_arg_version_label_and_tags(tmp_path: Path) -> None:
    cfg = images.BuildConfig(source_dir=tmp_path, base_image="registry.example/debian:12")
    argv = images.build_argv(cfg, "client")
    assert "BASE_IMAGE=registry.example/debian:12" in argv
    assert f"org.opencontainers.image.version={cfg.version}" in argv
    assert images.image_tag("client", cfg.version) in argv
    assert argv[-1] == str(tmp_path / "build" / "docker")


@pytest.mark.parametrize("name", images.IMAGE_NAMES)
def test_dockerfiles_take_a_base_arg_label_and_healthcheck(name: str) -> None:
    text = (REPO / "images" / f"{name}.Dockerfile").read_text()
    assert text.count("ARG BASE_IMAGE=fleetctl/base:bookworm") == 1
    assert "HEALTHCHECK" in text
    assert "org.opencontainers.image.version" in text
    if name != "router":  # tc needs root; the others run unprivileged
        assert "USER fleetctl" in text


@pytest.mark.parametrize("name", ["server", "client", "webviz"])
def test_code_layer_comes_after_dependency_layers(name: str) -> None:
    text = (REPO / "images" / f"{name}.Dockerfile").read_text()
    order = [m.group(1) for m in re.finditer(r"^COPY (?:--from=\S+ )?(\S+)", text, re.M)]
    assert order.index("wheels/app") > order.index("/opt/fleetctl")
    if name == "client":
        assert order.index("wheels/ros") < order.index("wheels/app")


class Recorder:
    """A runner that answers ``docker image inspect`` per *present* and records the rest."""

    def __init__(self, present: bool) -> None:
        self.present = present
        self.calls: list[list[str]] = []

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        self.calls.append(list(argv))
        ok = self.present or argv[:3] != ["docker", "image", "inspect"]
        return Completed(tuple(argv), 0 if ok else 1, "", "")


def test_existing_base_image_is_not_rebuilt(tmp_path: Path) -> None:
    rec = Recorder(present=True)
    built = images.ensure_base_image(images.BuildConfig(source_dir=tmp_path), rec, lambda s: None)
    assert built is False
    assert all("debootstrap" not in c for c in rec.calls)


def test_missing_foreign_base_image_is_a_clear_error(tmp_path: Path) -> None:
    cfg = images.BuildConfig(source_dir=tmp_path, base_image="registry.example/debian:12")
    with pytest.raises(FleetError, match=r"registry\.example/debian:12 is not present"):
        images.ensure_base_image(cfg, Recorder(present=False), lambda s: None)


def test_unknown_image_name_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(FleetError, match="unknown image"):
        images.build_all(images.BuildConfig(source_dir=tmp_path, images=("db",)),
                         Recorder(True), lambda s: None)


@pytest.mark.parametrize(("options", "message"), [
    ({"images": ("db",)}, r"--image: unknown image\(s\) 'db'; choose from server, client, "
                          r"webviz, router"),
    ({"mirror_url": "not a url"}, r"--mirror 'not a url': expected an http://, https:// or "
                                  r"file:/ URL of a Debian mirror"),
    ({"mirror_url": "deb.debian.org/debian"}, r"--mirror 'deb\.debian\.org/debian'"),
    ({"mirror_url": "http:///debian"}, r"--mirror 'http:///debian'"),
    ({"mirror_url": "http://h/debian\nx"}, r"--mirror"),
])
def test_bad_build_options_are_usage_errors_before_anything_runs(
        tmp_path: Path, options: dict[str, object], message: str) -> None:
    """`fleetctl build --mirror 'not a url'` made the wheelhouses (minutes of pip) and
    would have built every image with the option ignored (the base image was there), and
    `--image db` was exit 1 where every other bad option is 2."""
    rec = Recorder(True)
    with pytest.raises(FleetError, match=message) as err:
        images.build_all(images.BuildConfig(source_dir=tmp_path, **options),  # type: ignore[arg-type]
                         rec, lambda s: None)
    assert err.value.exit_code == ExitCode.USAGE
    assert rec.calls == []
    for good in ("http://deb.debian.org/debian", "https://mirror.example:8443/debian/",
                 "file:///srv/mirror"):
        images.check_mirror(good)


def test_a_build_context_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    """`build --source` of a checkout on a read-only mount printed mkdir's traceback (here
    a file stands where the context directory goes)."""
    context = tmp_path / "ctx"
    context.write_text("not a directory\n")
    cfg = images.BuildConfig(source_dir=tmp_path, context_dir=context)
    with pytest.raises(FleetError) as info:
        images.build_all(cfg, Recorder(True), lambda s: None)
    assert str(info.value) == (f"{context}/wheels: cannot write the build context {context}: "
                               "Not a directory")
    assert info.value.exit_code is ExitCode.ENVIRONMENT


def test_docker_absent_is_an_environment_error() -> None:
    with pytest.raises(EnvironmentMissing, match="docker: command not found"):
        require_docker(which=lambda name: None)


def test_find_source_dir_is_this_checkout_never_a_foreign_project(tmp_path: Path) -> None:
    # Running from the checkout (editable install): build from it.
    assert images.find_source_dir() == REPO
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'other'\n")
    (tmp_path / "images").mkdir()
    assert images.find_source_dir(tmp_path) == REPO
    with pytest.raises(ConfigError, match=r"--source .*not a fleetctl checkout"):
        images.check_source_dir(tmp_path)


def test_without_a_checkout_the_packaged_images_and_metadata_are_used() -> None:
    cfg = images.BuildConfig(source_dir=None)
    assert (cfg.images_dir / "server.Dockerfile").is_file()
    assert cfg.context.parts[-2:] == ("fleetctl", "build")
    core = images.installed_requirements()
    with_ros = images.installed_requirements(["ros"])
    assert any(r.startswith("websockets") for r in core)
    assert with_ros[: len(core)] == core
    assert any(r.startswith("ros-jazzy-rclpy") for r in with_ros[len(core):])


def test_ros_message_wheels_come_from_the_checkouts_script(tmp_path: Path) -> None:
    rec = Recorder(present=True)
    dest = tmp_path / "ctx" / "wheels" / "rosmsgs"
    said: list[str] = []
    cfg = images.BuildConfig(source_dir=REPO)
    host = BuildHost(ros_extra=lambda: True, missing_tools=list, is_root=lambda: False)
    assert images.ros_msg_wheels(cfg, dest, rec, said.append, host)
    (argv,) = rec.calls
    assert argv[1] == str(REPO / "scripts" / "ros_msgs" / "build.py")
    assert argv[2:5] == ["--no-install", "--wheel-dir", str(dest)]


def test_without_the_ros_extra_the_build_venv_gets_the_installed_ros_extra(
        tmp_path: Path) -> None:
    """A plain `pip install fleetctl` (no ros extra, no checkout) skipped the message
    wheels: the client image had no tf2_msgs and its robots sent no TF."""
    rec = Recorder(present=True)
    dest = tmp_path / "ctx" / "wheels" / "rosmsgs"
    host = BuildHost(ros_extra=lambda: False, missing_tools=list, is_root=lambda: False)
    assert images.ros_msg_wheels(images.BuildConfig(source_dir=None), dest, rec,
                                 lambda s: None, host)
    venv, install, build = rec.calls
    assert venv[-1] == str(tmp_path / "ctx" / "rosmsgs-venv")
    assert any(r.startswith("ros-jazzy-rclpy") for r in install)
    assert not any(r.startswith(("av", "pillow", "websockets")) for r in install)
    assert build[0] == str(tmp_path / "ctx" / "rosmsgs-venv" / "bin" / "python")


def test_the_client_image_installs_the_ros_message_wheels_when_there_are_some() -> None:
    text = (REPO / "images" / "client.Dockerfile").read_text()
    assert "COPY wheels/rosmsgs /wheels/rosmsgs" in text
    assert "if ls /wheels/rosmsgs/*.whl" in text


def test_the_message_build_venv_and_cache_stay_out_of_the_docker_context(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The build venv (240 MB) sat in the context, sent to the daemon for every image
    (373.6 MB instead of 137 MB per `docker build`)."""
    ctx = tmp_path / "ctx"
    app = ctx / "wheels" / "app"
    app.mkdir(parents=True)
    (app / "fleetctl-0.1.0-py3-none-any.whl").write_text("")
    (app / ".inputs").write_text(images.source_digest(REPO))  # no wheel built here
    monkeypatch.setattr(images, "ros_msg_wheels", lambda *args: True)
    cfg = images.BuildConfig(source_dir=REPO, context_dir=ctx)
    images.prepare_context(cfg, Recorder(True), lambda s: None)
    ignored = (ctx / ".dockerignore").read_text().split()
    assert ignored == ["rosmsgs-venv", "rosmsgs-build"]
    for dockerfile in (REPO / "images").glob("*.Dockerfile"):
        assert not any(name in dockerfile.read_text() for name in ignored)
