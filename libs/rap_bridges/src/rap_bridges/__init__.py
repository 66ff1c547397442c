"""rap_bridges: ports of a RAP model bound to protocols outside the Zenoh fabric.

A :class:`Bridge` runs one port's pump between the fabric and a :class:`Link` (MQTT in
:mod:`rap_bridges.mqtt`, TCP frames in :mod:`rap_bridges.tcp`), as a
:class:`BridgeSpec` says: reconnect with backoff and jitter, a bounded buffer with a
declared overflow policy, typed decoding at the boundary, and everything counted
(:class:`BridgeStats`, exported by :class:`rap_bridges.metrics.BridgeCollector`).
See docs/bridges.md.
"""

from .core import (
    HEADER_CAUSE,
    HEADER_CYCLE,
    HEADER_SOURCE,
    HEADER_TYPE,
    Backoff,
    Bridge,
    BridgeStats,
    Deliver,
    Direction,
    Frame,
    Link,
    LinkContext,
    LinkDown,
    buffer_policy,
    make_link,
    register_link,
)
from .spec import BridgeSpec, Format, OverflowPolicy, ProtocolName, decode_spec

__all__ = [
    "HEADER_CAUSE",
    "HEADER_CYCLE",
    "HEADER_SOURCE",
    "HEADER_TYPE",
    "Backoff",
    "Bridge",
    "BridgeSpec",
    "BridgeStats",
    "Deliver",
    "Direction",
    "Format",
    "Frame",
    "Link",
    "LinkContext",
    "LinkDown",
    "OverflowPolicy",
    "ProtocolName",
    "buffer_policy",
    "decode_spec",
    "make_link",
    "register_link",
]
