"""Nodes the admin tests swap between: a counter of numbered events, in two versions.

Each records every number it handles in ``HANDLED`` (by implementation) and keeps its
count as state, so a test can tell that no event was lost or handled twice across a
swap, and that the state was handed over."""

from __future__ import annotations

import msgspec
from rap_schemas import Message
from rap_sdk import Context, Node


class Tick(Message, frozen=True):
    TYPE = "test.Tick/1"
    n: int


class CounterConfig(msgspec.Struct):
    step: int = 1
    label: str = "a"
    limit: float = 10.0


HANDLED: dict[str, list[int]] = {"v1": [], "v2": []}


class _Counter:
    def __init__(self, version: str) -> None:
        self.version = version
        self.count = 0
        node = Node("counter", stage="monitor", config=CounterConfig())
        self.node = node
        node.implementation = f"admin_nodes:{version}"

        @node.on_event("tick")
        async def on_tick(ctx: Context, tick: Tick) -> None:
            HANDLED[self.version].append(tick.n)
            self.count += ctx.config.step

        @node.on_snapshot
        def snapshot() -> int:
            return self.count

        @node.on_restore
        def restore(state: int) -> None:
            self.count = state


LAST: dict[str, _Counter] = {}


def v1() -> Node:
    c = LAST["v1"] = _Counter("v1")
    return c.node


def v2() -> Node:
    c = LAST["v2"] = _Counter("v2")
    return c.node


def other_inputs() -> Node:
    node = Node("counter", stage="monitor")

    @node.on_event("tock")
    async def on_tock(ctx: Context, tick: Tick) -> None:
        return None

    return node


def source() -> Node:
    """Sends a ``tick`` for every ``go`` it gets: a local sender (direct dispatch)."""
    node = Node("source", stage="monitor")

    @node.on_event("go")
    async def on_go(ctx: Context, go: Tick) -> None:
        await ctx.emit("tick", Tick(n=go.n))

    return node
