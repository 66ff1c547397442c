"""Hosts the MAPLE-K components that a deployment plan maps to one compute node.

    doc = rap_schemas.load_plan("plan.yaml")
    async with ZenohFabric(fabric_config(doc.plan, "laptop")) as fabric:
        await run_plan(doc, "laptop", fabric=fabric, stop=stop)

or as a process: ``python -m maplek_runner plan.yaml --node laptop``. Errors: see
:mod:`maplek_runner.errors`.
"""

from .errors import LoadError, RunnerError
from .loading import LoadedComponent, NodeShare, import_node, load_share
from .runner import fabric_config, run_plan, run_share

__all__ = [
    "LoadError",
    "LoadedComponent",
    "NodeShare",
    "RunnerError",
    "fabric_config",
    "import_node",
    "load_share",
    "run_plan",
    "run_share",
]
