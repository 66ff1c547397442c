"""The data fabric: one protocol, two implementations that pass one contract suite."""

from ._types import (
    Fabric,
    FabricStats,
    LivelinessChange,
    LivelinessWatch,
    Outgoing,
    Queryable,
    QueryHandler,
    QueryRequest,
    Reply,
    Sample,
    Subscription,
    Token,
)
from .memory import MemoryBus, MemoryFabric
from .zenoh_fabric import CONFIG_ENV, ZenohConfig, ZenohFabric, free_port, node_overlay

__all__ = [
    "CONFIG_ENV",
    "Fabric",
    "FabricStats",
    "LivelinessChange",
    "LivelinessWatch",
    "MemoryBus",
    "MemoryFabric",
    "Outgoing",
    "QueryHandler",
    "QueryRequest",
    "Queryable",
    "Reply",
    "Sample",
    "Subscription",
    "Token",
    "ZenohConfig",
    "ZenohFabric",
    "free_port",
    "node_overlay",
]
