"""The manager on a fabric with a real loop (five nodes, a real gate, their admin
queryables): it registers the components with their compute node and state, follows
cycles and plans to the execute stage, answers ``rap trace``, pauses and resumes through
``rap_sdk.admin.call``, sees a component go, and shrugs off bad samples. On MemoryFabric
(in process) and on real Zenoh sessions over loopback."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from typing import Any, Literal

import anyio
import msgspec
import pytest
from adaptation_manager import Manager, Registry, TraceReply
from rap_schemas import StageTrace, keys
from rap_schemas.admin import ComponentState
from rap_sdk import LifecycleError, MemoryFabric, Node, admin, run_nodes
from rap_sdk.fabric import Fabric
from rap_sdk.testing import Harness

from services.adaptation_manager.tests.loop import Waiter, loop_nodes

pytestmark = pytest.mark.anyio

S = "mgr"
STAGES = ["monitor", "analyse", "plan", "legitimate", "execute"]


@contextlib.asynccontextmanager
async def running(
    fabric: Literal["memory", "zenoh"] = "memory", **kw: Any
) -> AsyncIterator[tuple[Harness, Manager, Waiter]]:
    """The loop on compute node ``edge``, and a manager on the harness's fabric."""
    async with Harness(system=S, fabric=fabric, timeout=10) as h:
        await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system=S, compute_node="edge"))
        waiter = Waiter()
        reg = Registry(S, cycle_timeout=kw.pop("cycle_timeout", 5.0), on_change=waiter.hook)
        manager = Manager(fabric=h.fabric, system=S, registry=reg, status_interval=0.2, **kw)
        manager.on_poll = waiter.poke
        async with anyio.create_task_group() as tg:
            await tg.start(manager.run)
            yield h, manager, waiter
            tg.cancel_scope.cancel()


def all_idle(reg: Registry) -> bool:
    names = {"monitor", "analysis", "planner", "legitimate", "executor"}
    comps = reg.components
    return names <= set(comps) and all(
        comps[n].answers and comps[n].state in ("idle", "active") for n in names
    )


async def trace(fabric: Fabric, payload: bytes) -> TraceReply:
    replies = await fabric.query(keys.admin(S, "manager", "trace"), payload, timeout=5.0)
    assert len(replies) == 1, replies
    return msgspec.json.decode(replies[0].payload, type=TraceReply)


@pytest.mark.parametrize("fabric", ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def test_the_manager_follows_a_loop_from_scan_to_execute(
    fabric: Literal["memory", "zenoh"],
) -> None:
    async with running(fabric) as (h, manager, waiter):
        reg = manager.registry
        await waiter.until(lambda: all_idle(reg))
        assert {c.compute_node for c in reg.components.values()} == {"edge"}
        assert reg.components["planner"].stage == "plan"
        env = await h.send(keys.data(S, "scan"))
        await h.expect_data("spin_config")

        def executed() -> bool:
            cyc = reg.cycles.get(env.uid)
            return cyc is not None and reg.cycle_state(cyc)[0] == "executed"

        await waiter.until(executed)
        cyc = reg.cycles[env.uid]
        assert cyc.stages == STAGES
        [plan] = reg.plans.values()
        assert (plan.status, plan.proposer, plan.legitimator, plan.executor) == (
            "executed",
            "planner",
            "legitimate",
            "executor",
        )
        # rap trace: by a prefix, and the latest complete cycle that reached execute
        by_prefix = await trace(h.fabric, env.uid.hex()[:10].encode())
        last = await trace(h.fabric, b'{"last": true, "executed": true}')
        for reply in (by_prefix, last):
            assert reply.ok, reply.message
            assert reply.trace is not None
            steps = reply.trace.steps
            assert [(s.depth, s.node) for s in steps] == [
                (0, "monitor"),
                (1, "analysis"),
                (2, "planner"),
                (3, "legitimate"),
                (4, "executor"),
            ]
            assert steps[-1].sent == [keys.data(S, "spin_config")]
            assert all(s.wait_ms is not None for s in steps[1:])
            assert reply.trace.executed
        nothing = await trace(h.fabric, b"ffff")
        assert not nothing.ok
        assert "no cycle ffff" in nothing.message
        bad = await trace(h.fabric, b"not hex")
        assert "is not hex" in bad.message
        assert (await trace(h.fabric, b'{"cycle": 3}')).message.startswith("bad trace request")


async def test_pause_and_resume_go_through_the_admin_verbs() -> None:
    async with running() as (h, manager, waiter):
        reg = manager.registry
        await waiter.until(lambda: all_idle(reg))
        result = await manager.command("monitor", "pause")
        assert result.ok, result.message
        assert result.state == "paused"
        [status] = await admin.call(h.fabric, S, "monitor", "status")
        assert status.status is not None
        assert status.status.state is ComponentState.PAUSED
        assert reg.components["monitor"].state == "paused"
        # a scan waits while it is paused; resume handles it
        env = await h.send(keys.data(S, "scan"))
        assert (await manager.command("monitor", "resume")).state in ("idle", "active")
        await waiter.until(
            lambda: env.uid in reg.cycles and "monitor" in reg.cycles[env.uid].stages
        )
        refused = await manager.command("monitor", "swap")
        assert not refused.ok
        assert "not one of pause, resume, restart" in refused.message
        nobody = await manager.command("nobody", "pause")
        assert not nobody.ok
        assert "did not answer" in nobody.message
        bad = await manager.command("a/b", "pause")
        assert not bad.ok
        assert "invalid node" in bad.message
        counted = reg.metrics.registry.get_sample_value(
            "rap_manager_admin_calls_total", {"verb": "pause", "result": "ok"}
        )
        assert counted == 1


async def test_a_component_that_stops_is_gone_and_counted() -> None:
    async with running() as (h, manager, waiter):
        reg = manager.registry
        extra = Node("extra", stage="monitor")

        @extra.on_data("other")
        async def noop(ctx: Any) -> None: ...

        async with run_nodes([extra], fabric=h.fabric, system=S, compute_node="robot"):
            await waiter.until(
                lambda: "extra" in reg.components and reg.components["extra"].answers
            )
            assert reg.components["extra"].compute_node == "robot"
        await waiter.until(lambda: reg.components["extra"].state == "gone")
        assert reg.alerts[-1].kind == "gone"
        gone = reg.metrics.registry.get_sample_value(
            "rap_manager_components_gone_total", {"component": "extra"}
        )
        assert gone == 1


async def test_bad_samples_are_counted_and_the_manager_carries_on() -> None:
    async with running() as (h, manager, waiter):
        reg = manager.registry
        for kind in (keys.Kind.TRACE, keys.Kind.EVENT, keys.Kind.LOG, keys.Kind.TRUST):
            name = "x" if kind in (keys.Kind.TRACE, keys.Kind.LOG) else "x/y"
            await h.publish_raw(keys.pattern(S, kind, name), b"\xc1 not msgpack")
        # a well-formed envelope whose body does not fit its type
        await h.send(keys.trace(S, "x"), None)
        await h.send(keys.event(S, "new-plan"), None)
        env = await h.send(keys.data(S, "scan"))
        await waiter.until(lambda: env.uid in reg.cycles and reg.cycles[env.uid].executed)

        def unreadable(kind: str) -> float:
            value = reg.metrics.registry.get_sample_value(
                "rap_manager_unreadable_samples_total", {"kind": kind}
            )
            return value or 0.0

        assert unreadable("trace") == 1
        assert unreadable("log") == 1
        assert unreadable("trust") == 1
        assert unreadable("event") == 1  # the garbage; an Empty new-plan is no proposal


async def test_bodies_msgspec_cannot_read_as_text_or_nest_too_deep_are_counted() -> None:
    # a map key that is not UTF-8 raises UnicodeDecodeError, not a msgspec error; deep
    # nesting raises RecursionError: both are bad input, counted, never the manager's end
    async with running() as (h, manager, waiter):
        reg = manager.registry
        bodies = (b"\x81\xa4node\xa2\xff\xfe", b"\x91" * 200_000 + b"\xc0")
        for body in bodies:
            payload, _ = h.sealer.seal_message(keys.trace(S, "x"), None)
            env = msgspec.msgpack.decode(payload)
            env["type"], env["body"] = StageTrace.TYPE, msgspec.Raw(body)
            await h.publish_raw(keys.trace(S, "x"), msgspec.msgpack.encode(env))
        await waiter.until(
            lambda: (
                reg.metrics.registry.get_sample_value(
                    "rap_manager_unreadable_samples_total", {"kind": "trace"}
                )
                == len(bodies)
            )
        )
        sent = await h.send(keys.data(S, "scan"))
        await waiter.until(lambda: sent.uid in reg.cycles and reg.cycles[sent.uid].executed)


async def test_a_stalled_cycle_is_found_at_its_deadline() -> None:
    async with running(cycle_timeout=0.3) as (h, manager, waiter):
        reg = manager.registry
        await waiter.until(lambda: all_idle(reg))
        assert (await manager.command("executor", "pause")).ok
        env = await h.send(keys.data(S, "scan"))
        await waiter.until(lambda: env.uid in reg.cycles and reg.cycles[env.uid].stalled)
        assert "no execute stage took it" in reg.alerts[-1].message
        assert (await manager.command("executor", "resume")).ok


async def test_one_manager_per_system() -> None:
    async with running() as (h, _, _):
        second = Manager(fabric=h.fabric, system=S)
        with pytest.raises(LifecycleError, match="running already"):
            await second.run()
        other = MemoryFabric()
        async with other:
            # another system's manager is no conflict
            Manager(fabric=other, system="elsewhere")
