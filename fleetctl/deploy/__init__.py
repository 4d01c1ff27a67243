"""fleetctl.deploy."""
