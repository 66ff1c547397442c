"""Digital twins that a Legitimate stage asks before a plan may act.

A twin answers one question: *if this plan ran now, what would happen?* It answers from
what the robot (or the system) knows - its belief - never from ground truth, and says how
thin that belief is. Two kinds fit one interface:

- ``TwinKind.SIMULATION``: runs the plan forward from the current belief over a horizon
  (the lidar case: a spin plan rolled out from the robot's pose, velocity, the obstacles it
  has seen and its current lidar mask);
- ``TwinKind.REPLAY``: replays recorded history through the candidate (the ship-motion
  case: a retrained model replayed over the history since the anomaly, against the
  running model).

A :class:`Twin` is synchronous and CPU-bound; :func:`ask` runs it in a worker thread so the
event loop keeps serving, times it, and returns its :class:`TwinReport`. A report's
:attr:`~TwinReport.verdict` is what a ``check()`` returns: ``None`` approves, else the first
rejecting finding as ``"<code>: <message>"`` - what ``plan-rejected`` then names::

    @legitimate(node)
    async def check(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        report = await ask(twin, proposal.plan, await belief_of(ctx))
        return report.verdict
"""

from __future__ import annotations

import enum
import time
from typing import Literal, Protocol, TypeVar

import anyio.to_thread
import msgspec

__all__ = ["BeliefQuality", "Finding", "Twin", "TwinKind", "TwinReport", "ask"]

P = TypeVar("P", contravariant=True)
B = TypeVar("B", contravariant=True)


class TwinKind(enum.Enum):
    SIMULATION = "simulation"
    """Runs the plan forward from the current belief over a horizon."""
    REPLAY = "replay"
    """Replays recorded history through the candidate (and what runs now)."""


class Finding(msgspec.Struct, frozen=True, kw_only=True):
    """Something the twin found: ``reject`` findings make the verdict, ``note`` ones are
    information (a thin belief, a near miss within the limits)."""

    code: str
    """Short and stable, for counting: ``collision``, ``clearance``, ``spin-too-long``..."""
    message: str
    """For a person: what, where and when (seconds into the horizon)."""
    severity: Literal["reject", "note"] = "reject"
    at_s: float | None = None
    """Seconds into the horizon (None: not tied to a moment)."""


class BeliefQuality(msgspec.Struct, frozen=True, kw_only=True):
    """How much the twin had to go on."""

    thin: bool = False
    """True when the belief does not cover what the rollout needed (an unseen sector on
    the way, too little history): an approval then means less."""
    notes: list[str] = msgspec.field(default_factory=list)


class TwinReport(msgspec.Struct, frozen=True, kw_only=True):
    kind: TwinKind
    horizon_s: float
    """Seconds simulated (SIMULATION) or of history replayed (REPLAY)."""
    findings: list[Finding] = msgspec.field(default_factory=list)
    metrics: dict[str, float] = msgspec.field(default_factory=dict)
    """What the rollout measured: ``min_clearance_m``, ``spin_s``, ``progress_m``,
    ``candidate_error_m``..."""
    belief: BeliefQuality = msgspec.field(default_factory=BeliefQuality)
    elapsed_s: float = 0.0
    """Wall time the rollout took (set by :func:`ask`)."""

    @property
    def rejections(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == "reject"]

    @property
    def verdict(self) -> str | None:
        """None when nothing rejects the plan, else ``"<code>: <message>"`` of the first
        rejecting finding."""
        for f in self.findings:
            if f.severity == "reject":
                return f"{f.code}: {f.message}"
        return None


class Twin(Protocol[P, B]):
    """A digital twin of one case: ``rollout(plan, belief)`` without side effects."""

    kind: TwinKind

    def rollout(self, plan: P, belief: B) -> TwinReport: ...


async def ask(twin: Twin[P, B], plan: P, belief: B) -> TwinReport:
    """``twin.rollout(plan, belief)`` in a worker thread, its wall time in the report."""
    began = time.perf_counter()
    report = await anyio.to_thread.run_sync(twin.rollout, plan, belief)
    return msgspec.structs.replace(report, elapsed_s=time.perf_counter() - began)
