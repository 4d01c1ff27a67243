"""Only what pyproject.toml cannot say: the top-level ``templates/`` and ``images/``
directories ship inside the wheel as package data (``fleetctl/_templates``,
``fleetctl/_images``), and so does ``scripts/ros_msgs`` (``fleetctl/_ros_msgs``, the builder
of the tf2_msgs/foxglove_msgs wheels ``fleetctl build`` puts in the client image), so an
installed fleetctl needs no source checkout. The builder runs as a script, never imported as
``fleetctl._ros_msgs``; its foxglove_msgs input is ``fleetctl/wire/msg``, already package
data."""

from setuptools import find_packages, setup

ASSET_PACKAGES = {
    "fleetctl._templates": "templates",
    "fleetctl._images": "images",
    "fleetctl._ros_msgs": "scripts/ros_msgs",
}

setup(
    packages=[*find_packages(include=["fleetctl", "fleetctl.*"]), *ASSET_PACKAGES],
    package_dir=ASSET_PACKAGES,
)
