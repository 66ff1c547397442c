"""The admin verbs of a running component (rap_sdk.admin), called over the fabric as an
operator does: status, config get/set, pause/resume, swap under load (no event lost,
none handled twice, the state handed over). Snapshot, restore and a restart from a
snapshot, through knowledge, are in tests/test_admin_knowledge.py (they need the
knowledge service)."""

from __future__ import annotations

import importlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_schemas import keys
from rap_schemas.admin import ComponentState, ComponentSwap, ConfigRequest
from rap_sdk import Context, Node, NodeGroup
from rap_sdk.admin import call
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

SYSTEM = "admin"


@pytest.fixture
def nodes(monkeypatch: pytest.MonkeyPatch) -> Any:
    """The test's node module, importable by name as a swap target is."""
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    mod = importlib.import_module("admin_nodes")
    for v in mod.HANDLED.values():
        v.clear()
    return mod


@pytest.fixture(params=["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def harness(request: pytest.FixtureRequest) -> AsyncIterator[Harness]:
    async with Harness(system=SYSTEM, fabric=request.param, timeout=10) as h:
        yield h


async def _wait(pred: Any, what: str, timeout: float = 10.0) -> None:
    with anyio.fail_after(timeout):
        while not pred():  # noqa: ASYNC110 (polls plain lists the nodes append to)
            await anyio.sleep(0.01)


async def test_status_lists_every_component_with_its_state_and_counts(
    harness: Harness, nodes: Any
) -> None:
    group: NodeGroup = await harness.start(nodes.v1())
    group["counter"].compute_node = "robot"
    for i in range(5):
        await harness.emit("tick", nodes.Tick(n=i))
    await _wait(lambda: len(nodes.HANDLED["v1"]) == 5, "5 handled")
    (reply,) = await call(harness.fabric, SYSTEM, "*", "status")
    assert reply.ok, reply.message
    st = reply.status
    assert st is not None
    assert (st.name, st.stage, st.compute_node) == ("counter", "monitor", "robot")
    assert st.state is ComponentState.IDLE
    assert st.handled == 5
    assert st.implementation == "admin_nodes:v1"
    assert st.last_cycle
    assert st.last_call > 0
    assert st.p99_ms >= st.p50_ms > 0


async def test_config_set_is_validated_and_a_bad_value_keeps_the_old_config(
    harness: Harness, nodes: Any
) -> None:
    await harness.start(nodes.v1())
    (got,) = await call(harness.fabric, SYSTEM, "counter", "config")
    assert got.ok
    assert got.config == {"step": 1, "label": "a", "limit": 10.0}
    (bad,) = await call(
        harness.fabric, SYSTEM, "counter", "config", ConfigRequest(values={"step": "two"})
    )
    assert not bad.ok
    assert bad.path == "$.step", bad.message
    assert "unchanged" in bad.message
    (unknown,) = await call(
        harness.fabric, SYSTEM, "counter", "config", ConfigRequest(values={"stpe": 2})
    )
    assert not unknown.ok
    assert unknown.path == "$.stpe"
    assert "step" in unknown.message
    (ok,) = await call(
        harness.fabric, SYSTEM, "counter", "config", ConfigRequest(values={"step": 10})
    )
    assert ok.ok
    assert ok.config is not None
    assert ok.config["step"] == 10
    await harness.emit("tick", nodes.Tick(n=1))
    await _wait(lambda: nodes.LAST["v1"].count == 10, "the new step applied")


async def test_pause_holds_input_and_resume_handles_it_in_order(
    harness: Harness, nodes: Any
) -> None:
    await harness.start(nodes.v1())
    (paused,) = await call(harness.fabric, SYSTEM, "counter", "pause")
    assert paused.ok
    assert paused.status is not None
    assert paused.status.state is ComponentState.PAUSED
    assert "inboxes" in paused.status.paused_policy
    for i in range(20):
        await harness.emit("tick", nodes.Tick(n=i))
    await anyio.sleep(0.3)
    assert nodes.HANDLED["v1"] == []  # nothing handled while paused
    (st,) = await call(harness.fabric, SYSTEM, "counter", "status")
    assert st.status is not None
    assert st.status.inbox >= 19
    (again,) = await call(harness.fabric, SYSTEM, "counter", "pause")
    assert again.ok
    assert again.message == "was paused already"
    (resumed,) = await call(harness.fabric, SYSTEM, "counter", "resume")
    assert resumed.ok
    await _wait(lambda: len(nodes.HANDLED["v1"]) == 20, "what waited handled")
    assert nodes.HANDLED["v1"] == list(range(20))


async def test_swap_under_load_loses_nothing_handles_nothing_twice_and_hands_state_over(
    harness: Harness, nodes: Any
) -> None:
    group = await harness.start(nodes.v1())
    swapped_at: list[int] = []
    sent = 0

    async def load() -> None:
        # events keep coming before, during and for 1000 events after the swap
        nonlocal sent
        while not swapped_at or sent < swapped_at[0] + 1000:
            await harness.emit("tick", nodes.Tick(n=sent))
            sent += 1
            if sent % 20 == 0:
                await anyio.sleep(0.001)  # let the swap's query in while events keep coming

    async def swap() -> None:
        await _wait(lambda: len(nodes.HANDLED["v1"]) >= 500, "load under way")
        (reply,) = await call(
            harness.fabric, SYSTEM, "counter", "swap", ComponentSwap(target="admin_nodes:v2")
        )
        assert reply.ok, reply.message
        swapped_at.append(sent)

    async with anyio.create_task_group() as tg:
        tg.start_soon(load)
        tg.start_soon(swap)
    n_events = sent
    v1, v2 = nodes.HANDLED["v1"], nodes.HANDLED["v2"]
    await _wait(lambda: len(v1) + len(v2) >= n_events, "every event handled", 30)
    await anyio.sleep(0.2)  # anything handled twice would show up now
    assert swapped_at, "the swap happened mid-load"
    assert v2, "v2 handled events"
    assert sorted(v1 + v2) == list(range(n_events)), (
        f"lost: {sorted(set(range(n_events)) - set(v1 + v2))[:10]}, "
        f"twice: {len(v1) + len(v2) - len(set(v1 + v2))}"
    )
    assert max(v1) < min(v2), "v1 handled something after v2 took over"
    assert nodes.LAST["v2"].count == n_events  # v2 went on counting from v1's state
    st = group["counter"]
    assert st.swaps == 1
    assert st.node.implementation == "admin_nodes:v2"
    assert st.stats.dropped == 0


async def test_swap_is_refused_when_the_inputs_differ_and_the_old_one_keeps_running(
    harness: Harness, nodes: Any
) -> None:
    await harness.start(nodes.v1())
    (reply,) = await call(
        harness.fabric, SYSTEM, "counter", "swap", ComponentSwap(target="admin_nodes:other_inputs")
    )
    assert not reply.ok
    assert "event/tick" in reply.message
    assert "event/tock" in reply.message
    (missing,) = await call(
        harness.fabric, SYSTEM, "counter", "swap", ComponentSwap(target="no_such_module:x")
    )
    assert not missing.ok
    assert "cannot import" in missing.message
    await harness.emit("tick", nodes.Tick(n=7))
    await _wait(lambda: nodes.HANDLED["v1"] == [7], "v1 still handles")


async def test_bad_requests_and_unknown_verbs_are_refused_with_a_reason(
    harness: Harness, nodes: Any
) -> None:
    await harness.start(nodes.v1())
    replies = await harness.fabric.query(keys.admin(SYSTEM, "counter", "config"), b"{not json")
    assert len(replies) == 1
    from rap_sdk.admin import _reply_decoder

    bad = _reply_decoder.decode(replies[0].payload)
    assert not bad.ok
    assert "bad request" in bad.message
    (unknown,) = await call(harness.fabric, SYSTEM, "counter", "explode")
    assert not unknown.ok
    assert "status" in unknown.message
    assert await call(harness.fabric, SYSTEM, "nobody", "status", timeout=0.5) == []


async def test_restart_takes_the_token_down_and_up_and_keeps_the_state(
    harness: Harness, nodes: Any
) -> None:
    group = await harness.start(nodes.v1())
    for i in range(3):
        await harness.emit("tick", nodes.Tick(n=i))
    await _wait(lambda: len(nodes.HANDLED["v1"]) == 3, "3 handled")
    with harness.fabric.watch_liveliness(keys.alive(SYSTEM, "counter")) as watch:
        with anyio.fail_after(5):
            assert (await watch.get()).alive  # as it is, before the restart
        (reply,) = await call(harness.fabric, SYSTEM, "counter", "restart", timeout=10)
        assert reply.ok, reply.message
        with anyio.fail_after(5):
            changes = [await watch.get(), await watch.get()]
    assert [c.alive for c in changes] == [False, True]  # down, then up
    rt = group["counter"]
    assert rt.restarts == 1
    # a fresh instance from the factory, with the count it had (no snapshot kept)
    assert nodes.LAST["v1"].count == 3
    assert rt.node is nodes.LAST["v1"].node
    await harness.emit("tick", nodes.Tick(n=3))
    await _wait(lambda: nodes.LAST["v1"].count == 4, "the fresh instance handles")


async def test_after_a_swap_local_senders_reach_the_new_implementation(
    harness: Harness, nodes: Any
) -> None:
    group = await harness.start(nodes.source(), nodes.v1())
    for i in range(3):
        await harness.emit("go", nodes.Tick(n=i))
    await _wait(lambda: len(nodes.HANDLED["v1"]) == 3, "v1 handles the source's ticks")
    await group["counter"].swap(nodes.v2())
    for i in range(3, 6):
        await harness.emit("go", nodes.Tick(n=i))
    await _wait(lambda: len(nodes.HANDLED["v2"]) == 3, "v2 handles them after the swap")
    assert nodes.HANDLED["v1"] == [0, 1, 2]
    assert nodes.HANDLED["v2"] == [3, 4, 5]
    assert nodes.LAST["v2"].count == 6


async def test_status_answers_while_a_pause_waits_for_a_long_handler(nodes: Any) -> None:
    slow = Node("slow", stage="monitor")
    release = anyio.Event()

    @slow.on_event("tick", type=nodes.Tick)
    async def on_tick(ctx: Context) -> None:
        await release.wait()

    async with Harness(system=SYSTEM, timeout=10) as h:
        group = await h.start(slow)
        await h.emit("tick", nodes.Tick(n=1))
        await _wait(lambda: group["slow"].busy and group["slow"].inbox_depth == 0, "running")
        async with anyio.create_task_group() as tg:
            replies: list[Any] = []

            async def pause() -> None:
                replies.extend(await call(h.fabric, SYSTEM, "slow", "pause", timeout=10))

            tg.start_soon(pause)
            await anyio.sleep(0.2)
            with anyio.fail_after(2):  # not behind the pause
                (st,) = await call(h.fabric, SYSTEM, "slow", "status")
            assert st.status is not None
            assert st.status.state is ComponentState.ACTIVE
            release.set()
        (paused,) = replies
        assert paused.ok
        assert paused.status is not None
        assert paused.status.state is ComponentState.PAUSED
