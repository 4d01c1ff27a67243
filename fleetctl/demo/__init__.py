"""``fleetctl demo``: a whole fleet on this machine (server, simulated robots, webviz)."""
