"""fleetctl.client."""
