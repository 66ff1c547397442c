"""Running a compute node's share of a plan: its Nodes in this process, on one fabric.

    async with ZenohFabric(fabric_config(doc.plan, "laptop")) as fabric:
        await run_plan(doc, "laptop", fabric=fabric, stop=stop)

Each route of each Node has its own bounded inbox and consumer (see rap_sdk.runtime);
the Nodes share the process's one fabric session.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import anyio
from anyio.abc import TaskStatus
from rap_schemas import DeploymentPlan, PlanDocument
from rap_sdk import Clock, Fabric, NodeGroup, ZenohConfig, run_nodes

from .errors import LoadError
from .loading import NodeShare, load_share

__all__ = ["fabric_config", "run_plan", "run_share"]

log = logging.getLogger(__name__)


def fabric_config(
    plan: DeploymentPlan,
    compute_node: str,
    *,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
) -> ZenohConfig:
    """The Zenoh config of ``compute_node``: the plan's endpoints, each list replaced by
    ``listen`` / ``connect`` when given (non-empty). No listen endpoint at all: the
    fabric's default (loopback, a free port). Its links drop a message over the model's
    ``fabric.max_sample_bytes``."""
    node = plan.compute_nodes.get(compute_node)
    if node is None:
        raise LoadError(
            f"compute node {compute_node!r} is not in the plan; its compute nodes are: "
            f"{', '.join(plan.compute_nodes)}"
        )
    listen_on = list(listen or node.listen)
    connect_to = list(connect or node.connect)
    limit = plan.fabric.max_sample_bytes
    if listen_on:
        return ZenohConfig(listen=listen_on, connect=connect_to, max_sample_bytes=limit)
    return ZenohConfig(connect=connect_to, max_sample_bytes=limit)


async def run_share(
    share: NodeShare,
    *,
    fabric: Fabric,
    system: str | None = None,
    stop: anyio.Event | None = None,
    clock: Clock | None = None,
    trace: bool = True,
    grace: float = 5.0,
    gc_idle: bool = False,
    resume_state: bool = False,
    task_status: TaskStatus[NodeGroup] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Run a loaded share until ``stop`` is set, then stop gracefully: no new input,
    what is queued is handled (within ``grace`` s). Cancelling the task stops at once.
    ``gc_idle``: collect garbage only while the nodes are idle (the runner process
    does; see :mod:`rap_sdk.gc`). ``resume_state``: components with a restore hook
    resume from their latest snapshot in knowledge (the runner process does).

    ``task_status.started`` gets the :class:`~rap_sdk.NodeGroup` once every Node is
    subscribed and its liveliness token declared. ``system`` overrides the plan's."""
    system = system or share.system
    log.info(
        "compute node %s of system %r: running %d component(s): %s",
        share.compute_node,
        system,
        len(share.components),
        ", ".join(
            f"{c.name} ({c.spec.stage or c.spec.role or 'no stage'}, {c.spec.module})"
            for c in share.components
        ),
    )
    async with run_nodes(
        share.nodes,
        fabric=fabric,
        system=system,
        clock=clock,
        trace=trace,
        grace=grace,
        gc_idle=gc_idle,
        compute_node=share.compute_node,
        resume_state=resume_state,
    ) as group:
        task_status.started(group)
        if stop is None:
            await anyio.sleep_forever()
        else:
            await stop.wait()
        log.info("stopping %d component(s)", len(share.components))
    for rt in group.runtimes:
        s = rt.stats
        trouble = s.failed or s.rejected or s.dropped or s.records_lost
        (log.warning if trouble else log.info)(
            "%s stopped: %d received, %d handled, %d failed, %d rejected, %d dropped by a "
            "full inbox, %d sent, %d trace/log records lost",
            rt.node.name,
            s.received,
            s.handled,
            s.failed,
            s.rejected,
            s.dropped,
            s.sent,
            s.records_lost,
        )


async def run_plan(
    plan: PlanDocument,
    compute_node: str,
    *,
    fabric: Fabric,
    system: str | None = None,
    stop: anyio.Event | None = None,
    clock: Clock | None = None,
    trace: bool = True,
    grace: float = 5.0,
    task_status: TaskStatus[NodeGroup] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Load what ``plan`` maps to ``compute_node`` (imports run in a worker thread) and
    run it as :func:`run_share` does. Raises :class:`~maplek_runner.errors.LoadError`
    before anything runs when the share cannot be loaded."""
    share = await anyio.to_thread.run_sync(load_share, plan, compute_node)
    await run_share(
        share,
        fabric=fabric,
        system=system,
        stop=stop,
        clock=clock,
        trace=trace,
        grace=grace,
        task_status=task_status,
    )
