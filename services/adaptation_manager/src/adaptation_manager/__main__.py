"""``python -m adaptation_manager --system S``: the adaptation manager of one system and
its live dashboard.

    python -m adaptation_manager --system demo --http 127.0.0.1:8470
    python -m adaptation_manager --system demo --connect tcp/10.0.0.2:7447 --http 127.0.0.1:0

It follows every component of the system (liveliness, trace records, events, trust
verdicts, logs), asks each for its status every --status-interval seconds, watches for
components gone or failing, cycles that do not complete within --cycle-timeout seconds
and trust verdicts false, answers ``rap trace``, and serves the dashboard (the page, a
WebSocket, /metrics) on --http. Under ``rap up`` it is a Zenoh client of its compute
node's router (``RAP_ZENOH_CONFIG``). With ``RAP_CERTS`` and ``RAP_AS`` set (``rap up``
with TLS sets them) it signs its admin requests as that identity, as components with
identities want. It runs until SIGTERM or SIGINT. A mistake in the options is one
``error:`` line and exit code 2; a second manager of the same system exits with code 1.
"""

from __future__ import annotations

import logging
import signal
from typing import Annotated

import anyio
import typer
from rap_sdk import FabricError, LifecycleError, ZenohConfig, ZenohFabric
from rap_sdk.entry import check_endpoints, check_system, fail, leaf, run_cli, setup_logging
from rap_sdk.identity import AS_ENV, CERTS_ENV, IdentityError, Signer, signer_from_env

from .dashboard import serve_dashboard
from .service import Manager
from .state import Registry

__all__ = ["cli", "main", "parse_http"]

cli = typer.Typer(add_completion=False, help=__doc__, rich_markup_mode=None)
log = logging.getLogger("adaptation_manager")


def parse_http(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8470`` for IPv6; port 0: a free one)."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise fail(
            f"--http {text!r} is not HOST:PORT - write e.g. 127.0.0.1:8470 (port 0: any free one)"
        )
    return host, int(port)


@cli.command()
def main(
    system: Annotated[str, typer.Option(help="The system to manage: rap/<system>/**.")],
    http: Annotated[
        str,
        typer.Option(
            metavar="HOST:PORT",
            help="Where the dashboard listens (loopback by default; port 0: a free one).",
        ),
    ] = "127.0.0.1:8470",
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect, repeatable.")
    ] = None,
    listen: Annotated[list[str] | None, typer.Option(help="Zenoh listen endpoint.")] = None,
    status_interval: Annotated[
        float, typer.Option(help="Seconds between status queries to the components.")
    ] = 1.0,
    cycle_timeout: Annotated[
        float, typer.Option(help="Seconds a cycle may stay open before it counts as stalled.")
    ] = 10.0,
    history: Annotated[int, typer.Option(help="Cycles kept (for the page and rap trace).")] = 500,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
) -> None:
    """Run the adaptation manager of one system until SIGTERM or SIGINT."""
    setup_logging(log_level)
    check_system(system)
    host, port = parse_http(http)
    if status_interval <= 0:
        raise fail(f"--status-interval {status_interval:g}: give a number of seconds > 0")
    if cycle_timeout <= 0:
        raise fail(f"--cycle-timeout {cycle_timeout:g}: give a number of seconds > 0")
    if history < 1:
        raise fail(f"--history {history}: keep at least 1 cycle")
    zconf = ZenohConfig(
        listen=check_endpoints("--listen", listen) or ["tcp/127.0.0.1:0"],
        connect=check_endpoints("--connect", connect),
    )
    try:
        signer = signer_from_env()
    except IdentityError as exc:
        raise fail(f"${AS_ENV} in ${CERTS_ENV}: {exc}") from None
    try:
        anyio.run(
            _serve, system, zconf, host, port, status_interval, cycle_timeout, history, signer
        )
    except (FabricError, LifecycleError, OSError, BaseExceptionGroup) as exc:
        inner = leaf(exc)
        if isinstance(inner, LifecycleError):  # another manager of the system runs
            raise fail(str(inner), 1) from None
        if isinstance(inner, FabricError):
            raise fail(f"{inner} - check --listen and --connect", 1) from None
        if isinstance(inner, OSError):  # the dashboard's address is taken or not ours
            raise fail(
                f"--http {http}: cannot listen there ({inner.strerror or inner}) - choose "
                "another address or port (port 0: a free one)",
                1,
            ) from None
        raise


async def _serve(
    system: str,
    zconf: ZenohConfig,
    host: str,
    port: int,
    status_interval: float,
    cycle_timeout: float,
    history: int,
    signer: Signer | None = None,
) -> None:
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with ZenohFabric(zconf) as fabric, anyio.create_task_group() as tg:
            registry = Registry(system, history=history, cycle_timeout=cycle_timeout)
            manager = Manager(
                fabric=fabric,
                system=system,
                registry=registry,
                status_interval=status_interval,
                signer=signer,
            )
            if signer is not None:
                log.info("signing admin requests as %s", signer.caller)
            await tg.start(manager.run)
            url = await tg.start(serve_dashboard, manager, host, port)
            log.info("ready: system %r, dashboard %s (metrics: %smetrics)", system, url, url)
            async for signum in signals:
                log.info("received %s: stopping", signal.Signals(signum).name)
                break
            tg.cancel_scope.cancel()


if __name__ == "__main__":
    run_cli(cli)
