"""A probe client that writes a numbered sequence of durable knowledge writes while
faults are injected, and checks afterwards which of them the service still holds.

Write ``n`` goes to its own key ``faults/<run>/<n>`` (value ``n``) with
``KnowledgeClient.write(..., durable=True)``: its outcome is ``ok`` (acknowledged: the
service stored it), ``refused`` (the service answered that it did not store it:
``unavailable``, past its budget, ...), ``unknown`` (the service could not tell, a
Redis that failed mid-write) or ``no answer`` (no service answered within the client's
timeout: stored or not, the client cannot know). Afterwards one listing of
``faults/<run>/**`` tells which writes are stored: an acknowledged one that is missing
is *lost*; a refused one that is present was *applied although reported failed*."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import anyio
from rap_schemas import keys
from rap_sdk import FabricError, KnowledgeClient, KnowledgeError, ZenohConfig, ZenohFabric

from .common import SYSTEM, ScenarioError

__all__ = ["Probe", "ProbeResult"]

PAUSE = 0.02
"""Seconds between two writes (each waits for its answer first)."""


@dataclass
class ProbeResult:
    outcomes: dict[int, str] = field(default_factory=dict)
    """Write number -> ok, refused, unknown, no answer."""
    at: dict[int, float] = field(default_factory=dict)
    """Write number -> time.monotonic() when its answer came."""
    reasons: Counter[str] = field(default_factory=Counter)
    stored: set[int] = field(default_factory=set)

    def check(self) -> dict[str, Any]:
        acked = {n for n, o in self.outcomes.items() if o == "ok"}
        refused = {n for n, o in self.outcomes.items() if o == "refused"}
        unsure = {n for n, o in self.outcomes.items() if o in ("unknown", "no answer")}
        lost = sorted(acked - self.stored)
        applied = sorted(refused & self.stored)
        return {
            "writes": len(self.outcomes),
            "acknowledged": len(acked),
            "outcomes": dict(Counter(self.outcomes.values())),
            "failure_reasons": dict(self.reasons.most_common(8)),
            "acknowledged_lost": len(lost),
            "lost_numbers": lost[:50],
            "refused_but_applied": len(applied),
            "refused_but_applied_numbers": applied[:50],
            "unsure_and_stored": len(unsure & self.stored),
            "unsure_and_not_stored": len(unsure - self.stored),
        }


class Probe:
    """``async with Probe(endpoint, run="kills"):`` writes until the block ends; then
    ``await probe.verify()`` lists what the service holds."""

    def __init__(self, endpoint: str, *, run: str, timeout: float = 2.0) -> None:
        self.endpoint = endpoint
        self.prefix = f"faults/{run}"
        self.timeout = timeout
        self.result = ProbeResult()
        self._stack: Any = None
        self._fabric: ZenohFabric | None = None
        self._kb: KnowledgeClient | None = None
        self._tg: Any = None
        self._answered = anyio.Event()

    async def __aenter__(self) -> Probe:
        conf = ZenohConfig(mode="client", listen=[], connect=[self.endpoint])
        self._fabric = ZenohFabric(conf)
        await self._fabric.__aenter__()
        try:
            await self._fabric.wait_matched(
                keys.kb(SYSTEM, f"{self.prefix}/0"), queryable=True, timeout=30
            )
        except FabricError as exc:
            await self._fabric.__aexit__(None, None, None)
            raise ScenarioError(f"no knowledge service reachable for the probe: {exc}") from None
        self._kb = KnowledgeClient(
            fabric=self._fabric, system=SYSTEM, writer="faults-probe", timeout=self.timeout
        )
        await self._kb.__aenter__()
        self._tg = anyio.create_task_group()
        await self._tg.__aenter__()
        self._tg.start_soon(self._write)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._tg.cancel_scope.cancel()
        await self._tg.__aexit__(None, None, None)

    async def close(self) -> None:
        if self._kb is not None:
            await self._kb.__aexit__(None, None, None)
        if self._fabric is not None:
            await self._fabric.__aexit__(None, None, None)

    async def _write(self) -> None:
        assert self._kb is not None
        n = 0
        while True:
            outcome = "ok"
            # the outcome is only known once the call returns: shielded, so that the
            # block ending does not leave a write whose outcome nobody knows
            with anyio.CancelScope(shield=True):
                try:
                    await self._kb.write(f"{self.prefix}/{n}", n, durable=True)
                except KnowledgeError as exc:
                    text = str(exc)
                    if text.startswith(("knowledge service did not answer", "no knowledge")):
                        outcome = "no answer"
                    elif exc.code == "unknown":
                        outcome = "unknown"
                    else:
                        outcome = "refused"
                    self.result.reasons[f"{outcome}: {exc.code}: {text[:90]}"] += 1
            self.result.outcomes[n] = outcome
            self.result.at[n] = time.monotonic()
            self._answered.set()
            self._answered = anyio.Event()
            n += 1
            await anyio.sleep(PAUSE)  # the write rate

    async def acknowledged_after(self, n: int, timeout: float) -> float | None:
        """When the first write after number ``n`` was acknowledged (None: none within
        ``timeout`` s)."""
        with anyio.move_on_after(timeout):
            while True:
                answered = self._answered
                for m, outcome in self.result.outcomes.items():
                    if m > n and outcome == "ok":
                        return self.result.at[m]
                await answered.wait()
        return None

    def failed_between(self, t0: float, t1: float) -> int:
        return sum(
            1 for n, o in self.result.outcomes.items() if o != "ok" and t0 <= self.result.at[n] < t1
        )

    async def verify(self, timeout: float = 60.0) -> dict[str, Any]:
        """List what the service holds (retried until it answers) and check."""
        assert self._kb is not None
        last = ""
        stored: list[str] | None = None
        with anyio.move_on_after(timeout):
            while stored is None:
                try:
                    stored = await self._kb.keys(f"{self.prefix}/**")
                except KnowledgeError as exc:
                    last = str(exc)
                    await anyio.sleep(0.5)  # the service is not back yet: ask again
        if stored is None:
            raise ScenarioError(f"the knowledge service did not list the probe's keys: {last}")
        self.result.stored = {
            int(k.rsplit("/", 1)[1]) for k in stored if k.rsplit("/", 1)[1].isdigit()
        }
        return self.result.check()
