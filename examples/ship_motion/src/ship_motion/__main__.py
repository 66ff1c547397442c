"""``python -m ship_motion [--seed N] [--speed X | --lockstep] [--duration S]``: the ship
simulator (the model's external component ``simulator``) on its own Zenoh session.

It publishes ``ship/pose`` and ``ship/weather`` every second of sim time, at ``--speed``
times real time (or as fast as it can with ``--lockstep``, which has no loop to wait for
here: use ``make eval-ship`` for lockstep runs with the loop). Under ``rap up``, make it a
client of the ship's router: ``RAP_ZENOH_CONFIG=.rap/ship_motion/vessel/zenoh-client.json5``
(the run directory beside the model).

The ship arrives with a data-driven model: unless ``--no-model``, when the model store has
no pinned version of ``ship_motion`` it trains one on a calm run of its own and stores and
pins it. Prints READY once it publishes; a mistake in an option is one ``error:`` line and
exit code 2.
"""

from __future__ import annotations

import contextlib
import logging
import signal
from typing import Annotated

import anyio
import anyio.to_thread
import typer
from rap_sdk import FabricError, ZenohConfig, ZenohFabric
from rap_sdk.entry import check_endpoints, check_system, fail, run_cli, setup_logging
from rap_sdk.knowledge import KnowledgeClient, KnowledgeError

from .eval import initial_model, scenario
from .loop import MODEL_NAME
from .physics import ScenarioSpec
from .service import ShipService

__all__ = ["cli", "main"]

log = logging.getLogger("ship_motion")

cli = typer.Typer(add_completion=False, help=__doc__)


@cli.command()
def main(
    seed: Annotated[int, typer.Option(help="Seeds the route and the weather front.")] = 1,
    onset: Annotated[float, typer.Option(help="Sim seconds of calm before the front.")] = 600.0,
    duration: Annotated[float, typer.Option(help="Sim seconds to run.", min=1)] = 2400.0,
    speed: Annotated[float, typer.Option(help="Real-time factor.")] = 1.0,
    lockstep: Annotated[bool, typer.Option("--lockstep", help="As fast as possible.")] = False,
    system: Annotated[str, typer.Option(help="System name on the fabric.")] = "ship_motion",
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect to (repeatable).")
    ] = None,
    model: Annotated[
        bool, typer.Option("--model/--no-model", help="Store and pin a first model if none is.")
    ] = True,
    log_level: Annotated[str, typer.Option(help="DEBUG, INFO, WARNING or ERROR.")] = "INFO",
) -> None:
    """Simulate the ship and publish its pose and weather."""
    setup_logging(log_level)
    check_system(system)
    if not lockstep and not 0 < speed <= 10_000:
        raise fail(f"--speed {speed:g}: give a real-time factor above 0 and at most 10000")
    connect_to = check_endpoints("--connect", connect)
    try:
        spec = scenario(seed, onset=onset, duration=duration)
    except ValueError as exc:
        raise fail(f"--onset/--duration: {exc}") from None
    zconf = ZenohConfig(mode="client" if connect_to else "peer", connect=connect_to)
    anyio.run(_serve, spec, zconf, system, None if lockstep else speed, model)


async def _serve(
    spec: ScenarioSpec, zconf: ZenohConfig, system: str, speed: float | None, model: bool
) -> None:
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with contextlib.AsyncExitStack() as stack:
            try:
                fabric = await stack.enter_async_context(ZenohFabric(zconf))
            except FabricError as exc:
                raise fail(f"{exc} - check --connect or RAP_ZENOH_CONFIG") from None
            if model:
                await _first_model(fabric, system, spec.seed)
            service = ShipService(spec, fabric=fabric, system=system, realtime_factor=speed)
            async with anyio.create_task_group() as tg:
                await tg.start(service.run)
                print("READY", flush=True)

                async def stop_on_signal() -> None:
                    async for signum in signals:
                        log.info("%s: stopping", signal.Signals(signum).name)
                        tg.cancel_scope.cancel()
                        return

                tg.start_soon(stop_on_signal)
                await service.finished.wait()
                tg.cancel_scope.cancel()
    log.info("simulated %.0f s of sim time, %d samples", spec.duration_s, len(service.states))


async def _first_model(fabric: ZenohFabric, system: str, seed: int) -> None:
    async with KnowledgeClient(
        fabric=fabric, system=system, writer="simulator", timeout=10.0
    ) as kb:
        try:
            _versions, pinned = await kb.list_models(MODEL_NAME)
            if pinned is not None:
                log.info("the model store pins %s v%d: the ship serves it", MODEL_NAME, pinned)
                return
            log.info("no %s model pinned: training the ship's first one on a calm run", MODEL_NAME)
            data = await anyio.to_thread.run_sync(initial_model, seed)
            meta = await kb.put_model(MODEL_NAME, data, tags={"trained": "calm"})
            await kb.pin_model(MODEL_NAME, meta.version)
        except KnowledgeError as exc:
            raise fail(
                f"cannot reach the model store ({exc}) - is the knowledge service up "
                "(rap up), or pass --no-model"
            ) from None
        log.info("stored and pinned %s v%d", MODEL_NAME, meta.version)


if __name__ == "__main__":
    run_cli(cli)
