"""fleetctl.client.ros."""
