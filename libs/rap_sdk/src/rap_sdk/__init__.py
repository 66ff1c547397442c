"""rap_sdk: the client SDK of RAP.

Declare MAPLE-K nodes with :class:`Node`, run them on a :class:`Fabric` with
:func:`run_nodes` (or :func:`run` as a process), test them with
:mod:`rap_sdk.testing`. Errors: see :mod:`rap_sdk.errors`.
"""

from .app import run
from .envelope import Clock, Opener, OutgoingEnvelope, Sealer, SenderStats, SystemClock
from .errors import (
    BackpressureTimeout,
    ConfigError,
    FabricError,
    HandlerError,
    LifecycleError,
    QueryError,
    RapError,
    RejectedSample,
)
from .fabric import (
    Fabric,
    LivelinessChange,
    MemoryBus,
    MemoryFabric,
    QueryRequest,
    Reply,
    Sample,
    ZenohConfig,
    ZenohFabric,
)
from .inbox import InboxPolicy, Overflow
from .knowledge import KnowledgeClient, KnowledgeError, KnowledgeTypeError
from .node import Node
from .runtime import (
    Context,
    ContextKnowledge,
    NodeGroup,
    NodeRuntime,
    NodeStats,
    await_alive,
    run_nodes,
    serve,
)

__all__ = [
    "BackpressureTimeout",
    "Clock",
    "ConfigError",
    "Context",
    "ContextKnowledge",
    "Fabric",
    "FabricError",
    "HandlerError",
    "InboxPolicy",
    "KnowledgeClient",
    "KnowledgeError",
    "KnowledgeTypeError",
    "LifecycleError",
    "LivelinessChange",
    "MemoryBus",
    "MemoryFabric",
    "Node",
    "NodeGroup",
    "NodeRuntime",
    "NodeStats",
    "Opener",
    "OutgoingEnvelope",
    "Overflow",
    "QueryError",
    "QueryRequest",
    "RapError",
    "RejectedSample",
    "Reply",
    "Sample",
    "Sealer",
    "SenderStats",
    "SystemClock",
    "ZenohConfig",
    "ZenohFabric",
    "await_alive",
    "run",
    "run_nodes",
    "serve",
]
