"""``python -m sim_world --world FILE [--lockstep] [--duration S] [--rerun out.rrd]``:
the simulator on its own Zenoh session."""

from __future__ import annotations

import logging
import signal
from pathlib import Path
from typing import Annotated

import anyio
import typer
from rap_sdk import ZenohConfig, ZenohFabric

from .service import SimService
from .sim import Simulation
from .viz import RerunLog
from .world import WorldError, default_world_path, load_world

cli = typer.Typer(add_completion=False, help=__doc__)


@cli.command()
def main(
    world: Annotated[Path | None, typer.Option(help="World YAML (default: shipped).")] = None,
    system: Annotated[str, typer.Option(help="System name on the fabric.")] = "rap",
    lockstep: Annotated[bool, typer.Option(help="As fast as possible (else real time).")] = False,
    speed: Annotated[float, typer.Option(help="Real-time factor without --lockstep.")] = 1.0,
    duration: Annotated[float | None, typer.Option(help="Sim seconds (default: forever).")] = None,
    listen: Annotated[list[str] | None, typer.Option(help="Zenoh listen endpoint.")] = None,
    connect: Annotated[list[str] | None, typer.Option(help="Zenoh endpoint to connect.")] = None,
    rerun: Annotated[Path | None, typer.Option(help="Log to this .rrd file.")] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
) -> None:
    """Simulate the world and serve its robots' topics."""
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        spec = load_world(world or default_world_path())
    except WorldError as exc:
        raise typer.BadParameter(str(exc), param_hint="--world") from None
    if not lockstep and speed <= 0:
        raise typer.BadParameter(f"--speed must be > 0, got {speed}", param_hint="--speed")
    zconf = ZenohConfig(listen=listen or ["tcp/127.0.0.1:0"], connect=connect or [])
    viz = RerunLog(spec, path=str(rerun)) if rerun is not None else None
    try:
        anyio.run(
            _serve, Simulation(spec), zconf, system, None if lockstep else speed, duration, viz
        )
    finally:
        if viz is not None:
            viz.close()


async def _serve(
    sim: Simulation,
    zconf: ZenohConfig,
    system: str,
    factor: float | None,
    duration: float | None,
    viz: RerunLog | None,
) -> None:
    log = logging.getLogger("sim_world")
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with ZenohFabric(zconf) as fabric, anyio.create_task_group() as tg:
            service = SimService(sim, fabric, system=system, realtime_factor=factor, rerun=viz)

            async def simulate() -> None:
                await service.run(duration)
                tg.cancel_scope.cancel()

            tg.start_soon(simulate)
            log.info(
                "simulating %d robot(s), %s",
                len(sim.robots),
                "lockstep" if factor is None else f"real time x{factor}",
            )
            print("READY", flush=True)
            async for _ in signals:
                log.info("stopping at sim time %.2f s", sim.t)
                tg.cancel_scope.cancel()
                break


if __name__ == "__main__":
    cli()
