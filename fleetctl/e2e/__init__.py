"""``fleetctl e2e``: end-to-end runs of the fleet over tc-shaped links in containers.

Modules: :mod:`.samples` (what consumers record), :mod:`.metrics` (pure analysis),
:mod:`.report` (JSON, Markdown, PNG), :mod:`.topology` (networks, router, containers),
:mod:`.wireguard` (the fleet over the tunnel), :mod:`.interrupt` (signals unwind a run),
:mod:`.cleanup` (labels, leftovers).
"""
