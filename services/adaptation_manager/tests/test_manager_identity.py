"""The manager of a system whose components have identities (RAP_CERTS): it signs its
status polls with its own identity (a process may read), so it follows every component;
unsigned, it learns nothing and says why. The dashboard's commands are changes: taken
only when the manager signs as an operator."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import pytest
from adaptation_manager import Manager, Registry
from rap_sdk import run_nodes
from rap_sdk.identity import Signer, load_signer
from rap_sdk.testing import Harness

from libs.rap_sdk.tests.certs_support import make_certs
from services.adaptation_manager.tests.loop import Waiter, loop_nodes

pytestmark = pytest.mark.anyio

S = "mgrid"
NAMES = {"monitor", "analysis", "planner", "legitimate", "executor"}


@pytest.fixture
def certs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = make_certs(tmp_path / "certs", {"edge.manager": "process", "alice": "operator"})
    monkeypatch.setenv("RAP_CERTS", str(folder))  # every component checks who asks
    return folder


@contextlib.asynccontextmanager
async def running(signer: Signer | None) -> AsyncIterator[tuple[Manager, Waiter]]:
    async with Harness(system=S, timeout=10) as h:
        await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system=S, compute_node="edge"))
        waiter = Waiter()
        reg = Registry(S, on_change=waiter.hook)
        manager = Manager(
            fabric=h.fabric, system=S, registry=reg, status_interval=0.2, signer=signer
        )
        manager.on_poll = waiter.poke
        async with anyio.create_task_group() as tg:
            await tg.start(manager.run)
            yield manager, waiter
            tg.cancel_scope.cancel()


def answering(manager: Manager) -> set[str]:
    comps = manager.registry.components
    return {n for n in NAMES if n in comps and comps[n].answers}


async def test_signed_polls_follow_every_component(certs: Path) -> None:
    async with running(load_signer(certs, "edge.manager")) as (manager, waiter):
        await waiter.until(lambda: answering(manager) == NAMES)
        comps = manager.registry.components
        assert {comps[n].state for n in NAMES} <= {"idle", "active"}
        # the dashboard's pause is a change: a process may not make it
        result = await manager.command("monitor", "pause")
        assert not result.ok
        assert "'edge.manager' (role process) may not pause monitor" in result.message
        assert comps["monitor"].state != "paused"


async def test_an_operator_identity_may_command(certs: Path) -> None:
    async with running(load_signer(certs, "alice")) as (manager, waiter):
        await waiter.until(lambda: answering(manager) == NAMES)
        result = await manager.command("monitor", "pause")
        assert result.ok, result.message
        assert result.state == "paused"
        assert (await manager.command("monitor", "resume")).ok


async def test_unsigned_polls_are_refused_and_counted(
    certs: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="adaptation_manager")
    async with running(None) as (manager, waiter):
        reg = manager.registry

        def refused() -> Any:
            return reg.metrics.registry.get_sample_value(
                "rap_manager_unreadable_samples_total", {"kind": "admin"}
            )

        await waiter.until(lambda: (refused() or 0) >= 5)
        await waiter.until(lambda: manager.polls >= 3)
        assert answering(manager) == set()
    said = "\n".join(r.getMessage() for r in caplog.records)
    assert "monitor: unsigned request" in said
