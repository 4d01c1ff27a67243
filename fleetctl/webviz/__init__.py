"""fleetctl.webviz."""
