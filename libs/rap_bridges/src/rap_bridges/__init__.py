"""rap_bridges: ports of a RAP model bound to protocols outside the Zenoh fabric.

A :class:`Bridge` runs one port's pump between the fabric and a :class:`Link` (MQTT,
TCP frames, Redis pub/sub and streams, AMQP, WebSocket, NATS, DDS for ROS 2, Kafka: a
module of this package each), as a
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
    FrameRefused,
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
    "FrameRefused",
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
