"""Relay replicas on a NATS cluster (issue 15, docs/scaling.md).

Only :mod:`fleetctl.server.cluster.natsfanout` imports ``nats``; the config and subject
modules are plain Python, so a server without a ``cluster:`` section never imports it.
"""
