"""The Foxglove WebSocket protocol (``foxglove.websocket.v1``) on the relay's port.

An adapter, not a second relay (STYLE.md): :mod:`.adapter` turns the protocol's messages
into :class:`~fleetctl.server.relay.RelayCore` calls (authenticate, subscribe, send) and
the core's deliveries, popped from the connection's own
:class:`~fleetctl.server.outbound.OutboundScheduler`, into Foxglove frames. ACLs, latched
messages and the bounded latest-per-topic queues are the core's.

Rooms: :mod:`.messages` (the wire format, no I/O), :mod:`.tickets` (short-lived single-use
sign-in tickets), :mod:`.catalog` (which topics exist, their channel ids),
:mod:`.transcode` (frame to CDR, once per frame), :mod:`.offload` (the conversion, off
the event loop), :mod:`.viewer` (one connection's channels and subscriptions),
:mod:`.adapter` (the asyncio layer).
"""
