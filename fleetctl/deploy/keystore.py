"""Key files beside ``fleet.yaml``: ``keys/`` (0700) holding 0600 files.

Layout::

    keys/server.key          server WireGuard private key
    keys/robots/NAME.key     robot WireGuard private key
    keys/robots/NAME.psk     preshared key of the robot <-> server pair
    keys/tls.key             private key of the generated HTTPS certificate (tls.py)

Public keys are always derived from private keys, never stored, so they cannot disagree.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

from fleetctl.deploy.files import SECRET_DIR_MODE, Plan
from fleetctl.deploy.keys import KeySource, decode_key, new_preshared_key, new_private_key
from fleetctl.deploy.secrets import Secret
from fleetctl.errors import ConfigError
from fleetctl.smallfile import MAX_SECRET_BYTES, read_small_text

KEYS_DIR = "keys"


@dataclass(frozen=True)
class RobotKeys:
    """A robot's private key and its preshared key with the server."""

    private_key: Secret
    preshared_key: Secret


def server_key_path(fleet_dir: Path) -> Path:
    """Return the path of the server's private key file."""
    return fleet_dir / KEYS_DIR / "server.key"


def robot_key_paths(fleet_dir: Path, name: str) -> tuple[Path, Path]:
    """Return the paths of robot *name*'s private key and preshared key files."""
    base = fleet_dir / KEYS_DIR / "robots"
    return base / f"{name}.key", base / f"{name}.psk"


def _read_key(path: Path) -> Secret:
    try:
        text = read_small_text(path, MAX_SECRET_BYTES, encoding="ascii").strip()
    except FileNotFoundError:
        raise ConfigError(f"{path}: key file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read key file: "
                          f"{exc.strerror or type(exc).__name__}") from None
    except UnicodeDecodeError:
        # Never the decoder's message: it would quote bytes of the key.
        raise ConfigError(f"{path}: cannot read key file: not ASCII text") from None
    decode_key(text, str(path))  # validates; the error never includes the key
    _require_private(path)
    return Secret(text)


def _require_private(path: Path) -> None:
    """Refuse a key that others may read, as ssh refuses such a private key: fleetctl
    makes every key 0600, so a looser one was copied or linked in from elsewhere (e.g. a
    link to a 0644 file) and may already be known to others."""
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read key file: "
                          f"{exc.strerror or type(exc).__name__}") from None
    if mode & 0o077:
        raise ConfigError(f"{path}: key file is readable or writable by others (mode "
                          f"{mode:04o}{', through a symbolic link' if path.is_symlink() else ''})"
                          f": `chmod 600` it if nobody else could read it, otherwise "
                          "replace the key")


def load_server_key(fleet_dir: Path) -> Secret:
    """Read the server's private key.

    Raises:
        ConfigError: naming the file if it is missing or malformed.
    """
    path = server_key_path(fleet_dir)
    if not os.path.lexists(path):
        # Never made again by itself: every robot's wg0.conf (and bundle) names its public
        # key, and a new one would cut them all off.
        raise ConfigError(f"{path}: key file not found: restore it from a backup of the "
                          "fleet directory (a new server key would cut off every robot "
                          "already deployed; `fleetctl init --force` makes a new fleet)")
    return _read_key(path)


def load_robot_keys(fleet_dir: Path, name: str) -> RobotKeys | None:
    """Read robot *name*'s keys; ``None`` if neither file exists.

    Raises:
        ConfigError: naming the file if one is missing or malformed.
    """
    key_path, psk_path = robot_key_paths(fleet_dir, name)
    if not key_path.exists() and not psk_path.exists():
        return None
    return RobotKeys(_read_key(key_path), _read_key(psk_path))


def new_robot_keys(source: KeySource) -> RobotKeys:
    """Make a robot key pair's private half and a preshared key."""
    return RobotKeys(new_private_key(source), new_preshared_key(source))


def plan_secret_file(plan: Plan, path: Path, text: str) -> None:
    """Add writing a secret file under ``keys/`` to *plan*: 0600 in 0700 directories,
    written through a temp file that is never opened through a symlink.
    """
    plan.directory(path.parent, SECRET_DIR_MODE)
    plan.write(path, text, secret=True)


def plan_server_key(plan: Plan, fleet_dir: Path, key: Secret) -> None:
    """Add writing the server's private key to *plan*."""
    plan.directory(fleet_dir / KEYS_DIR, SECRET_DIR_MODE)
    plan.write(server_key_path(fleet_dir), key.reveal() + "\n", secret=True)


def plan_robot_keys(plan: Plan, fleet_dir: Path, name: str, keys: RobotKeys) -> None:
    """Add writing robot *name*'s key files to *plan*."""
    key_path, psk_path = robot_key_paths(fleet_dir, name)
    plan.directory(fleet_dir / KEYS_DIR, SECRET_DIR_MODE)
    plan.write(key_path, keys.private_key.reveal() + "\n", secret=True)
    plan.write(psk_path, keys.preshared_key.reveal() + "\n", secret=True)
