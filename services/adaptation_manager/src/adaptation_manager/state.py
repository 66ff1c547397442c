"""The manager's picture of a running system, fed by what it sees on the fabric.

:class:`Registry` is plain synchronous state (no I/O, clocks injected), so that its
rules are tested without a fabric:

- **components**, from liveliness (``alive/*``: up is ``starting`` until it answers
  ``status``; down is ``gone``), the admin ``status`` answers and the trace records;
- **cycles**, a bounded history of the last ``history`` loop cycles, each with its
  handler calls (trace records), the events sent in it and its plans;
- **plans** proposed, approved, rejected, executed (events ``new-plan``, ``verdict``,
  ``plan-rejected``; an execute-stage call on an approving verdict);
- **trust** outputs (latest value per stream) and verdicts with their explanations;
- a **log tail** (LogRecord and Rejection records of ``log/**``);
- **watches**: a component gone or failing, a cycle still open ``cycle_timeout`` s after
  it started, a trust verdict false. Each is logged, counted (:class:`Metrics`) and kept
  as an alert.

What is outstanding in a cycle follows the MAPLE-K contract: a handler call that started
and has not ended, a proposal without a verdict (the Legitimate stage answers every
proposal), an approving verdict that no execute-stage call took. Every change is handed
to ``on_change(kind, view)`` (the dashboard pushes it).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Final

import msgspec
from prometheus_client import CollectorRegistry, Counter, Gauge
from rap_schemas import (
    LogRecord,
    PlanProposal,
    Rejection,
    StageTrace,
    TrustOutput,
    TrustVerdict,
    Verdict,
)
from rap_schemas.admin import ComponentState, ComponentStatus
from rap_sdk.rejections import Throttle

from .views import (
    AlertView,
    CallView,
    CauseView,
    ComponentView,
    CycleTrace,
    CycleView,
    LogView,
    PlanView,
    TraceStep,
    TrustOutputView,
    TrustVerdictView,
    short_json,
)

__all__ = ["Metrics", "Registry", "uid_time_ns"]

log = logging.getLogger("adaptation_manager")

MAX_TEXT: Final = 2000
"""Characters of a text from the fabric (a log message, a reason) kept."""
MAX_CALLS: Final = 256
"""Handler calls (and as many events) kept per cycle."""
MAX_LABELS: Final = 256
"""Distinct label values per Prometheus counter; the rest count under ``other``."""
OTHER: Final = "other"


def _cut(text: str, limit: int = MAX_TEXT) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def uid_time_ns(uid: bytes) -> int:
    """The creation time a UUIDv7 uid carries (its 48-bit ms timestamp), UTC ns; 0 when
    it is not a 16-byte uid."""
    if len(uid) != 16:
        return 0
    return int.from_bytes(uid[:6], "big") * 1_000_000


class Metrics:
    """The manager's counters, on a registry of its own (served at ``/metrics``)."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry or CollectorRegistry(auto_describe=True)
        r = self.registry
        self.alerts = Counter(
            "rap_manager_alerts", "What the watches found, by kind.", ["kind"], registry=r
        )
        self.gone = Counter(
            "rap_manager_components_gone",
            "Components whose liveliness token went away.",
            ["component"],
            registry=r,
        )
        self.failed = Counter(
            "rap_manager_components_failed",
            "Components that turned failed (their last handler call raised).",
            ["component"],
            registry=r,
        )
        self.handler_failures = Counter(
            "rap_manager_handler_failures",
            "Handler calls whose trace record says they failed.",
            ["component"],
            registry=r,
        )
        self.cycles = Counter(
            "rap_manager_cycles", "Loop cycles seen (a trace record of a new cycle).", registry=r
        )
        self.stalled = Counter(
            "rap_manager_cycles_stalled",
            "Cycles with something outstanding at their deadline.",
            registry=r,
        )
        self.plans = Counter(
            "rap_manager_plans",
            "Plans by outcome: proposed, approved, rejected, executed, refused.",
            ["outcome"],
            registry=r,
        )
        self.trust = Counter(
            "rap_manager_trust_verdicts",
            "Trust verdicts (a Bool output turned false, a trigger fired), by stream.",
            ["stream"],
            registry=r,
        )
        self.unreadable = Counter(
            "rap_manager_unreadable_samples",
            "Samples and replies the manager could not read, by kind of key.",
            ["kind"],
            registry=r,
        )
        self.admin_calls = Counter(
            "rap_manager_admin_calls",
            "Admin verbs called from the dashboard, by verb and result.",
            ["verb", "result"],
            registry=r,
        )
        self.components = Gauge(
            "rap_manager_components", "Components known, by state.", ["state"], registry=r
        )
        self.clients = Gauge(
            "rap_manager_dashboard_clients", "Dashboard pages connected now.", registry=r
        )
        self._labels: dict[str, set[str]] = {}

    def label(self, family: str, value: str) -> str:
        """``value``, or ``other`` once ``family`` has MAX_LABELS distinct values (names
        come from the fabric: their number is not ours to choose)."""
        seen = self._labels.setdefault(family, set())
        if value in seen:
            return value
        if len(seen) >= MAX_LABELS:
            return OTHER
        seen.add(value)
        return value


# -- cycles -------------------------------------------------------------------------------


@dataclass(slots=True)
class _Call:
    node: str
    handler: str
    stage: str
    trigger: bytes
    trigger_key: str
    start: int = 0
    duration_ns: int = 0
    started: bool = False
    ended: bool = False
    ok: bool = True
    error: str = ""
    sent: list[str] = field(default_factory=list)

    def view(self) -> CallView:
        return CallView(
            node=self.node,
            handler=self.handler,
            stage=self.stage,
            trigger_key=self.trigger_key,
            start=self.start,
            duration_ns=self.duration_ns,
            ended=self.ended,
            ok=self.ok,
            error=self.error,
        )

    @property
    def end(self) -> int:
        return self.start + self.duration_ns


@dataclass(slots=True, frozen=True)
class _Sent:
    """An event envelope of the cycle."""

    uid: bytes
    key: str
    name: str
    source: str
    ts: int
    cause: bytes | None


@dataclass(slots=True)
class _Cycle:
    uid: bytes
    due: float
    """``monotonic()`` deadline of its watch."""
    calls: dict[tuple[str, bytes], _Call] = field(default_factory=dict)
    sent: dict[bytes, _Sent] = field(default_factory=dict)
    plans: list[bytes] = field(default_factory=list)
    stages: list[str] = field(default_factory=list)
    last_activity: float = 0.0
    stalled: bool = False
    checked: bool = False

    @property
    def hex(self) -> str:
        return self.uid.hex()

    @property
    def start(self) -> int:
        starts = [c.start for c in self.calls.values() if c.start]
        t = uid_time_ns(self.uid)
        if starts:
            first = min(starts)
            return min(t, first) if t else first
        return t

    @property
    def end(self) -> int:
        return max((c.end for c in self.calls.values() if c.ended), default=0)

    @property
    def executed(self) -> bool:
        return any(c.stage == "execute" and c.ended and c.ok for c in self.calls.values())


EXECUTED_KEPT = 100
"""Executed cycles kept once they have left the cycle history."""


@dataclass(slots=True)
class _Plan:
    uid: bytes
    cycle: bytes
    status: str = "proposed"
    proposer: str = ""
    plan_type: str = ""
    created: int = 0
    legitimator: str = ""
    reason: str = ""
    decided: int = 0
    verdict_uid: bytes = b""
    """The approving verdict envelope's uid (what the execute stage is triggered by)."""
    executor: str = ""
    executed: int = 0

    def view(self) -> PlanView:
        return PlanView(
            plan=self.uid.hex(),
            cycle=self.cycle.hex(),
            status=self.status,
            proposer=self.proposer,
            plan_type=self.plan_type,
            created=self.created,
            legitimator=self.legitimator,
            reason=self.reason,
            decided=self.decided,
            executor=self.executor,
            executed=self.executed,
        )


OnChange = Callable[[str, Any], None]


def _nothing(kind: str, view: Any) -> None:
    return None


class Registry:
    def __init__(
        self,
        system: str,
        *,
        metrics: Metrics | None = None,
        history: int = 200,
        cycle_timeout: float = 10.0,
        max_components: int = 1024,
        tail: int = 200,
        on_change: OnChange = _nothing,
        now: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
        rejected_event: str = "",
    ) -> None:
        """``history``: cycles kept; ``cycle_timeout``: seconds after its first record
        at which a cycle with something outstanding counts as stalled; ``tail``: log
        lines, plans, verdicts and alerts kept (each); ``rejected_event``: the full key
        of the ``plan-rejected`` event (an execute-stage call that sent it refused the
        plan)."""
        if history < 1 or tail < 1 or max_components < 1:
            raise ValueError("history, tail and max_components must be >= 1")
        if cycle_timeout <= 0:
            raise ValueError(f"cycle_timeout must be > 0 s, got {cycle_timeout}")
        self.system = system
        self.metrics = metrics or Metrics()
        self.history = history
        self.cycle_timeout = cycle_timeout
        self.max_components = max_components
        self.on_change = on_change
        self.now = now
        self.monotonic = monotonic
        self.rejected_event = rejected_event
        self.components: dict[str, ComponentView] = {}
        self.cycles: OrderedDict[bytes, _Cycle] = OrderedDict()
        self.executed_kept: deque[_Cycle] = deque(maxlen=min(history, EXECUTED_KEPT))
        """Cycles in which a plan reached the execute stage, kept past the history (most
        cycles of a loop end at the analysis: plans would soon fall out of it)."""
        self.plans: OrderedDict[bytes, _Plan] = OrderedDict()
        self._by_verdict: dict[bytes, bytes] = {}
        """Approving verdict envelope uid -> plan uid."""
        self.trust_outputs: dict[str, TrustOutputView] = {}
        self.verdicts: deque[TrustVerdictView] = deque(maxlen=tail)
        self.log_tail: deque[LogView] = deque(maxlen=tail)
        self.alerts: deque[AlertView] = deque(maxlen=tail)
        self.tail = tail
        self._due: deque[tuple[float, bytes]] = deque()
        self._throttle = Throttle()
        self._missed: dict[str, int] = {}
        self.ignored: set[str] = set()
        """Names that are not components (the manager itself)."""

    # -- components ---------------------------------------------------------------------

    def _component(self, name: str) -> ComponentView | None:
        comp = self.components.get(name)
        if comp is None:
            if name in self.ignored:
                return None
            if len(self.components) >= self.max_components and not self._forget_gone():
                self._reject("component", f"more than {self.max_components} components")
                return None
            comp = self.components[name] = ComponentView(
                name=name, state=ComponentState.STARTING.value, alive=False
            )
        return comp

    def _forget_gone(self) -> bool:
        for name, comp in self.components.items():
            if not comp.alive:
                del self.components[name]
                self._missed.pop(name, None)
                return True
        return False

    def _changed(self, comp: ComponentView) -> None:
        comp.updated = self.now()
        self._gauge()
        self.on_change("component", comp)

    def _gauge(self) -> None:
        counts = dict.fromkeys((s.value for s in ComponentState), 0)
        for c in self.components.values():
            counts[c.state] = counts.get(c.state, 0) + 1
        for state, n in counts.items():
            self.metrics.components.labels(state=state).set(n)

    def liveliness(self, name: str, alive: bool) -> None:
        """The liveliness token of ``name`` came (``alive``) or went."""
        comp = self._component(name)
        if comp is None:
            return
        if alive:
            if comp.alive and comp.state != ComponentState.GONE:
                return
            comp.alive = True
            comp.state = ComponentState.STARTING.value
            comp.answers = False
            self._missed.pop(name, None)
        else:
            if not comp.alive:
                return
            comp.alive = False
            comp.state = ComponentState.GONE.value
            comp.inbox = 0
            where = f" on compute node {comp.compute_node}" if comp.compute_node else ""
            self.metrics.gone.labels(component=self.metrics.label("component", name)).inc()
            self._alert(
                "gone",
                name,
                f"component {name}{where} is gone (its liveliness token went away: it "
                "stopped, crashed or was cut off)",
            )
        self._changed(comp)

    def unanswered(self, answered: set[str], *, after: int = 2) -> None:
        """A status poll got no answer from the alive components not in ``answered``:
        after ``after`` such polls one that never answered is shown ``alive`` (a process
        with a liveliness token but no admin verbs: the knowledge service, say)."""
        for comp in self.components.values():
            if not comp.alive or comp.answers or comp.name in answered:
                continue
            n = self._missed[comp.name] = self._missed.get(comp.name, 0) + 1
            if n == after and comp.state == ComponentState.STARTING:
                comp.state = "alive"
                self._changed(comp)

    def status(self, st: ComponentStatus) -> None:
        """A component's answer to ``status`` (or to another verb that carries one)."""
        comp = self._component(st.name)
        if comp is None:
            return
        before = msgspec.structs.astuple(comp)
        old_state = comp.state
        old_restarts = comp.restarts
        state = st.state.value
        if not comp.alive and comp.state == ComponentState.GONE and comp.answers:
            # an answer in flight when its token went: it stays gone until the token is back
            return
        comp.alive = True
        comp.answers = True
        comp.state = state
        comp.compute_node = st.compute_node
        comp.stage = st.stage
        comp.implementation = st.implementation
        comp.last_cycle = st.last_cycle or comp.last_cycle
        comp.last_call = max(st.last_call, comp.last_call)
        comp.p50_ms = st.p50_ms
        comp.p99_ms = st.p99_ms
        comp.inbox = st.inbox
        comp.received = st.received
        comp.handled = st.handled
        comp.failed = st.failed
        comp.rejected = st.rejected
        comp.dropped = st.dropped
        comp.restarts = st.restarts
        comp.swaps = st.swaps
        comp.paused_policy = _cut(st.paused_policy)
        if state == ComponentState.FAILED and old_state != ComponentState.FAILED:
            self.metrics.failed.labels(component=self.metrics.label("component", st.name)).inc()
            self._alert(
                "failed",
                st.name,
                f"component {st.name}: its last handler call failed ({st.failed} failed "
                "call(s) in all); see its log",
            )
        if st.restarts > old_restarts and old_state != ComponentState.STARTING:
            self._log("INFO", st.name, f"{st.name} restarted ({st.restarts} restart(s))", "manager")
        if msgspec.structs.astuple(comp) != before:
            self._changed(comp)

    # -- cycles ---------------------------------------------------------------------------

    def _cycle(self, uid: bytes) -> _Cycle:
        cyc = self.cycles.get(uid)
        if cyc is None:
            now = self.monotonic()
            cyc = self.cycles[uid] = _Cycle(uid=uid, due=now + self.cycle_timeout)
            self._due.append((cyc.due, uid))
            self.metrics.cycles.inc()
            while len(self.cycles) > self.history:
                _, old = self.cycles.popitem(last=False)  # its deadline entry is skipped
                if old.executed:
                    self.executed_kept.append(old)  # rap trace --executed finds it later
        return cyc

    def trace(self, rec: StageTrace) -> None:
        """A ``StageTrace`` record."""
        cyc = self._cycle(rec.cycle)
        cyc.last_activity = self.monotonic()
        ident = (rec.node, rec.trigger)
        call = cyc.calls.get(ident)
        if call is None:
            if len(cyc.calls) >= MAX_CALLS:
                self._reject("trace", f"cycle {cyc.hex} has more than {MAX_CALLS} calls")
                return
            stage = rec.stage.value if rec.stage is not None else ""
            call = cyc.calls[ident] = _Call(
                node=rec.node,
                handler=_cut(rec.handler, 200),
                stage=stage,
                trigger=rec.trigger,
                trigger_key=rec.trigger_key,
            )
            if stage and stage not in cyc.stages:
                cyc.stages.append(stage)
        if rec.started:
            call.started = True
            call.start = rec.ts
        if rec.ended:
            call.ended = True
            call.duration_ns = rec.duration_ns
            if rec.phase == "end" and not call.start:
                call.start = rec.ts - rec.duration_ns
            call.ok = rec.ok
            call.error = _cut(rec.error)
            call.sent = [_cut(k, 300) for k in rec.sent[:64]]
            if not rec.ok:
                self.metrics.handler_failures.labels(
                    component=self.metrics.label("component", rec.node)
                ).inc()
                if self._throttle.hit(f"failed {rec.node}"):
                    self._log(
                        "ERROR",
                        rec.node,
                        f"{rec.node}.{call.handler} failed in cycle {cyc.hex[:12]}: "
                        f"{call.error or 'no reason given'}",
                        "manager",
                    )
            if call.stage == "execute":
                self._executed(cyc, call)
        comp = self.components.get(rec.node)
        if comp is not None and rec.ended:
            comp.last_cycle = cyc.hex
            comp.last_call = max(comp.last_call, call.end)
        self._cycle_changed(cyc)

    def _executed(self, cyc: _Cycle, call: _Call) -> None:
        plan_uid = self._by_verdict.get(call.trigger)
        plan = self.plans.get(plan_uid) if plan_uid is not None else None
        if plan is None or plan.status not in ("approved",):
            return
        if not call.ok or (self.rejected_event and self.rejected_event in call.sent):
            plan.status = "refused"
            plan.reason = plan.reason or (call.error or "the execute stage's gate refused it")
            self.metrics.plans.labels(outcome="refused").inc()
        else:
            plan.status = "executed"
            self.metrics.plans.labels(outcome="executed").inc()
        plan.executor = call.node
        plan.executed = call.end
        self.on_change("plan", plan.view())

    def event(
        self,
        name: str,
        key: str,
        uid: bytes,
        source: str,
        ts: int,
        cycle: bytes | None,
        cause: bytes | None,
    ) -> None:
        """An event envelope (its body, when it is a plan message, goes to
        :meth:`proposal` or :meth:`verdict`)."""
        if cycle is None:
            return
        cyc = self._cycle(cycle)
        if len(cyc.sent) >= MAX_CALLS:
            return
        cyc.sent[uid] = _Sent(uid=uid, key=key, name=name, source=source, ts=ts, cause=cause)
        cyc.last_activity = self.monotonic()

    def proposal(self, cycle: bytes | None, prop: PlanProposal[Any]) -> None:
        """A ``new-plan`` event."""
        plan = self.plans.get(prop.plan_uid)
        if plan is not None and plan.proposer:
            return  # a replay, or seen already
        if plan is None:
            plan = self._new_plan(prop.plan_uid, cycle or b"")
        plan.proposer = prop.proposer
        plan.plan_type = _cut(prop.plan_type, 200)
        plan.created = prop.created
        self.metrics.plans.labels(outcome="proposed").inc()
        self.on_change("plan", plan.view())
        if cycle is not None:
            self._cycle_changed(self._cycle(cycle))

    def _new_plan(self, uid: bytes, cycle: bytes) -> _Plan:
        plan = self.plans[uid] = _Plan(uid=uid, cycle=cycle)
        while len(self.plans) > self.tail:
            self._drop_plan(next(iter(self.plans)))
        if cycle:
            cyc = self.cycles.get(cycle) or self._cycle(cycle)
            if uid not in cyc.plans:
                cyc.plans.append(uid)
        return plan

    def _drop_plan(self, uid: bytes) -> None:
        plan = self.plans.pop(uid, None)
        if plan is not None and plan.verdict_uid:
            self._by_verdict.pop(plan.verdict_uid, None)

    def verdict(
        self, cycle: bytes | None, env_uid: bytes, source: str, v: Verdict[Any], *, rejected: bool
    ) -> None:
        """A ``verdict`` event, or a ``plan-rejected`` one (``rejected``)."""
        plan = self.plans.get(v.plan_uid)
        if plan is None:
            plan = self._new_plan(v.plan_uid, cycle or b"")
        if rejected:
            # the planner's cue: from the legitimator (a rejection it also gave as its
            # verdict) or from the execute stage's gate (refused an approved plan)
            if plan.status == "approved" or plan.status == "executed":
                plan.status = "refused"
                plan.reason = _cut(v.reason) or "refused at the execute stage"
                self.metrics.plans.labels(outcome="refused").inc()
            elif plan.status == "proposed":
                plan.status = "rejected"
                plan.reason = _cut(v.reason)
                plan.legitimator = v.legitimator
                plan.decided = v.ts
                self.metrics.plans.labels(outcome="rejected").inc()
            else:
                return
        else:
            if plan.status != "proposed":
                return  # decided already (a second legitimator, a replay)
            plan.legitimator = v.legitimator
            plan.decided = v.ts
            plan.reason = _cut(v.reason)
            if v.approved:
                plan.status = "approved"
                plan.verdict_uid = env_uid
                self._by_verdict[env_uid] = plan.uid
                self.metrics.plans.labels(outcome="approved").inc()
                # the execute stage's record may have come first (another subscription)
                cyc = self.cycles.get(cycle) if cycle is not None else None
                if cyc is not None:
                    for call in cyc.calls.values():
                        if call.trigger == env_uid and call.stage == "execute" and call.ended:
                            self._executed(cyc, call)
                            break
            else:
                plan.status = "rejected"
                self.metrics.plans.labels(outcome="rejected").inc()
        self.on_change("plan", plan.view())
        if cycle is not None and cycle in self.cycles:
            self._cycle_changed(self.cycles[cycle])

    def outstanding(self, cyc: _Cycle) -> list[str]:
        """What the cycle still owes (see the module's doc)."""
        out = [
            f"{call.node}.{call.handler} started and has not ended"
            for call in cyc.calls.values()
            if call.started and not call.ended
        ]
        for uid in cyc.plans:
            plan = self.plans.get(uid)
            if plan is None:
                continue
            if plan.status == "proposed":
                out.append(f"plan {uid.hex()[:12]} of {plan.proposer or '?'} has no verdict")
            elif plan.status == "approved":
                out.append(
                    f"plan {uid.hex()[:12]} was approved by {plan.legitimator or '?'} and no "
                    "execute stage took it"
                )
        return out

    def cycle_state(self, cyc: _Cycle) -> tuple[str, list[str]]:
        out = self.outstanding(cyc)
        if cyc.stalled:
            return "stalled", out
        if out:
            return "open", out
        return ("executed" if cyc.executed else "done"), out

    def cycle_view(self, cyc: _Cycle) -> CycleView:
        state, out = self.cycle_state(cyc)
        calls = sorted(cyc.calls.values(), key=lambda c: c.start)
        return CycleView(
            cycle=cyc.hex,
            state=state,
            start=cyc.start,
            end=cyc.end,
            stages=list(cyc.stages),
            calls=[c.view() for c in calls[:32]],
            plans=[p.hex() for p in cyc.plans],
            outstanding=out,
        )

    def _cycle_changed(self, cyc: _Cycle) -> None:
        self.on_change("cycle", cyc)

    def next_due(self) -> float | None:
        """When the next cycle deadline falls (``monotonic()``), or None."""
        return self._due[0][0] if self._due else None

    def check_due(self) -> int:
        """Check the cycles whose deadline has passed; the number found stalled."""
        now = self.monotonic()
        stalled = 0
        while self._due and self._due[0][0] <= now:
            _, uid = self._due.popleft()
            cyc = self.cycles.get(uid)
            if cyc is None or cyc.checked:
                continue
            cyc.checked = True
            out = self.outstanding(cyc)
            if not out:
                continue
            cyc.stalled = True
            stalled += 1
            self.metrics.stalled.inc()
            self._alert(
                "stalled",
                cyc.hex,
                f"cycle {cyc.hex[:12]} has not completed {self.cycle_timeout:g} s after it "
                f"started: {'; '.join(out[:3])}",
            )
            self._cycle_changed(cyc)
        return stalled

    # -- trust, logs ----------------------------------------------------------------------

    def trust_output(self, out: TrustOutput) -> None:
        if out.stream not in self.trust_outputs and len(self.trust_outputs) >= 1024:
            self._reject("trust", "more than 1024 trust streams")
            return
        view = TrustOutputView(
            stream=_cut(out.stream, 300),
            tick=out.tick,
            ts=out.ts,
            value=short_json(out.value),
            deferred=out.deferred,
            false=out.value is False,
        )
        self.trust_outputs[out.stream] = view
        self.on_change("trust", view)

    def trust_verdict(self, v: TrustVerdict) -> None:
        view = TrustVerdictView(
            stream=_cut(v.stream, 300),
            tick=v.tick,
            ts=v.ts or self.now(),
            value=short_json(v.value),
            kind=v.kind,
            expr=_cut(v.expr),
            message=_cut(v.message),
            severity=v.severity or "",
            because=[
                CauseView(
                    expr=_cut(c.expr, 500),
                    value="⊥" if c.deferred else short_json(c.value),
                    depth=c.depth,
                    input=c.input or "",
                    input_tick=c.input_tick,
                )
                for c in v.because[:32]
            ],
            truncated=v.truncated or len(v.because) > 32,
        )
        self.verdicts.append(view)
        self.metrics.trust.labels(stream=self.metrics.label("stream", v.stream)).inc()
        why = "; ".join(f"{c.expr} = {c.value}" for c in view.because[:3])
        what = (
            f"trigger {view.stream} fired: {view.message or view.expr}"
            if v.kind == "trigger"
            else f"trust verdict false: {view.stream} = {view.value} at tick {v.tick}"
        )
        self.on_change("verdict", view)
        self._alert("trust", view.stream, what + (f" (because {why})" if why else ""))

    def log_record(self, source: str, rec: LogRecord) -> None:
        text = rec.message + (f"\n{rec.exc}" if rec.exc else "")
        self._log(rec.level, rec.component or rec.process or source, text, "log", ts=rec.ts)

    def rejection(self, rec: Rejection) -> None:
        count = f" ({rec.count} samples)" if rec.count > 1 else ""
        src = f" from {rec.source}" if rec.source else ""
        self._log(
            "WARNING",
            rec.node,
            f"rejected{count} on {rec.key}{src}: {rec.reason}",
            "rejection",
            ts=rec.ts,
        )

    def other_log(self, source: str, type_name: str) -> None:
        self._log("INFO", source, f"a {type_name} record", "other")

    def _log(self, level: str, source: str, text: str, kind: str, ts: int = 0) -> None:
        view = LogView(
            ts=ts or self.now(),
            level=_cut(level, 16),
            source=_cut(source, 200),
            text=_cut(text),
            kind=kind,
        )
        self.log_tail.append(view)
        self.on_change("log", view)

    def _alert(self, kind: str, subject: str, message: str) -> None:
        view = AlertView(ts=self.now(), kind=kind, subject=subject, message=message)
        self.alerts.append(view)
        self.metrics.alerts.labels(kind=kind).inc()
        level = logging.INFO if kind == "trust" else logging.WARNING
        if self._throttle.hit(f"alert {kind} {subject}"):
            log.log(level, "watch %s: %s", kind, message)
        self.on_change("alert", view)
        self._log("WARNING", "manager", message, "manager")

    def _reject(self, kind: str, reason: str) -> None:
        self.metrics.unreadable.labels(kind=kind).inc()
        if self._throttle.hit(f"reject {kind}"):
            log.warning("manager: ignored a %s record: %s", kind, reason)

    def unreadable(self, kind: str, key: str, reason: str) -> None:
        """A sample or reply the manager could not read: counted and logged (rate-limited)."""
        self.metrics.unreadable.labels(kind=kind).inc()
        count = self._throttle.hit(f"unreadable {key}")
        if count:
            log.warning("manager: could not read %d sample(s) on %s: %s", count, key, reason)

    # -- queries --------------------------------------------------------------------------

    def snapshot(self, cycles: int = 40) -> dict[str, Any]:
        """Everything the dashboard shows, as JSON-able data."""
        recent = list(self.cycles.values())[-cycles:]
        return {
            "system": self.system,
            "components": [
                msgspec.to_builtins(c) for c in sorted(self.components.values(), key=_by_node)
            ],
            "cycles": [msgspec.to_builtins(self.cycle_view(c)) for c in recent],
            "plans": [msgspec.to_builtins(p.view()) for p in self.plans.values()],
            "trust": [msgspec.to_builtins(v) for v in self.trust_outputs.values()],
            "verdicts": [msgspec.to_builtins(v) for v in self.verdicts],
            "log": [msgspec.to_builtins(v) for v in self.log_tail],
            "alerts": [msgspec.to_builtins(v) for v in self.alerts],
            "counters": self.counters(),
        }

    def counters(self) -> dict[str, float]:
        """The watches' totals, for the page (the same numbers as ``/metrics``)."""
        out: dict[str, float] = {}
        for family in ("alerts", "plans"):
            metric = getattr(self.metrics, family)
            for sample in _samples(metric):
                labels = sample.labels
                name = labels.get("kind") or labels.get("outcome") or ""
                out[f"{family}.{name}"] = sample.value
        out["cycles"] = _total(self.metrics.cycles)
        out["cycles.stalled"] = _total(self.metrics.stalled)
        return out

    def find(self, digits: str, *, suffix: bool = False) -> list[_Cycle]:
        """Cycles in the history whose hex uid starts (``suffix``: ends) with ``digits``,
        newest first."""
        d = digits.lower()
        every = [*reversed(self.cycles.values()), *reversed(self.executed_kept)]
        if suffix:
            return [c for c in every if c.hex.endswith(d)]
        return [c for c in every if c.hex.startswith(d)]

    def last_complete(self, *, executed: bool = False, quiet: float = 0.5) -> _Cycle | None:
        """The newest cycle with nothing outstanding and no record for ``quiet`` s (or
        that reached the execute stage), that reached execute with ``executed``."""
        now = self.monotonic()
        for cyc in reversed(self.cycles.values()):
            if executed and not cyc.executed:
                continue
            if cyc.stalled or self.outstanding(cyc):
                continue
            if cyc.executed or now - cyc.last_activity >= quiet:
                return cyc
        if executed and self.executed_kept:
            return self.executed_kept[-1]
        return None

    def chain(self, cyc: _Cycle) -> CycleTrace:
        """The causal chain of ``cyc``: each call under the call that sent its sample."""
        sent = cyc.sent
        calls = list(cyc.calls.values())
        by_trigger: dict[bytes, list[_Call]] = {}
        for c in calls:
            by_trigger.setdefault(c.trigger, []).append(c)
        children: dict[int, list[_Call]] = {}
        roots: list[_Call] = []
        for c in calls:
            env = sent.get(c.trigger)
            parent = None
            if env is not None and env.cause is not None:
                for p in by_trigger.get(env.cause, []):
                    if p.node == env.source:
                        parent = p
                        break
            if parent is None:
                roots.append(c)
            else:
                children.setdefault(id(parent), []).append(c)
        start = cyc.start
        steps: list[TraceStep] = []

        def walk(items: list[_Call], depth: int) -> None:
            for c in sorted(items, key=lambda c: c.start):
                env = sent.get(c.trigger)
                trigger_ts = env.ts if env is not None else 0
                if not trigger_ts and c.trigger == cyc.uid:
                    trigger_ts = uid_time_ns(c.trigger)
                steps.append(
                    TraceStep(
                        depth=depth,
                        node=c.node,
                        handler=c.handler,
                        stage=c.stage,
                        trigger=c.trigger.hex(),
                        trigger_key=c.trigger_key,
                        trigger_source=env.source if env is not None else "",
                        trigger_ts=trigger_ts,
                        start=c.start,
                        offset_ms=round((c.start - start) / 1e6, 3) if c.start else 0.0,
                        wait_ms=(
                            round((c.start - trigger_ts) / 1e6, 3)
                            if trigger_ts and c.start
                            else None
                        ),
                        duration_ms=round(c.duration_ns / 1e6, 3),
                        ended=c.ended,
                        ok=c.ok,
                        error=c.error,
                        sent=list(c.sent),
                    )
                )
                if len(steps) < MAX_CALLS:
                    walk(children.get(id(c), []), depth + 1)

        walk(roots, 0)
        state, out = self.cycle_state(cyc)
        end = cyc.end
        root_key = next((c.trigger_key for c in calls if c.trigger == cyc.uid), "")
        return CycleTrace(
            system=self.system,
            cycle=cyc.hex,
            state=state,
            start=start,
            end=end,
            total_ms=round((end - start) / 1e6, 3) if end and start else 0.0,
            root_key=root_key,
            executed=cyc.executed,
            steps=steps,
            plans=[self.plans[p].view() for p in cyc.plans if p in self.plans],
            outstanding=out,
        )


def _by_node(c: ComponentView) -> tuple[str, str]:
    return (c.compute_node or "~", c.name)


def _samples(metric: Counter) -> Iterator[Any]:
    for fam in metric.collect():
        for sample in fam.samples:
            if sample.name.endswith("_total"):
                yield sample


def _total(metric: Counter) -> float:
    return float(sum(s.value for s in _samples(metric)))
