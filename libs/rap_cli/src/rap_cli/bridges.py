"""The bridges of a model: ports with a ``bridge:`` (docs/bridges.md), as ``rap up``
runs them.

Which way a bridge carries messages follows from whose port it is:

- a port of a component RAP runs (a stage, a ``run:`` command) lives on the fabric and
  is mirrored outside: an ``out`` port's messages are sent out over the protocol, an
  ``in`` port's messages arrive from the protocol and are published on its key;
- a port of an ``external: true`` component that RAP does not start (no ``run:``: a
  ROS 2 node, a PLC, a dashboard) lives on the protocol: its ``out`` port's messages
  come in from the protocol onto the fabric, and what the fabric sends its ``in`` port
  goes out over the protocol.

The fabric key is the port's channel (the same key the generated code and the access
control rules use). Each compute node runs the bridges of the components mapped to it
in one process, ``bridges`` (``python -m rap_cli.bridges MODEL --node NODE``), which
``rap up`` supervises and ``rap generate`` writes into the node's compose file.
"""

from __future__ import annotations

import importlib
import logging
import signal
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import anyio
import typer
from rap_schemas import DeploymentPlan, PlanDocument, PlanError, keys, load_plan
from rap_schemas.bridge import BridgeSpec
from rap_schemas.catalog import registered
from rap_schemas.message import Message
from rap_sdk import FabricError, ZenohConfig, ZenohFabric
from rap_sdk.entry import (
    EntryError,
    LogFileOpt,
    MetricsOpt,
    check_system,
    fail,
    leaf,
    run_cli,
    setup_logging,
)
from rap_sdk.logs import LogContext, open_file_log, publish_logs
from rap_sdk.metrics import check_metrics_option, start_metrics

from .generate.wiring import channels

if TYPE_CHECKING:
    from rap_bridges import Bridge
    from rap_sdk.fabric import Fabric

__all__ = ["PortBridge", "bridges_on", "message_class", "port_bridges"]

PROCESS = "bridges"
"""The name of the process that runs a compute node's bridges."""


@dataclass(frozen=True, slots=True)
class PortBridge:
    """One port's bridge, resolved against the model."""

    component: str
    port: str
    node: str | None
    spec: BridgeSpec
    key: str
    """The fabric key of the port's channel."""
    direction: Literal["in", "out"]
    """``out``: fabric -> protocol; ``in``: protocol -> fabric."""
    type: str | None
    """The port's type as the model writes it (a model message or a RAP wire type)."""

    @property
    def name(self) -> str:
        """``component.port``: the bridge's name in logs, metrics and envelopes."""
        return f"{self.component}.{self.port}"


def port_bridges(plan: DeploymentPlan, system: str | None = None) -> list[PortBridge]:
    """Every bridge of ``plan``, in model order (``system`` overrides the model's system
    name in the keys). A port whose direction is ``in-out`` has none (``rap check`` says
    so: one bridge per direction)."""
    chans = channels(plan)
    s = system or plan.system
    out: list[PortBridge] = []
    for cname, comp in plan.components.items():
        for pname, port in comp.ports.items():
            spec = port.bridge
            if spec is None or port.direction == "in-out":
                continue
            ch = chans[(cname, pname)]
            key = keys.data(s, ch.key) if ch.family == "data" else keys.event(s, ch.key)
            outward = port.direction == "out"
            if comp.external and not comp.run:  # it lives on the protocol: the other way
                outward = not outward
            out.append(
                PortBridge(
                    component=cname,
                    port=pname,
                    node=comp.node,
                    spec=spec,
                    key=key,
                    direction="out" if outward else "in",
                    type=port.type,
                )
            )
    return out


def bridges_on(plan: DeploymentPlan, node: str, system: str | None = None) -> list[PortBridge]:
    """The bridges compute node ``node`` runs."""
    return [b for b in port_bridges(plan, system) if b.node == node]


def _packages(plan: DeploymentPlan) -> list[str]:
    """The generated packages the model's components come from (``pkg.nodes.x``)."""
    found: list[str] = []
    for comp in plan.components.values():
        module = (comp.module or "").partition(":")[0]
        pkg, sep, _ = module.partition(".nodes.")
        if sep and pkg not in found:
            found.append(pkg)
    return found


def message_class(plan: DeploymentPlan, type_name: str | None) -> type[Message] | None:
    """The message class of a port's type: a RAP wire type (``rap.LaserScan/2``), or a
    message of the model that ``rap generate`` wrote (its package's ``messages`` module
    registers it, under the wire type ``<package>.<Class>/1``, when imported). None: no
    type, or one whose class is not importable (only format ``envelope`` can carry it:
    the envelope names its own type)."""
    if type_name is None:
        return None
    known = registered()
    if type_name in known:
        return known[type_name]
    if type_name not in plan.messages:
        return None
    from .generate.messages import MessageNames

    for pkg in _packages(plan):
        try:
            importlib.import_module(f"{pkg}.messages")
        except ImportError:
            continue
        wire = f"{pkg}.{MessageNames.of(plan, pkg).classes[type_name]}/1"
        cls = registered().get(wire)
        if cls is not None:
            return cls
    return None


# -- the process: python -m rap_cli.bridges MODEL --node NODE ----------------------------

cli = typer.Typer(add_completion=False, help=__doc__, rich_markup_mode=None)
log = logging.getLogger("rap_cli.bridges")


@cli.command()
def main(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="The system model (YAML).")],
    node: Annotated[str, typer.Option("--node", help="The compute node whose bridges to run.")],
    system: Annotated[str | None, typer.Option(help="System name (default: the model's).")] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
    metrics: MetricsOpt = None,
    log_file: LogFileOpt = None,
) -> None:
    """Run the bridges of a compute node: every port with a ``bridge:`` of the components
    mapped to it. A model that cannot be used exits with code 2.

    Example: python -m rap_cli.bridges model.yaml --node robot --metrics 127.0.0.1:9465"""
    setup_logging(log_level)
    metrics = check_metrics_option(metrics)
    if system is not None:
        check_system(system)
    try:
        doc = load_plan(model)
    except PlanError as exc:
        raise fail(str(exc)) from None
    plan = doc.plan
    if node not in plan.compute_nodes:
        raise fail(
            f"{model}: compute node {node!r} is not in the model; its compute nodes are: "
            f"{', '.join(plan.compute_nodes)}"
        )
    todo = bridges_on(plan, node, system)
    if not todo:
        raise fail(
            f"{doc.where(('compute_nodes', node), key=True)}: no port of a component on "
            f"{node!r} has a bridge - add 'bridge:' to a port (docs/bridges.md)"
        )
    zconf = ZenohConfig()  # rap up's node config (RAP_ZENOH_CONFIG) is laid over it
    fabric = ZenohFabric(zconf)  # opened in the event loop; the bridges take it now
    bridges = _make(doc, todo, fabric)  # every link's settings checked before starting
    logs = LogContext(system=system or plan.system, compute_node=node, process=PROCESS)
    open_file_log(log_file, logs)
    try:
        anyio.run(partial(_serve, bridges, fabric, logs=logs, metrics=metrics))
    except (FabricError, BaseExceptionGroup) as exc:
        inner = leaf(exc)
        if isinstance(inner, FabricError):
            raise fail(str(inner), 1) from None
        if isinstance(inner, EntryError):
            raise inner from None
        raise


def _make(doc: PlanDocument, todo: list[PortBridge], fabric: Fabric) -> list[Bridge]:
    """The bridges, built (nothing connects yet): a format that needs a message class it
    cannot have, or settings a link refuses, are errors at the port's bridge."""
    from rap_bridges import Bridge

    out = []
    for b in todo:
        at = ("components", b.component, "ports", b.port, "bridge")
        cls = message_class(doc.plan, b.type)
        if b.spec.format != "envelope" and cls is None:
            what = (
                "the port has no type"
                if b.type is None
                else f"its type {b.type!r} is not a RAP wire type and no generated package "
                "of the model defines it (run rap generate, and put the package on PYTHONPATH)"
            )
            raise fail(
                f"{doc.where((*at, 'format'))}: format {b.spec.format} needs the port's "
                f"message type, but {what} - give the port a type, or use format: envelope"
            )
        try:
            bridge = Bridge(b.name, b.spec, fabric, b.key, direction=b.direction, message=cls)
        except ValueError as exc:  # what only the link knows (the direction, the type)
            raise fail(f"{doc.where(at)}: bridge {b.name} ({b.direction}): {exc}") from None
        out.append(bridge)
    return out


async def _serve(
    bridges: list[Bridge], fabric: ZenohFabric, *, logs: LogContext, metrics: str | None
) -> None:
    from rap_bridges.metrics import BridgeCollector

    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with (
            fabric,
            publish_logs(fabric, logs, node=f"{PROCESS}-{logs.compute_node}"),
            anyio.create_task_group() as tg,
        ):
            for bridge in bridges:
                await tg.start(bridge.run)
                log.info(
                    "bridge %s: %s %s %s (%s, qos %d)",
                    bridge.name,
                    bridge.key,
                    "->" if bridge.direction == "out" else "<-",
                    bridge.link.where,
                    bridge.spec.format,
                    bridge.spec.qos,
                )
            start_metrics(
                metrics,
                [BridgeCollector(bridges, system=logs.system, compute_node=logs.compute_node)],
                what="bridges",
            )
            log.info("ready: %d bridge(s)", len(bridges))
            async for signum in signals:
                log.info("received %s; stopping", signal.Signals(signum).name)
                break
            tg.cancel_scope.cancel()


if __name__ == "__main__":
    run_cli(cli)
