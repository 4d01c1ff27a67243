"""Where the files the CLI needs besides Python code live: ``templates/`` and ``images/``.

In the repository they are top-level directories (the layout of docs/design.md); a built
wheel carries them as package data at ``fleetctl/_templates`` and ``fleetctl/_images``
(``setup.py`` maps them), so an installed ``fleetctl`` renders configs and builds images
with no checkout. An editable install has neither copy in the package and uses the
checkout's directories.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from fleetctl.errors import EnvironmentMissing

AssetName = Literal["templates", "images"]
_PACKAGE_DIR = Path(__file__).resolve().parents[1]
# Overrides, mostly for tests and for operators who keep customised templates.
ENV_OVERRIDES: dict[str, str] = {"templates": "FLEETCTL_TEMPLATES", "images": "FLEETCTL_IMAGES"}


def candidates(name: AssetName) -> list[Path]:
    """The places *name* is looked up, in order (override, package data, checkout)."""
    found = []
    override = os.environ.get(ENV_OVERRIDES[name])
    if override:
        found.append(Path(override))
    found.append(_PACKAGE_DIR / f"_{name}")
    found.append(_PACKAGE_DIR.parent / name)
    return found


def asset_dir(name: AssetName) -> Path:
    """Return the directory holding *name* (``templates`` or ``images``).

    Raises:
        EnvironmentMissing: none of the candidates exists (a broken installation).
    """
    places = candidates(name)
    for place in places:
        if place.is_dir():
            return place
    raise EnvironmentMissing(
        f"{name}/ not found (looked in {', '.join(str(p) for p in places)}): the fleetctl "
        f"installation is incomplete; reinstall it, or set {ENV_OVERRIDES[name]}"
    )
