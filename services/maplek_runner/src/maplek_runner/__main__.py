"""``python -m maplek_runner PLAN --node NAME``: run the MAPLE-K components that a
deployment plan maps to one compute node, in this process, until SIGTERM or SIGINT."""

from __future__ import annotations

import importlib.util
import logging
import signal
from functools import partial
from pathlib import Path
from typing import Annotated

import anyio
import typer
import zenoh
from rap_schemas import PlanError, load_plan
from rap_sdk import FabricError, LifecycleError, ZenohConfig, ZenohFabric
from rap_sdk.entry import (
    LogFileOpt,
    LogRedisOpt,
    MetricsOpt,
    check_endpoints,
    check_system,
    fail,
    leaf,
    run_cli,
    setup_logging,
)
from rap_sdk.logs import LogContext, check_redis_url, open_file_log, publish_logs
from rap_sdk.metrics import RuntimeCollector, check_metrics_option, start_metrics
from rap_sdk.peers import PeerWatch

from .errors import RunnerError
from .loading import NodeShare, load_share
from .runner import fabric_config, run_share

__all__ = ["cli", "main"]

cli = typer.Typer(add_completion=False, help=__doc__, rich_markup_mode=None)

log = logging.getLogger("maplek_runner")


@cli.command()
def main(
    plan: Annotated[Path, typer.Argument(metavar="PLAN", help="Deployment plan (YAML).")],
    node: Annotated[
        str, typer.Option("--node", help="The compute node to run (a key of compute_nodes).")
    ],
    listen: Annotated[
        list[str] | None,
        typer.Option(help="Zenoh listen endpoint, repeatable (replaces the plan's)."),
    ] = None,
    connect: Annotated[
        list[str] | None,
        typer.Option(help="Zenoh endpoint to connect, repeatable (replaces the plan's)."),
    ] = None,
    system: Annotated[str | None, typer.Option(help="System name (default: the plan's).")] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
    metrics: MetricsOpt = None,
    log_file: LogFileOpt = None,
    log_redis: LogRedisOpt = None,
) -> None:
    """Run a compute node's share of a deployment plan. A bad plan exits with code 2.

    Example: python -m maplek_runner model.yaml --node robot --metrics 127.0.0.1:9464"""
    setup_logging(log_level)
    metrics = check_metrics_option(metrics)
    log_redis = check_redis_url(log_redis)
    if system is not None:
        check_system(system)
    listen = check_endpoints("--listen", listen)
    connect = check_endpoints("--connect", connect)
    try:
        doc = load_plan(plan)
        share = load_share(doc, node)
        zconf = fabric_config(doc.plan, node, listen=listen, connect=connect)
    except (PlanError, RunnerError) as exc:
        raise fail(str(exc)) from None
    if not share.components:
        raise fail(
            f"{doc.where(('compute_nodes', node), key=True)}: the plan maps no components "
            f"to compute node {node!r}, so there is nothing to run - map one with "
            f"'node: {node}' under components"
        )
    zenoh.try_init_log_from_env()
    logs = LogContext(
        system=system or share.system,
        compute_node=node,
        process="runner",
        components={(c.spec.module or "").partition(":")[0]: c.name for c in share.components},
        names=frozenset(c.name for c in share.components),
    )
    open_file_log(log_file, logs)
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    try:
        anyio.run(
            partial(_serve, logs=logs, metrics=metrics, log_redis=log_redis),
            share,
            zconf,
            system,
            backend_options={"use_uvloop": use_uvloop},
        )
    except (FabricError, LifecycleError, BaseExceptionGroup) as exc:
        inner = leaf(exc)
        if isinstance(inner, FabricError):  # e.g. a listen endpoint that is taken
            raise fail(f"{inner} - check --listen and --connect (or the plan's)", 1) from None
        if isinstance(inner, LifecycleError):  # a component already running elsewhere
            raise fail(str(inner), 1) from None
        raise


async def _serve(
    share: NodeShare,
    zconf: ZenohConfig,
    system: str | None,
    *,
    logs: LogContext,
    metrics: str | None = None,
    log_redis: str | None = None,
) -> None:
    stop = anyio.Event()
    name = system or share.system
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with (
            ZenohFabric(zconf) as fabric,
            publish_logs(fabric, logs, node=f"runner-{share.compute_node}", redis_url=log_redis),
            anyio.create_task_group() as tg,
        ):
            watch = PeerWatch(
                fabric=fabric,
                system=name,
                mine={c.name for c in share.components},
                expect_knowledge=True,
            )
            await tg.start(watch.run)
            async with anyio.create_task_group() as share_tg:
                group = await share_tg.start(
                    partial(
                        run_share,
                        share,
                        fabric=fabric,
                        system=system,
                        stop=stop,
                        gc_idle=True,
                        resume_state=True,  # a restarted runner resumes its components' state
                    )
                )
                # served from a daemon thread of its own until the process ends
                collector = RuntimeCollector(
                    lambda: group.runtimes, system=name, compute_node=share.compute_node
                )
                start_metrics(metrics, [collector], what="runner")
                log.info("ready: %s", fabric.reach)
                async for signum in signals:
                    log.info("received %s; stopping", signal.Signals(signum).name)
                    stop.set()
                    break
            tg.cancel_scope.cancel()  # the share has stopped: the watch ends too


if __name__ == "__main__":
    run_cli(cli)
