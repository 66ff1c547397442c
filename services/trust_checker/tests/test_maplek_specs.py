"""The shipped MAPLE-K specs against the lidar-occlusion loop, in this process on the
memory fabric: one checker per spec (``open_service`` with a fabric transport
subscribed to the loop's system, as ``python -m trust_checker SPEC --fabric SYSTEM``
runs it). On the healthy loop every output stays true; each planted fault (a variant of
the loop's nodes built here, the example untouched) turns the right spec false. Last,
a guard: a false verdict makes the executor take its safe action and refuse plans
until the verdict is true again."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import AsyncIterator, Awaitable, Callable, Collection, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import anyio
import msgspec
import pytest
from knowledge.app import open_service as open_knowledge
from knowledge.config import KnowledgeConfig
from lidar_occlusion.nodes import ANOMALY, DIRECTIONS, HANDLING, LASER_SCAN, LIDAR_MASK, build
from lidar_occlusion.planning import LegitimacyConfig, PlanConfig
from lidar_occlusion.scans import occluded_scan
from lidar_occlusion.scenario import run_in_process
from rap_schemas import (
    LaserScan,
    LidarMask,
    PlanProposal,
    SpinPlan,
    TrustOutput,
    TrustSpecStatus,
    Verdict,
    keys,
    pack_flags,
)
from rap_sdk import Context, Fabric, MemoryFabric, Node
from rap_sdk.gate import PLAN_REJECTED, ApprovalGate, TrustGuard
from rap_sdk.node import EVENT_POLICY
from rap_sdk.testing import Harness, Record
from sim_world.world import Occlusion, default_world_path, load_world
from trust_checker.config import FabricConfig, ServiceConfig
from trust_checker.io.ports import OutputLike
from trust_checker.io.session import Session
from trust_checker.io.specs import load_text
from trust_checker.service import open_service
from trust_checker.specs import MAPLEK_OUTPUTS, maplek_specs

pytestmark = pytest.mark.anyio

SYS = "lo"


scan = occluded_scan


# -- the checkers ----------------------------------------------------------------------


@dataclass
class Checker:
    """One spec running on the fabric (a sink of its session); ``values`` are its
    output's verdicts in order."""

    name: str
    session: Session | None = None
    values: list[object] = field(default_factory=list)

    @property
    def stats(self) -> Any:
        assert self.session is not None
        return self.session.stats

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        self.values += [o.value for o in outs]

    async def status(self, status: TrustSpecStatus) -> None:
        """No swaps here."""


@asynccontextmanager
async def checking(
    fabric: Fabric, system: str = SYS, names: Collection[str] | None = None
) -> AsyncIterator[dict[str, Checker]]:
    specs = maplek_specs()
    checkers: dict[str, Checker] = {}
    async with contextlib.AsyncExitStack() as stack:
        for name in sorted(names if names is not None else specs):
            checker = checkers[name] = Checker(name)
            config = ServiceConfig(
                node=f"trust_{name}", verdicts=False, fabric=FabricConfig(system=system)
            )
            service = await stack.enter_async_context(
                open_service(config, load_text(specs[name], name), fabric=fabric, sinks=[checker])
            )
            checker.session = service.session
        yield checkers


async def settle() -> None:
    """Everything in flight is taken: the loop's cycle is over and every checker has read
    every record of it (all tasks wait on empty inboxes, one process, memory fabric)."""
    with anyio.fail_after(10):
        await anyio.wait_all_tasks_blocked()


def went_false(checkers: dict[str, Checker]) -> set[str]:
    """The specs whose output was false at least once (every verdict is a Bool)."""
    for c in checkers.values():
        assert c.values, f"{c.name} gave no verdict"
        assert all(type(v) is bool for v in c.values), (c.name, c.values)
    return {name for name, c in checkers.items() if False in c.values}


@asynccontextmanager
async def running(nodes: Sequence[Node]) -> AsyncIterator[tuple[Harness, dict[str, Checker]]]:
    async with Harness(system=SYS) as h:
        checkers = await h.hold(checking(h.fabric))
        await h.hold(open_knowledge(KnowledgeConfig(system=SYS), fabric=h.fabric))
        await h.start(*nodes)
        yield h, checkers


async def feed(h: Harness, *scans: LaserScan) -> None:
    """Publish scans one cycle at a time (lockstep, like the simulator)."""
    for s in scans:
        await h.publish("tb1/scan", s)
        await settle()


OCCLUDED = [scan(-0.4, 0.8), scan(-0.4, 0.8), scan(), scan(), scan(), scan(1.0, 0.6)]
"""An occlusion (anomaly, plan), the same again (nothing new), clear (the plan goes back
to nominal), then another occlusion."""


def spin_configs(h: Harness) -> list[SpinPlan]:
    return [r.decode(SpinPlan) for r in h.of(keys.Kind.DATA, "tb1/spin_config")]


# -- faulty variants of the loop's nodes -----------------------------------------------


def delayed(node: Node, before: Callable[[], Awaitable[None]], events: Collection[str]) -> Node:
    """``node`` whose handlers of ``events`` first await ``before()``."""
    slow = Node(node.name, stage=node.stage, config=node.config)
    for route in node.routes:
        fn = route.fn
        if route.name in events:

            async def waiting(*args: Any, _fn: Callable[..., Awaitable[None]] = fn) -> None:
                await before()
                await _fn(*args)

            waiting.__qualname__ = fn.__qualname__
            fn = waiting
        slow.routes.append(dataclasses.replace(route, fn=fn))
    return slow


class Hold:
    """While ``on``, a delayed handler waits for ``release`` (the test's, not a sleep)."""

    def __init__(self) -> None:
        self.on = False
        self.release = anyio.Event()
        self.holding = anyio.Event()

    async def __call__(self) -> None:
        if self.on:
            self.holding.set()
            with anyio.fail_after(20):
                await self.release.wait()


def hasty_monitor() -> Node:
    """Skips analyse: takes every unreachable beam for occlusion and raises the anomaly."""
    mon = Node("monitor", stage="monitor")

    @mon.on_data("tb1/scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        occluded = pack_flags([not math.isfinite(r) for r in s.values()])
        mask = LidarMask(
            angle_min=s.angle_min,
            angle_increment=s.angle_increment,
            occluded=occluded,
            frame_id=s.frame_id,
        )
        await ctx.kb.write(LIDAR_MASK, mask)
        await ctx.emit(ANOMALY, mask)

    return mon


def forgetful_monitor() -> Node:
    """Writes every scan but announces only every other one: the scans in between are
    overwritten by the next before anyone read them."""
    mon = Node("monitor", stage="monitor")
    scans = [0]

    @mon.on_data("tb1/scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        scans[0] += 1
        await ctx.kb.write(LASER_SCAN, s)
        if scans[0] % 2:
            await ctx.emit("new-data")

    return mon


def rogue_executor() -> Node:
    """Acts on the anomaly itself, bypassing plan, legitimate and the gate."""
    exe = Node("rogue", stage="execute")

    @exe.on_event(ANOMALY)
    async def act(ctx: Context, mask: LidarMask) -> None:
        await ctx.publish("tb1/spin_config", SpinPlan(commands=[]))

    return exe


def careless_executor() -> Node:
    """Executes whatever the planner left in knowledge on every verdict, approved or not
    (RPIO's Execute did that)."""
    exe = Node("executor", stage="execute")

    async def act(ctx: Context) -> None:
        plan = await ctx.kb.read(DIRECTIONS, SpinPlan)
        await ctx.publish("tb1/spin_config", plan)

    # rap_sdk refuses an execute stage that takes verdicts outside the gate; this plants
    # the fault the way a stage written without the SDK's check would have it
    exe._route("event", "verdict", EVENT_POLICY, Verdict, gated=True)(act)
    return exe


def twin_executors(legitimate: str) -> list[Node]:
    """Two executors acting on the same approved plans, each waiting in its handler
    until the other has started: their handlers overlap."""
    started = {"a": anyio.Event(), "b": anyio.Event()}
    nodes = []
    for me, other in (("a", "b"), ("b", "a")):
        exe = Node(f"executor_{me}", stage="execute")
        gate = ApprovalGate(legitimators={legitimate}, max_age=0.2)

        @gate.on_approved(exe)
        async def act(
            ctx: Context, proposal: PlanProposal[SpinPlan], me: str = me, other: str = other
        ) -> None:
            started[me].set()
            with anyio.fail_after(5):
                await started[other].wait()
            await ctx.publish("tb1/spin_config", proposal.plan)
            await ctx.kb.write(HANDLING, False)

        nodes.append(exe)
    return nodes


# -- healthy ---------------------------------------------------------------------------


async def test_every_spec_stays_true_on_the_healthy_loop() -> None:
    loop = build("tb1")
    async with running(loop.nodes) as (h, checkers):
        await feed(h, *OCCLUDED)
        assert loop.gate.stats.approved == 3  # onset, back to nominal, the second one
        assert len(h.of(keys.Kind.EVENT, ANOMALY)) == 3
        assert went_false(checkers) == set()
        # they did look: every spec took ticks of the loop's records
        assert all(c.stats.ticks >= 3 for c in checkers.values())
        # a start and an end tick per handler call (one record, or two)
        ticks = sum(2 if t.phase == "call" else 1 for t in h.traces())
        assert checkers["stage_order"].stats.ticks == ticks


async def test_every_spec_stays_true_over_a_simulated_run() -> None:
    world = load_world(default_world_path("default"))
    occ = Occlusion(robot="tb1", mode="sector", start_angle=-0.5, width=1.0, t_start=2.0, t_end=9.0)
    world = msgspec.structs.replace(world, occlusions=[occ])
    async with MemoryFabric() as fabric, checking(fabric, "demo") as checkers:
        m = await run_in_process(world, duration=12.0, system="demo", fabric=fabric)
        await settle()
    assert m["plans_executed"] == 2
    assert m["lockstep_timeouts"] == 0
    assert went_false(checkers) == set()
    assert checkers["stage_order"].stats.ticks > 100  # 12 s of scans at 5 Hz


# -- planted faults --------------------------------------------------------------------


async def test_a_skipped_stage_is_caught_by_stage_order() -> None:
    loop = build("tb1")
    nodes = [hasty_monitor(), loop.plan, loop.legitimate, loop.execute]
    async with running(nodes) as (h, checkers):
        await feed(h, scan(-0.4, 0.8))
        assert len(spin_configs(h)) == 1  # the loop acted, in the wrong order
        assert went_false(checkers) == {"stage_order"}
        assert checkers["stage_order"].values.count(False) == 1  # the planner's start


async def test_overlapping_executions_are_caught_by_no_overlap() -> None:
    loop = build("tb1")
    nodes = [loop.monitor, loop.analyse, loop.plan, loop.legitimate]
    async with running([*nodes, *twin_executors(loop.legitimate.name)]) as (h, checkers):
        await feed(h, scan(-0.4, 0.8))
        assert len(spin_configs(h)) == 2
        assert went_false(checkers) == {"no_overlap"}


async def test_a_deadline_miss_is_caught_and_ends_with_the_execution() -> None:
    hold = Hold()
    loop = build("tb1")
    slow_plan = delayed(loop.plan, hold, {ANOMALY})
    nodes = [loop.monitor, loop.analyse, slow_plan, loop.legitimate, loop.execute]
    async with running(nodes) as (h, checkers):
        await feed(h, scan(-0.4, 0.8))
        hold.on = True
        await h.publish("tb1/scan", scan(1.0, 0.6))
        deadline = checkers["anomaly_deadline"]
        # the checker's timer ticks report the miss while the planner is stuck
        await h.wait_for(deadline_says(False))
        assert hold.holding.is_set()
        hold.release.set()
        await h.wait_for(lambda r: len(spin_configs(h)) == 2)
        await settle()
        assert went_false(checkers) == {"anomaly_deadline"}
        assert deadline.values[-1] is True  # the late execution ended the wait
        assert loop.gate.stats.approved == 2


async def test_an_executor_acting_on_the_anomaly_is_caught_by_execute_approved() -> None:
    loop = build("tb1")
    async with running([*loop.nodes, rogue_executor()]) as (h, checkers):
        await feed(h, scan(-0.4, 0.8))
        assert len(spin_configs(h)) == 2  # the rogue's, then the approved plan
        # execute jumped straight after analyse: the stage order is broken as well
        assert went_false(checkers) == {"execute_approved", "stage_order"}
        assert checkers["execute_approved"].values.count(False) == 2  # its start and end


async def test_an_executor_ignoring_rejections_is_caught_by_execute_approved_alone() -> None:
    loop = build("tb1", legitimacy=LegitimacyConfig(max_angular=0.5))  # rejects every plan
    nodes = [loop.monitor, loop.analyse, loop.plan, loop.legitimate, careless_executor()]
    async with running(nodes) as (h, checkers):
        await feed(h, scan(-0.4, 0.8))
        assert len(h.of(keys.Kind.EVENT, PLAN_REJECTED)) == 2  # proposed twice, refused
        assert len(spin_configs(h)) == 2  # and executed twice all the same
        assert went_false(checkers) == {"execute_approved"}
        assert checkers["execute_approved"].values.count(False) == 2  # at each end


async def test_a_scan_nobody_read_is_caught_by_unread_overwrite() -> None:
    loop = build("tb1")
    nodes = [forgetful_monitor(), loop.analyse, loop.plan, loop.legitimate, loop.execute]
    async with running(nodes) as (h, checkers):
        await feed(h, scan(-0.4, 0.8), scan(), scan(), scan(), scan())
        assert len(spin_configs(h)) == 1  # the onset (analyse saw 3 scans of 5)
        assert len([t for t in h.traces("analysis") if t.ended]) == 3
        assert went_false(checkers) == {"unread_overwrite"}
        assert checkers["unread_overwrite"].values.count(False) == 2  # scans 3 and 5


# -- veto ------------------------------------------------------------------------------


def deadline_says(value: bool) -> Callable[[Record], bool]:
    """A record: the anomaly_deadline spec's output, with ``value``."""
    stream = MAPLEK_OUTPUTS["anomaly_deadline"]

    def pred(r: Record) -> bool:
        if r.kind is not keys.Kind.TRUST or r.name != stream:
            return False
        return r.decode(TrustOutput).value is value

    return pred


async def test_a_false_guard_stops_the_robot_and_refuses_plans_until_it_is_true() -> None:
    """The anomaly_deadline spec guards the executor: a stuck planner turns it false, the
    executor publishes a stop plan once and refuses the late plan; when the spec is true
    again, plans flow again."""
    hold = Hold()
    loop = build("tb1", planning=PlanConfig(replans=0))
    slow_plan = delayed(loop.plan, hold, {ANOMALY})
    stop = SpinPlan(commands=[])

    async def stop_the_robot(ctx: Context, reason: str) -> None:
        await ctx.publish("tb1/spin_config", stop)

    guard = TrustGuard(
        streams={MAPLEK_OUTPUTS["anomaly_deadline"]},
        safe_action=stop_the_robot,
        checkers={"trust_anomaly_deadline"},
    )
    gate = ApprovalGate(legitimators={loop.legitimate.name}, max_age=0.2, guard=guard)
    exe = Node("executor", stage="execute")

    @gate.on_approved(exe)
    async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        await ctx.publish("tb1/spin_config", proposal.plan)
        await ctx.kb.write(HANDLING, False)

    nodes = [loop.monitor, loop.analyse, slow_plan, loop.legitimate, exe]
    async with running(nodes) as (h, checkers):
        # healthy: the guard is true, the plan runs
        await feed(h, scan(-0.4, 0.8))
        assert len(spin_configs(h)) == 1
        assert guard.veto() is None
        assert guard.stats.verdicts > 0
        # the fault: the planner is stuck past the deadline; the guard turns false
        hold.on = True
        await h.publish("tb1/scan", scan(1.0, 0.6))
        await h.wait_for(lambda r: len(spin_configs(h)) == 2)
        assert spin_configs(h)[1] == stop  # the safe action
        assert guard.veto() is not None
        assert "trust guard 'anomaly_deadline_ok' vetoes" in (guard.veto() or "")
        # the late plan is approved by legitimate, and refused by the guard
        n = len(h.records)
        hold.release.set()
        rejected = await h.expect_event(PLAN_REJECTED, after=n)
        assert "trust guard 'anomaly_deadline_ok' vetoes" in rejected.decode(Verdict).reason
        assert gate.stats.vetoed == 1
        # the execute stage took the anomaly up: the deadline spec, and the guard, are true
        await h.wait_for(deadline_says(True), after=n)
        await settle()
        assert guard.veto() is None
        assert (guard.stats.closed, guard.stats.reopened, guard.stats.safe_actions) == (1, 1, 1)
        # plans flow again
        hold.on = False
        await feed(h, scan(-2.0, 0.6))
        assert len(spin_configs(h)) == 3  # the first plan, the stop plan, this one
        assert spin_configs(h)[2].commands
        assert (gate.stats.approved, gate.stats.vetoed) == (2, 1)
        # the veto broke no other rule of the loop
        assert went_false(checkers) == {"anomaly_deadline"}
