"""Errors of the runner.

    RunnerError            base of the runner's own errors
     └── LoadError         the plan's share for a compute node cannot be loaded: unknown
                           compute node, a module that does not import, an attribute that
                           is not a rap_sdk.Node, a stage or name that disagrees with the
                           plan, a config the Node rejects

A plan file that is not valid is a :class:`rap_schemas.PlanError` (raised before the
runner looks at code). Both carry ``file:line:col`` of the plan.
"""

from __future__ import annotations

__all__ = ["LoadError", "RunnerError"]


class RunnerError(Exception):
    """Base of the runner's errors."""


class LoadError(RunnerError):
    """A component of the plan cannot be loaded; the message starts with the plan's
    ``file:line:col`` (or the file alone) and says how to fix it."""
