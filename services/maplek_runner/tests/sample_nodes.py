"""Tiny Nodes that the runner's tests name in plans, as
``services.maplek_runner.tests.sample_nodes:<attr>`` (importable from the repository
root, which pytest puts on sys.path and the CLI test uses as working directory)."""

from __future__ import annotations

import msgspec
from rap_schemas import LaserScan
from rap_sdk import Context, Node

echo = Node("echo", stage="monitor")


@echo.on_data("ping")
async def on_ping(ctx: Context, scan: LaserScan) -> None:
    await ctx.publish("pong", scan)


class RelayConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    reply: str = "tock"
    """The event emitted for each ``tick``."""
    repeat: int = 1


relay = Node("relay", stage="analyse", config=RelayConfig())


@relay.on_event("tick")
async def on_tick(ctx: Context) -> None:
    for _ in range(ctx.config.repeat):
        await ctx.emit(ctx.config.reply)


silent = Node("silent", stage="plan")

not_a_node = "I am a string"

echo_again = echo
"""The same Node object under a second name."""
