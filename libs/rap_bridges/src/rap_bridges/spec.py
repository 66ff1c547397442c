"""What a bridge is bound to: :class:`BridgeSpec`. Its home is :mod:`rap_schemas.bridge`,
because a model's port carries one (``PortSpec.bridge``); it is named here too for code
that builds bridges."""

from rap_schemas.bridge import (
    DEFAULT_PORTS,
    PROTOCOLS,
    SCHEMES,
    BridgeSpec,
    Format,
    OverflowPolicy,
    ProtocolName,
    decode_spec,
)

__all__ = [
    "DEFAULT_PORTS",
    "PROTOCOLS",
    "SCHEMES",
    "BridgeSpec",
    "Format",
    "OverflowPolicy",
    "ProtocolName",
    "decode_spec",
]
