"""Run a deployment plan as local processes on loopback, the way ``rap up`` will.

    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        async with local_deployment(plan_path, fabric=fabric, endpoint=ep, logs=dir) as d:
            ...                                 # every component is alive and reachable

One knowledge service process and one ``maplek_runner`` process per compute node of the
plan. Peers do not route for each other, so the processes form a full mesh: each listens
on a free loopback port and connects to every endpoint started before it (the caller's
first). Output goes to ``<logs>/<name>.log``. On exit every process gets SIGTERM (then
SIGKILL after a grace period), in reverse order.
"""

from __future__ import annotations

import contextlib
import logging
import subprocess
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import anyio
from anyio.abc import Process
from maplek_runner.loading import load_share
from rap_schemas import PlanDocument, load_plan
from rap_sdk import Fabric, Node, await_alive
from rap_sdk.fabric import free_port

__all__ = ["Deployment", "local_deployment", "plan_nodes"]

log = logging.getLogger(__name__)

KNOWLEDGE = "knowledge"
STARTUP = 60.0
"""Seconds every process has to come up."""


def plan_nodes(doc: PlanDocument) -> list[Node]:
    """Every component of the plan, on all compute nodes (imported here, not run)."""
    return [n for cn in doc.plan.compute_nodes for n in load_share(doc, cn).nodes]


@dataclass
class Deployment:
    doc: PlanDocument
    processes: dict[str, Process] = field(default_factory=dict)

    @property
    def system(self) -> str:
        return self.doc.plan.system


async def _stop(name: str, proc: Process, grace: float = 10.0) -> None:
    if proc.returncode is None:
        proc.terminate()
    with anyio.move_on_after(grace):
        await proc.wait()
    if proc.returncode is None:
        log.warning("%s did not stop within %.0f s of SIGTERM; killing it", name, grace)
        proc.kill()
        await proc.wait()
    if proc.returncode not in (0, -15):
        log.warning("%s exited with code %s (see its log)", name, proc.returncode)


@contextlib.asynccontextmanager
async def local_deployment(
    plan: str | Path,
    *,
    fabric: Fabric,
    endpoint: str,
    logs: Path,
    knowledge: bool = True,
    system: str | None = None,
) -> AsyncIterator[Deployment]:
    """Start the plan's processes meshed with ``fabric`` (listening on ``endpoint``)."""
    doc = load_plan(plan)
    dep = Deployment(doc)
    sys_name = system or doc.plan.system
    await anyio.Path(logs).mkdir(parents=True, exist_ok=True)
    endpoints = [endpoint]
    async with contextlib.AsyncExitStack() as stack:

        async def start(name: str, args: list[str], alive: set[str]) -> None:
            ep = f"tcp/127.0.0.1:{free_port()}"
            connects = [a for e in endpoints for a in ("--connect", e)]
            path = logs / f"{name}.log"
            out = stack.enter_context(await anyio.to_thread.run_sync(path.open, "wb"))
            proc = await anyio.open_process(
                [sys.executable, "-m", *args, "--listen", ep, *connects],
                stdout=out,
                stderr=subprocess.STDOUT,
            )
            dep.processes[name] = proc
            stack.push_async_callback(_stop, name, proc)
            endpoints.append(ep)
            try:
                await await_alive(alive, fabric=fabric, system=sys_name, timeout=STARTUP)
            except TimeoutError as exc:
                raise RuntimeError(
                    f"{name} did not come up ({exc}); its output is in {logs / (name + '.log')}"
                ) from None

        if knowledge:
            backend = doc.plan.knowledge.backend
            await start(
                KNOWLEDGE,
                ["knowledge", "--system", sys_name, "--backend", backend, "--log-level", "WARNING"],
                {KNOWLEDGE},
            )
        for cn in doc.plan.compute_nodes:
            share = load_share(doc, cn)
            if not share.components:
                continue
            await start(
                f"runner-{cn}",
                ["maplek_runner", str(plan), "--node", cn, "--system", sys_name],
                {n.name for n in share.nodes},
            )
        yield dep
