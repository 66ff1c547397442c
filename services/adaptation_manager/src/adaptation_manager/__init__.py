"""RAP adaptation manager: the registry of a running system, its watches and dashboard.

    python -m adaptation_manager --system demo --http 127.0.0.1:8470

:class:`Manager` follows one system on a fabric (liveliness, trace records, events,
trust verdicts, logs; status queries), keeps a :class:`Registry` of its components,
cycles and plans with the watches' :class:`Metrics`, answers ``rap trace``
(:class:`TraceRequest` / :class:`TraceReply` on ``rap/<system>/admin/manager/trace``),
and :func:`serve_dashboard` serves the live page.
"""

from .dashboard import Hub, serve_dashboard
from .service import COMMANDS, CommandResult, Manager
from .state import Metrics, Registry
from .views import MANAGER, TRACE_VERB, CycleTrace, TraceReply, TraceRequest, TraceStep

__all__ = [
    "COMMANDS",
    "MANAGER",
    "TRACE_VERB",
    "CommandResult",
    "CycleTrace",
    "Hub",
    "Manager",
    "Metrics",
    "Registry",
    "TraceReply",
    "TraceRequest",
    "TraceStep",
    "serve_dashboard",
]
