"""fleetctl.wire: the Robofleet-compatible FlatBuffers wire format (no I/O).

Public API (``docs/design.md`` section 1): :mod:`.errors` (``WireError``),
:mod:`.metadata` (``Metadata``, ``read_metadata``, ``normalize_type``), :mod:`.registry`
(``TypeRegistry``), :mod:`.codec` (``Codec``, ``default_codec``), :mod:`.control`
(subscription and status helpers), :mod:`.fragments` (``split``, ``Reassembler``),
:mod:`.schema` (``export_fbs``, ``describe``). See ``docs/wire.md``.
"""
