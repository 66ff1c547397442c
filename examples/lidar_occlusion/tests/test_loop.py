"""The five nodes together on the in-memory fabric: detection, causal order, the gate."""

from __future__ import annotations

import contextlib
import itertools
import struct
from collections.abc import AsyncIterator

import msgspec
import numpy as np
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from lidar_occlusion.nodes import Loop, build
from lidar_occlusion.planning import LegitimacyConfig
from lidar_occlusion.scans import occluded_scan
from rap_schemas import LidarMask, PlanProposal, SpinPlan, Verdict, keys
from rap_sdk import Sealer
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio


scan = occluded_scan


@contextlib.asynccontextmanager
async def running(loop: Loop, fabric: str = "memory") -> AsyncIterator[Harness]:
    async with Harness(system="lo", fabric=fabric) as h:  # type: ignore[arg-type]
        await h.hold(open_service(KnowledgeConfig(system="lo"), fabric=h.fabric))
        await h.start(*loop.nodes)
        yield h


async def test_an_occlusion_is_detected_planned_approved_and_sent_to_the_robot() -> None:
    loop = build("tb1")
    async with running(loop) as h:
        env = await h.publish("tb1/scan", scan(-0.4, 0.8))
        plan_rec = await h.expect_data("tb1/spin_config")
        plan = plan_rec.decode(SpinPlan)
        anomaly = h.of(keys.Kind.EVENT, "anomaly")[0].decode(LidarMask)
        assert np.count_nonzero(np.asarray(anomaly.flags())) > 40
        # both ends of the +-0.4 rad sector and back: three commands, net zero
        assert len(plan.commands) == 3
        assert sum(c.omega * c.duration for c in plan.commands) == pytest.approx(0, abs=1e-9)
        # every record of the cycle carries the scan's uid as its cycle
        assert plan_rec.envelope is not None
        assert plan_rec.envelope.cycle == env.uid
        # stage order by causality: each handler was triggered by what the previous one sent
        starts = [t for t in h.traces() if t.started and t.cycle == env.uid]
        stages = [t.stage.value if t.stage else "" for t in starts]
        assert stages == ["monitor", "analyse", "plan", "legitimate", "execute"]
        sent = {r.envelope.uid: r for r in h.records if r.envelope is not None}
        for prev, nxt in itertools.pairwise(starts):
            cause = sent[nxt.trigger].envelope
            assert cause is not None
            assert cause.source == prev.node
        assert loop.gate.stats.approved == 1
        # the anomaly is being handled no more, and the same occlusion raises nothing new
        await h.publish("tb1/scan", scan(-0.4, 0.8))
        await h.wait_for(lambda r: len([t for t in h.traces("analysis") if t.ended]) == 2)
        assert len(h.of(keys.Kind.EVENT, "anomaly")) == 1


async def test_a_rejecting_legitimate_stops_every_plan_before_the_robot() -> None:
    loop = build("tb1", legitimacy=LegitimacyConfig(max_angular=0.5))  # 1 rad/s is too fast
    async with running(loop) as h:
        await h.publish("tb1/scan", scan(0.2, 0.6))
        first = await h.expect_event("plan-rejected")
        assert "limit" in first.decode(Verdict).reason
        # the planner proposes once more (its budget), is refused again, and gives up
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, "plan-rejected")) == 2)
        await h.wait_for(
            lambda r: (
                any(t.ended and t.node == "planner" for t in h.traces())
                and len([t for t in h.traces("planner") if t.ended]) == 3
            )
        )
        assert not h.of(keys.Kind.DATA, "tb1/spin_config")
        assert loop.gate.stats.approved == 0
        assert loop.gate.stats.not_approved == 2
        verdicts = [r.decode(Verdict) for r in h.of(keys.Kind.EVENT, "verdict")]
        assert [v.approved for v in verdicts] == [False, False]
        # given up: the anomaly is no longer handled, so a new scan raises it again
        n = len(h.of(keys.Kind.EVENT, "anomaly"))
        await h.publish("tb1/scan", scan(0.2, 0.6))
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, "anomaly")) > n)


async def test_replayed_stale_and_forged_approvals_are_refused() -> None:
    loop = build("tb1")
    async with running(loop) as h:
        await h.publish("tb1/scan", scan(-0.4, 0.8))
        await h.expect_data("tb1/spin_config")
        approval = next(
            r.decode(Verdict[SpinPlan])  # type: ignore[arg-type]
            for r in h.of(keys.Kind.EVENT, "verdict")
            if r.decode(Verdict).approved
        )
        assert approval.proposal is not None
        key = keys.event("lo", "verdict")
        as_legit = Sealer("legitimate")
        # 1. the same approval again, in a new envelope from the legitimator: replayed
        # (refused and counted; no plan-rejected: that plan ran, nothing is to be replanned)
        payload, _ = as_legit.seal_message(key, approval)
        await h.publish_raw(key, payload)
        await h.wait_for(lambda r: loop.gate.stats.replayed == 1)
        assert not h.of(keys.Kind.EVENT, "plan-rejected")
        # 2. an approval of a plan made long ago: stale
        plan = approval.proposal.plan
        old = PlanProposal(
            plan_uid=b"o" * 16, plan_type=plan.TYPE, plan=plan, proposer="planner", created=1
        )
        stale = Verdict(
            plan_uid=old.plan_uid, approved=True, legitimator="legitimate", ts=2, proposal=old
        )
        payload, _ = as_legit.seal_message(key, stale)
        n = len(h.of(keys.Kind.EVENT, "plan-rejected"))
        await h.publish_raw(key, payload)
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, "plan-rejected")) > n)
        assert "stale" in h.of(keys.Kind.EVENT, "plan-rejected")[-1].decode(Verdict).reason
        # 3. an approval from a node that is not the legitimator: forged
        fresh = PlanProposal(
            plan_uid=b"f" * 16, plan_type=plan.TYPE, plan=plan, proposer="x", created=2**62
        )
        forged = Verdict(
            plan_uid=fresh.plan_uid, approved=True, legitimator="legitimate", ts=2, proposal=fresh
        )
        n = len(h.of(keys.Kind.EVENT, "plan-rejected"))
        await h.emit("verdict", forged)  # sent by "harness"
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, "plan-rejected")) > n)
        assert (
            "not a legitimator" in h.of(keys.Kind.EVENT, "plan-rejected")[-1].decode(Verdict).reason
        )
        st = loop.gate.stats
        assert (st.approved, st.replayed, st.stale, st.unknown_legitimator) == (1, 1, 1, 1)
        assert len(h.of(keys.Kind.DATA, "tb1/spin_config")) == 1  # only the one approved plan


@pytest.mark.parametrize("victim", ["planner", "legitimate", "executor"])
async def test_a_stage_killed_mid_cycle_takes_the_next_cycle_after_its_restart(
    victim: str,
) -> None:
    """A planner, legitimate or executor killed mid-cycle left the anomaly marked as
    handled, and new plans waited 25 scans (5 s); now a lost plan is given up on after
    the plan age has passed, and the restarted stage takes the next anomaly."""
    loop = build("tb1")
    stage = {"planner": loop.plan, "legitimate": loop.legitimate, "executor": loop.execute}
    others = [n for n in loop.nodes if n is not stage[victim]]
    period = 200_000_000  # 5 Hz scans: stamps in ns
    async with Harness(system="lo") as h:
        await h.hold(open_service(KnowledgeConfig(system="lo"), fabric=h.fabric))
        await h.start(*others)  # the victim is dead: the first cycle is lost on the way
        await h.publish("tb1/scan", scan(-0.4, 0.8, stamp=period))
        await h.expect_event("anomaly")
        await h.start(stage[victim])  # restarted
        for i in range(2, 6):
            await h.publish("tb1/scan", scan(-0.4, 0.8, stamp=i * period))
            await h.wait_for(
                lambda r, i=i: (
                    len([t for t in h.traces("monitor") if t.ended]) == i
                    and len([t for t in h.traces("analysis") if t.ended]) == i
                )
            )
            if h.of(keys.Kind.DATA, "tb1/spin_config"):
                break
        plan = await h.expect_data("tb1/spin_config", timeout=5)
        assert plan.envelope is not None
        # the first scan whose anomaly could be raised again: 0.6 s after the lost one
        assert i == 5
        assert len(h.of(keys.Kind.EVENT, "anomaly")) == 2


async def test_nan_and_negative_readings_are_rejected_at_the_boundary() -> None:
    """A scan with NaN or -inf ranges is refused by the monitor's route (the schema), so
    no stage acts on it; a good scan after it still closes the loop."""
    loop = build("tb1")
    good = scan(-0.4, 0.8)
    async with running(loop) as h:
        for bad in (float("nan"), float("-inf"), -1.0):
            raw = msgspec.to_builtins(good, builtin_types=(bytes,))
            packed = bytearray(raw["ranges"])
            struct.pack_into("<f", packed, 4 * 10, bad)  # beam 10, in the packed bytes
            raw["ranges"] = bytes(packed)
            payload, _ = h.sealer.seal(
                keys.data("lo", "tb1/scan"), good.TYPE, msgspec.msgpack.encode(raw)
            )
            await h.publish_raw(keys.data("lo", "tb1/scan"), payload)
        await h.wait_for(lambda r: len(h.rejections("monitor")) >= 1)
        # one reason per key is logged (the rest are counted): the first, the NaN
        assert "ranges[10] is nan" in h.rejections("monitor")[0].reason
        assert not h.of(keys.Kind.EVENT, "new-data")
        await h.publish("tb1/scan", good)
        await h.expect_data("tb1/spin_config")


async def test_a_scan_stamped_in_the_future_does_not_hold_the_anomaly_for_good() -> None:
    """make fuzz: a forged scan stamped far ahead raised an anomaly whose plan never came;
    every real scan after it looked older than it, so the anomaly never timed out and the
    loop never closed again."""
    loop = build("tb1")
    stage = loop.legitimate
    others = [n for n in loop.nodes if n is not stage]
    async with Harness(system="lo") as h:
        await h.hold(open_service(KnowledgeConfig(system="lo"), fabric=h.fabric))
        await h.start(*others)  # no legitimate: the forged scan's plan goes nowhere
        await h.publish("tb1/scan", scan(-0.4, 0.8, stamp=2**62))
        await h.expect_event("anomaly")
        await h.start(stage)
        await h.publish("tb1/scan", scan(-0.4, 0.8, stamp=10**9))
        await h.expect_data("tb1/spin_config")
