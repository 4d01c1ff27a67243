"""Only what pyproject.toml cannot say: the top-level ``templates/`` and ``images/``
directories ship inside the wheel as package data (``fleetctl/_templates``,
``fleetctl/_images``), so an installed fleetctl needs no source checkout."""

from setuptools import find_packages, setup

ASSET_PACKAGES = {"fleetctl._templates": "templates", "fleetctl._images": "images"}

setup(
    packages=[*find_packages(include=["fleetctl", "fleetctl.*"]), *ASSET_PACKAGES],
    package_dir=ASSET_PACKAGES,
)
