"""The contract floor: the chain's five stages as coroutines awaited one after another,
doing what RAP's message and knowledge contract asks of every cycle and nothing else.

Per cycle, with RAP's own primitives (``Sealer``, ``HybridClock``, ``ApprovalGate``):
- six envelopes (the robot's scan, ``new-data``, ``anomaly``, the proposal, the verdict,
  the plan to the robot), each with uid, time, source, per-key sequence, type, cycle,
  cause and the versions written before it (``ctx``);
- three knowledge writes, each a hybrid-logical-clock version and a ``Versioned`` record
  kept in the key's bounded history; two causal reads, each checking that the replica
  holds at least the version the event names;
- the legitimate check and the execute gate (freshness, replay, the legitimator's name).

No routing, no subscriptions, no inbox, no trace, no task switch: a stage calls the
next one. Paced like the loop rows, it is the least any runtime keeping RAP's contract
can take per cycle on this machine with these handlers; the distance from it to
``rap-inproc`` is what RAP's dispatch costs.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any

from lidar_occlusion.planning import check_plan
from rap_schemas import LaserScan, LidarMask, PlanProposal, SpinPlan, Verdict
from rap_sdk.envelope import OutgoingEnvelope, Sealer, new_uid
from rap_sdk.gate import ApprovalGate
from rap_sdk.knowledge import HybridClock, Versioned

from .chain import LEGIT, PLAN, ROBOT, mask_of

HISTORY = 100


class _Store:
    """Latest record and bounded history per key, as the co-located replica and the
    memory store keep them."""

    def __init__(self) -> None:
        self.latest: dict[str, Versioned] = {}
        self.history: dict[str, deque[Versioned]] = {}

    def write(self, clock: HybridClock, writer: str, key: str, value: Any) -> int:
        version = clock.next()
        rec = Versioned(key=key, version=version, ts=time.time_ns(), writer=writer, value=value)
        self.latest[key] = rec
        hist = self.history.get(key)
        if hist is None:
            hist = self.history[key] = deque(maxlen=HISTORY)
        hist.append(rec)
        return version

    def read(self, clock: HybridClock, key: str, at_least: int) -> Any:
        rec = self.latest[key]
        if rec.version < at_least:
            raise LookupError(f"{key}: replica behind the version the event names")
        clock.observe(rec.version)
        return rec.value


def contract_cycle() -> Callable[[LaserScan], Awaitable[SpinPlan | None]]:
    """One cycle of the chain, keeping the contract, as one awaitable per scan."""
    kb = _Store()
    names = ("robot", "monitor", "analysis", "planner", "legitimate", "executor")
    seal = {n: Sealer(n) for n in names}
    clocks = {n: HybridClock(n) for n in names}
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=1.0)
    now = time.time_ns

    async def executor(env: OutgoingEnvelope) -> SpinPlan | None:
        verdict: Verdict[SpinPlan] = env.body
        if gate.check(verdict, env.source, now()) is not None:
            return None
        assert verdict.proposal is not None
        out = (
            seal["executor"]
            .seal_out(f"{ROBOT}/spin_config", verdict.proposal.plan, cycle=env.cycle, cause=env.uid)
            .obj
        )
        return out.body  # type: ignore[no-any-return]

    async def legitimate(env: OutgoingEnvelope) -> SpinPlan | None:
        proposal: PlanProposal[SpinPlan] = env.body
        reason = check_plan(proposal, now(), LEGIT)
        verdict = Verdict(
            plan_uid=proposal.plan_uid,
            approved=reason is None,
            legitimator="legitimate",
            reason=reason or "",
            ts=now(),
            proposal=proposal,
        )
        out = seal["legitimate"].seal_out("verdict", verdict, cycle=env.cycle, cause=env.uid)
        return await executor(out.obj)

    async def planner(env: OutgoingEnvelope) -> SpinPlan | None:
        clock = clocks["planner"]
        kb.read(clock, "lidar_mask", env.ctx["lidar_mask"])
        v = kb.write(clock, "planner", "directions", PLAN)
        ts = now()
        proposal = PlanProposal(
            plan_uid=new_uid.at(ts), plan_type=PLAN.TYPE, plan=PLAN, proposer="planner", created=ts
        )
        out = seal["planner"].seal_out(
            "new-plan", proposal, cycle=env.cycle, cause=env.uid, ctx={"directions": v}
        )
        return await legitimate(out.obj)

    async def analysis(env: OutgoingEnvelope) -> SpinPlan | None:
        clock = clocks["analysis"]
        scan: LaserScan = kb.read(clock, "laser_scan", env.ctx["laser_scan"])
        mask: LidarMask = mask_of(scan)
        v = kb.write(clock, "analysis", "lidar_mask", mask)
        out = seal["analysis"].seal_out(
            "anomaly", None, cycle=env.cycle, cause=env.uid, ctx={"lidar_mask": v}
        )
        return await planner(out.obj)

    async def monitor(env: OutgoingEnvelope) -> SpinPlan | None:
        v = kb.write(clocks["monitor"], "monitor", "laser_scan", env.body)
        out = seal["monitor"].seal_out(
            "new-data", None, cycle=env.uid, cause=env.uid, ctx={"laser_scan": v}
        )
        return await analysis(out.obj)

    async def cycle(scan: LaserScan) -> SpinPlan | None:
        env = seal["robot"].seal_out(f"{ROBOT}/scan", scan).obj
        return await monitor(env)

    return cycle
