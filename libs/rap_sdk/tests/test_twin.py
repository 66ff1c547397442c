"""rap_sdk.twin: the interface a Legitimate stage asks, for simulation and replay twins alike."""

from __future__ import annotations

import threading
import time

import anyio
import pytest
from rap_sdk.twin import BeliefQuality, Finding, TwinKind, TwinReport, ask

pytestmark = pytest.mark.anyio


class SlowTwin:
    kind = TwinKind.SIMULATION

    def __init__(self) -> None:
        self.thread: int | None = None

    def rollout(self, plan: float, belief: float) -> TwinReport:
        self.thread = threading.get_ident()
        time.sleep(0.05)  # CPU-bound work stands in: it must not hold the event loop
        findings = [Finding(code="note-only", message="close", severity="note")]
        if plan > belief:
            findings += [
                Finding(code="collision", message=f"at {belief} m", at_s=1.5),
                Finding(code="clearance", message="0.01 m"),
            ]
        return TwinReport(
            kind=self.kind, horizon_s=8.0, findings=findings, belief=BeliefQuality(thin=plan < 0)
        )


def test_the_first_rejecting_finding_is_the_verdict() -> None:
    report = SlowTwin().rollout(2.0, 1.0)
    assert report.verdict == "collision: at 1.0 m"
    assert [f.code for f in report.rejections] == ["collision", "clearance"]
    assert SlowTwin().rollout(0.5, 1.0).verdict is None  # a note alone approves


async def test_ask_runs_the_rollout_off_the_event_loop_and_times_it() -> None:
    twin = SlowTwin()
    ticks = 0

    async def tick() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await anyio.sleep(0.005)

    async with anyio.create_task_group() as tg:
        tg.start_soon(tick)
        report = await ask(twin, -1.0, 1.0)
        tg.cancel_scope.cancel()
    assert twin.thread != threading.get_ident()
    assert ticks >= 3, "the loop kept running while the twin worked"
    assert report.elapsed_s >= 0.05
    assert report.belief.thin
    assert report.kind is TwinKind.SIMULATION
