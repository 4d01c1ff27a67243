"""``fleetctl e2e``: end-to-end runs of the fleet over tc-shaped links in containers.

Modules: :mod:`.samples` (what consumers record), :mod:`.metrics` (pure analysis),
:mod:`.report` (JSON, Markdown, PNG), :mod:`.topology` (networks, router, containers),
:mod:`.deployment` (the fleet as ``fleetctl up`` deploys it), :mod:`.wireguard` (tunnel on
or off, MTU, subnet), :mod:`.interrupt` (signals unwind a run),
:mod:`.cleanup` (labels, leftovers).
"""
