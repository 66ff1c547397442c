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
from rap_schemas import PlanError, keys, load_plan
from rap_schemas.plan import ENDPOINT
from rap_sdk import FabricError, ZenohConfig, ZenohFabric

from .errors import RunnerError
from .loading import NodeShare, load_share
from .runner import fabric_config, run_share

cli = typer.Typer(add_completion=False, help=__doc__)

log = logging.getLogger("maplek_runner")


def _fail(message: str, code: int) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


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
) -> None:
    """Run a compute node's share of a deployment plan. A bad plan exits with code 2."""
    level = logging.getLevelNamesMapping().get(log_level.upper())
    if level is None:
        raise typer.BadParameter(
            f"{log_level!r} is not a logging level; use DEBUG, INFO, WARNING or ERROR",
            param_hint="--log-level",
        )
    try:
        if system is not None:
            keys.system_pattern(system)
        for option, endpoints in (("--listen", listen), ("--connect", connect)):
            for endpoint in endpoints or ():
                if not ENDPOINT.fullmatch(endpoint):
                    raise _fail(
                        f"{option} {endpoint!r} is not a Zenoh endpoint; write "
                        "'<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'",
                        2,
                    )
        doc = load_plan(plan)
        share = load_share(doc, node)
        zconf = fabric_config(doc.plan, node, listen=listen, connect=connect)
    except (PlanError, RunnerError, keys.KeyError_) as exc:
        raise _fail(str(exc), 2) from None
    if not share.components:
        raise _fail(
            f"{doc.where(('compute_nodes', node), key=True)}: the plan maps no components "
            f"to compute node {node!r}, so there is nothing to run; map one with "
            f"'node: {node}' under components",
            2,
        )
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    zenoh.try_init_log_from_env()
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    try:
        anyio.run(_serve, share, zconf, system, backend_options={"use_uvloop": use_uvloop})
    except FabricError as exc:  # e.g. a listen endpoint that is taken
        raise _fail(str(exc), 1) from None


async def _serve(share: NodeShare, zconf: ZenohConfig, system: str | None) -> None:
    stop = anyio.Event()
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with ZenohFabric(zconf) as fabric, anyio.create_task_group() as tg:
            await tg.start(partial(run_share, share, fabric=fabric, system=system, stop=stop))
            log.info("ready: listening on %s", ", ".join(zconf.listen))
            async for signum in signals:
                log.info("received %s; stopping", signal.Signals(signum).name)
                stop.set()
                break


if __name__ == "__main__":
    cli()
