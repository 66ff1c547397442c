"""The checker as a service: a spec, the session that runs it, its transports and sinks,
wired and running for the duration of a block.

    async with ZenohFabric(zconf) as fabric, open_service(
        ServiceConfig(node="trust_stage_order", fabric=FabricConfig(system="tb1")),
        load_spec(Path("stage_order.dsrv")),
        fabric=fabric,
        sinks=[ConsoleSink()],
    ) as service:
        ...                                   # running: inputs in, outputs and verdicts out
        service.session.stats, service.fabric.stats.rejections.by_reason

On entry every part is ready (the console writer and the session started, MQTT and
Redis connected and subscribed, the fabric subscribed and the swap queryable served); on
exit all of it stops. With identities (``verifier=``, or ``RAP_CERTS`` in the
environment) a hot swap, over the fabric, MQTT or Redis, needs an operator's signature
(:mod:`trust_checker.io.auth`); over Redis there is none without identities.
``python -m trust_checker``, bench/trust and the tests all run the checker through here.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass

import anyio
from rap_sdk import Fabric
from rap_sdk.admin import Gate
from rap_sdk.envelope import Clock
from rap_sdk.errors import ConfigError
from rap_sdk.identity import Verifier

from .config import ServiceConfig
from .engine import SpecRunner
from .io.dds import DdsTransport
from .io.fabric import FabricTransport
from .io.mqtt import MqttTransport
from .io.ports import RunnerLike, RunningSink, Sink, SpecLoader
from .io.redis import RedisTransport
from .io.session import Session
from .io.specs import load_text
from .lang import ast

__all__ = ["TrustService", "open_service"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TrustService:
    """A running checker (what :func:`open_service` yields)."""

    config: ServiceConfig
    session: Session
    mqtt: MqttTransport | None
    """The MQTT transport, when ``config.mqtt`` is set."""
    fabric: FabricTransport | None
    """The fabric transport, when ``config.fabric`` is set."""
    redis: RedisTransport | None = None
    """The Redis transport, when ``config.redis`` is set."""
    dds: DdsTransport | None = None
    """The DDS inputs, when ``config.dds`` is set."""

    @property
    def runner(self) -> RunnerLike:
        """The running spec (a new one after each hot swap)."""
        return self.session.runner

    @property
    def rejected(self) -> int:
        """Payloads the transports refused, in all."""
        transports = (self.mqtt, self.redis, self.fabric, self.dds)
        return sum(t.stats.rejections.total for t in transports if t is not None)

    def summary(self) -> str:
        """One line of counts, for the log when the service stops."""
        s = self.session.stats
        return (
            f"{s.ticks} ticks: {s.outputs} outputs, {s.verdicts} verdicts, "
            f"{self.rejected} rejected, {s.input_errors} input errors, "
            f"{s.eval_errors} eval errors, {s.swaps} swaps ({s.swaps_rejected} refused)"
        )


@asynccontextmanager
async def open_service(
    config: ServiceConfig,
    spec: ast.Spec | RunnerLike,
    *,
    fabric: Fabric | None = None,
    sinks: Sequence[Sink] = (),
    loader: SpecLoader = load_text,
    clock: Clock | None = None,
    verifier: Verifier | None = None,
) -> AsyncIterator[TrustService]:
    """Run a checker for the duration of the block (ready on entry).

    ``spec``: a checked spec (run by a :class:`~trust_checker.engine.SpecRunner`), or a
    runner of one's own (tests). ``fabric``: the fabric to run on, required with
    ``config.fabric`` (and only then). ``sinks`` get every tick's outputs before the
    transports do; a sink with a ``run`` task (:class:`~.io.ports.RunningSink`, e.g. the
    console) is started first. ``loader`` parses and checks hot-swapped specs (default:
    :func:`~trust_checker.io.specs.load_text`, which never opens a file); ``clock`` the
    wall clock of tick times. ``verifier``: take hot swaps only from requests an operator
    of its CA signed (default: ``RAP_CERTS``'s CA when it is set; else every swap over
    the fabric and MQTT is taken, and none over Redis). Raises
    :class:`rap_sdk.ConfigError` for a mismatch between ``config`` and ``fabric``."""
    if config.fabric is not None and fabric is None:
        raise ConfigError(
            f"config.fabric is set (system {config.fabric.system!r}) but no fabric was "
            "given - pass fabric=..., or drop config.fabric"
        )
    if config.fabric is None and fabric is not None:
        raise ConfigError(
            "a fabric was given but config.fabric is None - set "
            "config.fabric=FabricConfig(system=...), or do not pass a fabric"
        )
    runner: RunnerLike = SpecRunner(spec) if isinstance(spec, ast.Spec) else spec
    session = Session(
        runner,
        loader=loader,
        sinks=sinks,
        policy=config.policy,
        clock=clock,
        node=config.node,
        capacity=config.capacity,
        explain=config.verdicts and isinstance(runner, SpecRunner),
    )
    gate = Gate(verifier)
    try:
        mqtt = None
        if config.mqtt is not None:
            mqtt = MqttTransport(session, config.mqtt, gate=gate)
        red = None
        if config.redis is not None:
            red = RedisTransport(session, config.redis, gate=gate)
        fab = None
        if config.fabric is not None and fabric is not None:
            fab = FabricTransport(session, config.fabric, fabric=fabric, gate=gate)
        dds = DdsTransport(session, config.dds) if config.dds is not None else None
    except BaseException:
        session.discard()
        raise
    service = TrustService(config, session, mqtt, fab, red, dds)
    async with anyio.create_task_group() as tg:
        for sink in sinks:
            if isinstance(sink, RunningSink):
                await tg.start(sink.run)
        await tg.start(session.run)
        if mqtt is not None:
            await tg.start(mqtt.run)
        if red is not None:
            await tg.start(red.run)
        if fab is not None:
            await tg.start(fab.run)
        if dds is not None:
            await tg.start(dds.run)
        log.info(
            "ready: inputs %s, outputs %s, tick policy %s",
            ", ".join(runner.inputs) or "none",
            ", ".join(runner.outputs) or "none",
            config.tick,
        )
        try:
            yield service
        finally:
            tg.cancel_scope.cancel()
    log.info("stopped after %s", service.summary())
