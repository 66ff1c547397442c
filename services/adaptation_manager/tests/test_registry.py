"""The registry's rules, as a unit: component states from liveliness and status, the
watches (gone, failed, stalled cycles, trust verdicts) and their counters, plans through
the gate, and a cycle's causal chain."""

from __future__ import annotations

from typing import Any

import pytest
from adaptation_manager.state import Registry, uid_time_ns
from prometheus_client import generate_latest
from rap_schemas import (
    LogRecord,
    PlanProposal,
    SpinPlan,
    Stage,
    StageTrace,
    TrustCause,
    TrustOutput,
    TrustVerdict,
    Verdict,
    keys,
)
from rap_schemas.admin import ComponentState, ComponentStatus

S = "t"
T0 = 1_700_000_000_000_000_000


class Clock:
    def __init__(self) -> None:
        self.mono = 100.0
        self.wall = T0

    def monotonic(self) -> float:
        return self.mono

    def now(self) -> int:
        return self.wall


def registry(**kw: Any) -> tuple[Registry, Clock, list[tuple[str, Any]]]:
    clock = Clock()
    changes: list[tuple[str, Any]] = []
    reg = Registry(
        S,
        now=clock.now,
        monotonic=clock.monotonic,
        on_change=lambda k, v: changes.append((k, v)),
        rejected_event=keys.event(S, "plan-rejected"),
        **kw,
    )
    return reg, clock, changes


def metric(reg: Registry, name: str, **labels: str) -> float:
    value = reg.metrics.registry.get_sample_value(name, labels)
    return 0.0 if value is None else value


def uid(n: int, ms: int = 1_700_000_000_000) -> bytes:
    return ms.to_bytes(6, "big") + n.to_bytes(10, "big")


def call(
    node: str,
    stage: Stage | None,
    trigger: bytes,
    key: str,
    cycle: bytes,
    ts: int,
    dur: int = 1_000_000,
    *,
    phase: str = "call",
    sent: list[str] | None = None,
    ok: bool = True,
) -> StageTrace:
    return StageTrace(
        node=node,
        handler=f"{node}_h",
        phase=phase,  # type: ignore[arg-type]
        trigger=trigger,
        trigger_key=key,
        cycle=cycle,
        ts=ts,
        stage=stage,
        duration_ns=dur if phase != "start" else 0,
        ok=ok,
        error="" if ok else "boom",
        sent=sent or [],
    )


def test_a_component_starts_answers_and_goes_and_each_step_is_pushed() -> None:
    reg, _, changes = registry()
    reg.liveliness("monitor", True)
    assert reg.components["monitor"].state == "starting"
    reg.status(
        ComponentStatus(name="monitor", state=ComponentState.IDLE, compute_node="robot", inbox=3)
    )
    comp = reg.components["monitor"]
    assert (comp.state, comp.compute_node, comp.inbox, comp.answers) == ("idle", "robot", 3, True)
    reg.liveliness("monitor", False)
    assert (comp.state, comp.alive, comp.inbox) == ("gone", False, 0)
    assert [k for k, _ in changes].count("component") == 3
    assert metric(reg, "rap_manager_components_gone_total", component="monitor") == 1
    assert metric(reg, "rap_manager_alerts_total", kind="gone") == 1
    assert "on compute node robot is gone" in reg.alerts[-1].message
    # a status answer that was in flight when the token went does not revive it
    reg.status(ComponentStatus(name="monitor", state=ComponentState.IDLE))
    assert comp.state == "gone"
    reg.liveliness("monitor", True)  # back
    assert (comp.state, comp.alive) == ("starting", True)
    text = generate_latest(reg.metrics.registry).decode()
    assert 'rap_manager_components_gone_total{component="monitor"} 1.0' in text


def test_a_process_that_is_alive_but_never_answers_status_is_shown_alive() -> None:
    reg, _, _ = registry()
    reg.liveliness("knowledge", True)
    reg.liveliness("monitor", True)
    reg.status(ComponentStatus(name="monitor", state=ComponentState.IDLE))
    reg.unanswered({"monitor"})
    assert reg.components["knowledge"].state == "starting"  # give it a second chance
    reg.unanswered({"monitor"})
    assert reg.components["knowledge"].state == "alive"
    assert reg.components["monitor"].state == "idle"
    reg.liveliness("knowledge", False)
    reg.liveliness("knowledge", True)  # back: starting again, until it misses two polls
    assert reg.components["knowledge"].state == "starting"


def test_failing_is_counted_once_per_turn_and_the_manager_itself_is_not_a_component() -> None:
    reg, _, _ = registry()
    reg.ignored.add("manager")
    reg.liveliness("manager", True)
    assert "manager" not in reg.components
    for state in ("idle", "failed", "failed", "idle", "failed"):
        reg.status(ComponentStatus(name="plan", state=ComponentState(state), failed=1))
    assert metric(reg, "rap_manager_components_failed_total", component="plan") == 2
    assert metric(reg, "rap_manager_alerts_total", kind="failed") == 2


def test_a_cycle_whose_handler_never_ends_is_stalled_at_its_deadline_and_only_then() -> None:
    reg, clock, _ = registry(cycle_timeout=5.0)
    c1, c2 = uid(1), uid(2)
    reg.trace(call("monitor", Stage.MONITOR, c1, "k", c1, T0, phase="start"))
    reg.trace(call("monitor", Stage.MONITOR, c2, "k", c2, T0))  # a complete call
    assert reg.next_due() == 105.0
    clock.mono = 104.9
    assert reg.check_due() == 0
    assert reg.cycle_view(reg.cycles[c1]).state == "open"
    clock.mono = 105.0
    assert reg.check_due() == 1
    assert reg.cycle_view(reg.cycles[c1]).state == "stalled"
    assert reg.cycle_view(reg.cycles[c2]).state == "done"
    assert metric(reg, "rap_manager_cycles_stalled_total") == 1
    assert reg.alerts[-1].kind == "stalled"
    assert "monitor.monitor_h started and has not ended" in reg.alerts[-1].message
    assert reg.next_due() is None


def test_plans_proposed_approved_executed_and_an_approval_nobody_took() -> None:
    reg, clock, _ = registry(cycle_timeout=1.0)
    cyc, p1, p2 = uid(1), uid(11), uid(12)
    prop1 = PlanProposal(
        plan_uid=p1, plan_type="rap.SpinPlan/1", plan={}, proposer="planner", created=T0
    )
    reg.proposal(cyc, prop1)
    assert reg.plans[p1].status == "proposed"
    assert "has no verdict" in reg.outstanding(reg.cycles[cyc])[0]
    verdict_env = uid(21)
    reg.verdict(
        cyc,
        verdict_env,
        "legit",
        Verdict(plan_uid=p1, approved=True, legitimator="legit", ts=T0 + 5),
        rejected=False,
    )
    assert reg.plans[p1].status == "approved"
    assert "no execute stage took it" in reg.outstanding(reg.cycles[cyc])[0]
    reg.trace(
        call(
            "executor",
            Stage.EXECUTE,
            verdict_env,
            "verdict",
            cyc,
            T0 + 9,
            sent=[keys.data(S, "tb1/spin_config")],
        )
    )
    assert reg.plans[p1].status == "executed"
    assert reg.plans[p1].executor == "executor"
    assert reg.cycle_view(reg.cycles[cyc]).state == "executed"
    # a second plan rejected; a third approved that no execute stage ever takes
    reg.proposal(
        cyc, PlanProposal(plan_uid=p2, plan_type="x", plan={}, proposer="planner", created=T0)
    )
    reg.verdict(
        cyc,
        uid(22),
        "legit",
        Verdict(plan_uid=p2, approved=False, legitimator="legit", ts=T0, reason="too wide"),
        rejected=False,
    )
    reg.verdict(
        cyc,
        uid(23),
        "legit",
        Verdict(plan_uid=p2, approved=False, legitimator="legit", ts=T0, reason="too wide"),
        rejected=True,
    )
    assert (reg.plans[p2].status, reg.plans[p2].reason) == ("rejected", "too wide")
    other, p3 = uid(2), uid(13)
    reg.proposal(
        other, PlanProposal(plan_uid=p3, plan_type="x", plan={}, proposer="planner", created=T0)
    )
    reg.verdict(
        other,
        uid(24),
        "legit",
        Verdict(plan_uid=p3, approved=True, legitimator="legit", ts=T0),
        rejected=False,
    )
    clock.mono += 1.0
    assert reg.check_due() == 1  # the cycle of p3 only
    assert reg.cycle_view(reg.cycles[other]).state == "stalled"
    outcomes = {
        o: metric(reg, "rap_manager_plans_total", outcome=o)
        for o in ("proposed", "approved", "rejected", "executed")
    }
    assert outcomes == {"proposed": 3, "approved": 2, "rejected": 1, "executed": 1}


def test_an_execute_call_that_sent_plan_rejected_refused_the_plan() -> None:
    reg, _, _ = registry()
    cyc, p1, v = uid(1), uid(11), uid(21)
    reg.proposal(cyc, PlanProposal(plan_uid=p1, plan_type="x", plan={}, proposer="p", created=T0))
    reg.verdict(
        cyc, v, "l", Verdict(plan_uid=p1, approved=True, legitimator="l", ts=T0), rejected=False
    )
    reg.trace(
        call(
            "executor", Stage.EXECUTE, v, "verdict", cyc, T0, sent=[keys.event(S, "plan-rejected")]
        )
    )
    assert reg.plans[p1].status == "refused"


def test_a_false_trust_verdict_is_an_alert_with_its_explanation() -> None:
    reg, _, changes = registry()
    reg.trust_output(TrustOutput(stream="ok", tick=3, ts=T0, value=False))
    assert reg.trust_outputs["ok"].false
    reg.trust_verdict(
        TrustVerdict(
            stream="ok",
            tick=3,
            ts=T0,
            value=False,
            expr="latency < 2.0",
            because=[TrustCause(expr="latency", value=2.5, input="latency", input_tick=3)],
        )
    )
    assert metric(reg, "rap_manager_trust_verdicts_total", stream="ok") == 1
    assert metric(reg, "rap_manager_alerts_total", kind="trust") == 1
    assert "because latency = 2.5" in reg.alerts[-1].message
    assert reg.verdicts[-1].because[0].input == "latency"
    assert {k for k, _ in changes} >= {"trust", "verdict", "alert", "log"}


def test_the_causal_chain_puts_each_call_under_the_call_that_sent_its_sample() -> None:
    reg, _, _ = registry()
    scan = uid(1)
    t = uid_time_ns(scan)
    assert t == 1_700_000_000_000 * 1_000_000
    new_data, anomaly = uid(2), uid(3)
    # records arrive out of order; the events carry their cause
    reg.trace(
        call(
            "analysis",
            Stage.ANALYSE,
            new_data,
            keys.event(S, "new-data"),
            scan,
            t + 3_000_000,
            2_000_000,
            sent=[keys.event(S, "anomaly")],
        )
    )
    reg.event(
        "anomaly", keys.event(S, "anomaly"), anomaly, "analysis", t + 5_000_000, scan, new_data
    )
    reg.trace(
        call(
            "monitor",
            Stage.MONITOR,
            scan,
            keys.data(S, "tb1/scan"),
            scan,
            t + 1_000_000,
            sent=[keys.event(S, "new-data")],
        )
    )
    reg.event("new-data", keys.event(S, "new-data"), new_data, "monitor", t + 2_000_000, scan, scan)
    reg.trace(call("planner", Stage.PLAN, anomaly, keys.event(S, "anomaly"), scan, t + 6_000_000))
    chain = reg.chain(reg.cycles[scan])
    steps = [(s.depth, s.node, s.offset_ms, s.wait_ms, s.trigger_source) for s in chain.steps]
    assert steps == [
        (0, "monitor", 1.0, 1.0, ""),
        (1, "analysis", 3.0, 1.0, "monitor"),
        (2, "planner", 6.0, 1.0, "analysis"),
    ]
    assert chain.root_key == keys.data(S, "tb1/scan")
    assert chain.total_ms == 7.0
    # a prefix finds it; the log tail and snapshot are JSON-able
    assert reg.find(scan.hex()[:20]) == [reg.cycles[scan]]
    reg.log_record("x", LogRecord(ts=T0, level="INFO", logger="l", message="<b>hi</b>"))
    snap = reg.snapshot()
    assert snap["log"][-1]["text"] == "<b>hi</b>"  # kept as text: the page escapes it
    assert snap["cycles"][-1]["stages"] == ["analyse", "monitor", "plan"]


def test_the_history_is_bounded_and_a_cycle_that_left_it_is_not_checked() -> None:
    reg, clock, _ = registry(history=3, cycle_timeout=1.0)
    for n in range(10):
        c = uid(n)
        reg.trace(call("m", None, c, "k", c, T0, phase="start"))
    assert len(reg.cycles) == 3
    clock.mono += 2
    assert reg.check_due() == 3  # only the three it still holds


def test_an_executed_cycle_outlives_the_history_for_rap_trace() -> None:
    reg, _, _ = registry(history=3, cycle_timeout=1.0)
    done = uid(100)
    reg.trace(call("x", Stage.EXECUTE, done, "k", done, T0))
    for n in range(10):  # cycles that end at the analysis push it out of the history
        c = uid(n)
        reg.trace(call("m", Stage.MONITOR, c, "k", c, T0))
    assert done not in reg.cycles
    last = reg.last_complete(executed=True)
    assert last is not None
    assert last.uid == done
    assert reg.find(done.hex()) == [last]


@pytest.mark.parametrize("bad", [{"history": 0}, {"cycle_timeout": 0.0}, {"tail": 0}])
def test_bad_bounds_are_refused(bad: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="must be"):
        Registry(S, **bad)


def test_a_spin_plan_proposal_decodes_as_plain_data() -> None:
    # what the manager receives: a PlanProposal[Any] whose plan is plain data
    import msgspec

    plan = SpinPlan(commands=[])
    prop = PlanProposal(plan_uid=uid(1), plan_type=plan.TYPE, plan=plan, proposer="p", created=T0)
    raw = msgspec.msgpack.encode(prop)
    back = msgspec.msgpack.decode(raw, type=PlanProposal[Any])
    reg, _, _ = registry()
    reg.proposal(uid(9), back)
    assert reg.plans[uid(1)].plan_type == "rap.SpinPlan/1"
