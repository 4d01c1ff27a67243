"""The Debian-packaged browser libraries the page uses, and a clear report when missing.

The page loads three.js (``libjs-three``) for the point cloud and Leaflet (``libjs-leaflet``)
for GPS from ``/vendor/<lib>/``. Without them it still works (a 2D projection and a text
readout), so a missing library is a warning naming the Debian package, not an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class VendorLib:
    """One vendored library.

    Attributes:
        name: Directory name under the vendor dir and under ``/vendor/`` in URLs.
        entry: The file the page imports, relative to the library directory.
        debian_package: Package that provides it.
    """

    name: str
    entry: str
    debian_package: str


VENDOR_LIBS: tuple[VendorLib, ...] = (
    VendorLib("three", "three.module.js", "libjs-three"),
    VendorLib("leaflet", "leaflet.esm.js", "libjs-leaflet"),
)


def missing_vendor_libs(vendor_dir: Path) -> list[str]:
    """Say which vendored libraries are absent.

    Args:
        vendor_dir: Directory expected to hold ``three/`` and ``leaflet/``.

    Returns:
        One human-readable line per missing library (empty when all are present).
    """
    out = []
    for lib in VENDOR_LIBS:
        path = vendor_dir / lib.name / lib.entry
        if not path.is_file():
            out.append(
                f"{path} not found: install the Debian package {lib.debian_package} "
                f"(apt-get install {lib.debian_package}) or pass --vendor-dir; "
                f"the page falls back to a simpler view without it"
            )
    return out
