"""Snapshots kept in knowledge: ``snapshot`` writes a component's state as a versioned
key, ``restore`` puts back the latest or a given version, ``restart --from-snapshot``
restarts from the latest, a plain ``restart`` keeps the state it has; with the knowledge
service on the same fabric, called over it as an operator does."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import anyio
import pytest
from knowledge import KnowledgeConfig, open_service
from rap_schemas.admin import RestartRequest, RestoreRequest, snapshot_key
from rap_sdk.admin import call
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

SYSTEM = "snap"
NODES = Path(__file__).resolve().parents[1] / "libs/rap_sdk/tests"


@pytest.fixture
def nodes(monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.syspath_prepend(str(NODES))
    mod = importlib.import_module("admin_nodes")
    for v in mod.HANDLED.values():
        v.clear()
    return mod


async def _until(pred: Callable[[], bool]) -> None:
    with anyio.fail_after(10):
        while not pred():  # noqa: ASYNC110 (polls a counter the node updates)
            await anyio.sleep(0.01)


async def test_snapshots_in_knowledge_restore_and_restart_from_them(nodes: Any) -> None:
    async with Harness(system=SYSTEM, timeout=10) as h:
        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))
        await h.start(nodes.v1())
        counter = nodes.LAST["v1"]

        async def ticks(n: int) -> None:
            target = counter.count + n
            for i in range(n):
                await h.emit("tick", nodes.Tick(n=i))
            await _until(lambda: counter.count == target)

        async def verb(name: str, request: Any = None) -> Any:
            (reply,) = await call(h.fabric, SYSTEM, "counter", name, request, timeout=10)
            assert reply.ok, reply.message
            return reply

        await ticks(3)
        first = (await verb("snapshot")).snapshot
        assert first is not None
        assert first.key == snapshot_key("counter")
        await ticks(2)
        second = (await verb("snapshot")).snapshot
        assert second is not None
        assert second.version > first.version
        await ticks(4)
        assert counter.count == 9

        await verb("restore", RestoreRequest(version=first.version))
        assert counter.count == 3
        await verb("restore")  # the latest
        assert counter.count == 5

        await ticks(1)
        await verb("restart")  # keeps the state it has
        fresh = nodes.LAST["v1"]
        assert fresh is not counter  # a new instance from the factory
        assert fresh.count == 6
        counter = fresh
        await verb("restart", RestartRequest(from_snapshot=True))
        assert nodes.LAST["v1"].count == 5

        (missing,) = await call(
            h.fabric, SYSTEM, "counter", "restore", RestoreRequest(version=1), timeout=10
        )
        assert not missing.ok
        assert "no snapshot of counter with version 1" in missing.message
