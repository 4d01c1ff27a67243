"""fleetctl.wire."""
