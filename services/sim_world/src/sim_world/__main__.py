"""``python -m sim_world [--world NAME|FILE] [--lockstep | --speed X] [--duration S]
[--rerun FILE.rrd]``: the simulator on its own Zenoh session.

Prints READY once it serves its robots' topics and, when the run ends (its --duration
is over, or SIGINT/SIGTERM), a summary: scans published and, per robot, collisions,
waypoints reached and whether the route was completed. A mistake in an option or in the
world file is one ``error:`` line and exit code 2.
"""

from __future__ import annotations

import contextlib
import logging
import signal
from pathlib import Path
from typing import Annotated

import anyio
import typer
from rap_sdk import FabricError, ZenohConfig, ZenohFabric
from rap_sdk.entry import MetricsOpt, check_endpoints, check_system, fail, run_cli, setup_logging
from rap_sdk.metrics import RuntimeCollector, check_metrics_option, start_metrics

from .config import SimConfig, SimConfigError
from .service import RunSummary, open_service
from .viz import RerunFileError
from .world import WorldError, WorldSpec, find_world, load_world, shipped_worlds

__all__ = ["cli", "main"]

log = logging.getLogger(__name__)

cli = typer.Typer(add_completion=False, help=__doc__)


@cli.command()
def main(
    world: Annotated[
        str,
        typer.Option(help=f"A shipped world ({', '.join(shipped_worlds())}) or a world file."),
    ] = "default",
    system: Annotated[str, typer.Option(help="System name on the fabric.")] = "rap",
    name: Annotated[
        str,
        typer.Option(
            help="Its node name on the fabric (a system model's component gives its own)."
        ),
    ] = "sim_world",
    lockstep: Annotated[
        bool, typer.Option("--lockstep", help="As fast as possible (else real time).")
    ] = False,
    speed: Annotated[float, typer.Option(help="Real-time factor without --lockstep.")] = 1.0,
    duration: Annotated[
        float | None, typer.Option(help="Seconds of sim time (default: until stopped).")
    ] = None,
    listen: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to listen on (repeatable).")
    ] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect to (repeatable).")
    ] = None,
    rerun: Annotated[Path | None, typer.Option(help="Write a Rerun recording (.rrd).")] = None,
    log_level: Annotated[str, typer.Option(help="DEBUG, INFO, WARNING or ERROR.")] = "INFO",
    metrics: MetricsOpt = None,
) -> None:
    """Simulate the world and serve its robots' topics. Prints READY once serving, and a
    summary (scans published; per robot collisions and waypoints reached) at the end.

    Example: python -m sim_world --world occlusion --system demo --metrics 127.0.0.1:9465"""
    setup_logging(log_level)
    metrics = check_metrics_option(metrics)
    check_system(system)
    listen_on = check_endpoints("--listen", listen) or ["tcp/127.0.0.1:0"]
    connect_to = check_endpoints("--connect", connect)
    try:
        config = SimConfig(
            world=world,
            system=system,
            name=name,
            lockstep=lockstep,
            speed=speed,
            duration=duration,
            rerun=None if rerun is None else str(rerun),
        )
    except SimConfigError as exc:
        raise fail(f"--{exc.field.replace('_', '-')} {exc.value!r}: {exc.problem}") from None
    if rerun is not None:
        _check_recording_path(rerun)
    try:
        spec = load_world(find_world(world))
    except WorldError as exc:
        raise fail(str(exc)) from None
    zconf = ZenohConfig(listen=listen_on, connect=connect_to)
    try:
        summary = anyio.run(_serve, config, spec, zconf, metrics)
    except RerunFileError as exc:
        raise fail(f"--rerun {exc}") from None
    print(summary.render(), flush=True)


def _check_recording_path(path: Path) -> None:
    if path.is_dir():
        raise fail(f"--rerun {path}: is a directory - give a file path, e.g. {path / 'sim.rrd'}")
    if not path.parent.is_dir():
        raise fail(
            f"--rerun {path}: the directory {path.parent} does not exist - create it or "
            "give a path in an existing directory"
        )


async def _serve(
    config: SimConfig, world: WorldSpec, zconf: ZenohConfig, metrics: str | None = None
) -> RunSummary:
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with contextlib.AsyncExitStack() as stack:
            try:
                fabric = await stack.enter_async_context(ZenohFabric(zconf))
            except FabricError as exc:
                raise fail(
                    f"{exc} - check --listen and --connect (is the port already in use?)"
                ) from None
            service = await stack.enter_async_context(
                open_service(config, fabric=fabric, world=world)
            )
            log.info(
                "simulating %d robot(s) of world %r, %s",
                len(service.sim.robots),
                config.world,
                "lockstep" if config.lockstep else f"real time x{config.speed:g}",
            )
            # served from a daemon thread of its own until the process ends
            start_metrics(
                metrics,
                [
                    RuntimeCollector(
                        lambda: [rt] if (rt := service.runtime) else [], system=config.system
                    )
                ],
                what="sim_world",
            )
            print("READY", flush=True)
            async with anyio.create_task_group() as tg:

                async def stop_on_signal() -> None:
                    async for signum in signals:
                        log.info("signal %s: stopping at sim time %.2f s", signum, service.sim.t)
                        break
                    tg.cancel_scope.cancel()

                tg.start_soon(stop_on_signal)
                await service.finished.wait()
                tg.cancel_scope.cancel()
            summary = service.summary()
    return summary


if __name__ == "__main__":
    run_cli(cli)
