"""fleetctl.server."""
