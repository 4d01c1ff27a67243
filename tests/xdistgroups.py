"""A pytest plugin: the xdist groups scripts/test.sh runs the suite in.

``pytest -n 2 --dist loadgroup``: a module marked ``own_worker`` (the e2e scenario run:
~9.5 min spent mostly waiting on timed phases) is one group, every other test the other,
in its usual order. Why not plain ``-n 2``: the other tests were written to run one at a
time (docker fleets, network namespaces, ROS nodes, a browser, timed phases on two
cores); two of them at once is not what they were checked against (a run that split
them failed two ROS link tests and ran the e2e fixture twice). The e2e run shares nothing
with them but the CPU: its containers, networks and volumes carry its own run id, it
publishes no host port, and its image build is a no-op after the script's ``fleetctl
build``. Without ``-n`` the groups are ignored and everything runs serially, as before.
"""

from __future__ import annotations

import pytest

SUITE_GROUP = "suite"


# First: xdist's own hook turns each item's xdist_group marker into its node id's group,
# and a marker added after it is ignored (every test then went to either worker).
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        module = getattr(item, "module", None)
        own = item.get_closest_marker("own_worker") is not None and module is not None
        item.add_marker(pytest.mark.xdist_group(module.__name__ if own else SUITE_GROUP))
