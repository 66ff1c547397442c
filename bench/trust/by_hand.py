"""The two bench specs written out by hand in Python, and the traces they run on.

Each hand-written monitor computes exactly what its spec does on the inputs it sees:
inputs are sampled and held (NoVal until a first value), lifted streams have no value
until all their operands have had one, ``x[k]`` is x's held value k ticks ago (⊥ before
that: here ``None`` in the history), ``default`` replaces ⊥. It keeps the same per-cycle
map as the spec (mutated in place, where the spec's values are immutable and copied). It
returns the same :class:`~trust_checker.engine.Output` rows the runner does (that is
the runner's contract, and what every transport consumes), but checks no input types
and no Int overflow: the traces stay far from 2**63, and give every input its declared
type.
"""

from __future__ import annotations

import random
from typing import Any

import immutables
from trust_checker.engine import Output
from trust_checker.values import BOTTOM, NOVAL, MapV

STAGES = ("monitor", "analyse", "plan", "legitimate", "execute")
RANK = {s: i for i, s in enumerate(STAGES)}
KEEP = 256
"""The spec's memory: the highest rank of the last KEEP cycles."""


class StageOrderByHand:
    """The MAPLE-K library's stage order
    (services/trust_checker/src/trust_checker/specs/maplek/stage_order.dsrv), by hand.

    The spec keeps ``reached`` (cycle -> highest rank started in it) and ``order`` (the
    cycles in the order first seen, oldest evicted past KEEP). Both gain a cycle at the
    same record and lose the oldest at the same record, so one dict in insertion order
    is both here, updated in place where the spec builds new values."""

    __slots__ = ("cycle", "phase", "reached", "stage", "tick")

    def __init__(self) -> None:
        self.stage: str | None = None
        self.phase: str | None = None
        self.cycle: str | None = None
        self.reached: dict[str, int] = {}
        self.tick = 0

    def step(self, inputs: dict[str, Any], ts_ns: int | None = None) -> list[Output]:
        tick = self.tick
        self.tick = tick + 1
        v = inputs.get("stage")
        if v is not None:
            self.stage = v
        v = inputs.get("phase")
        if v is not None:
            self.phase = v
        v = inputs.get("cycle")
        if v is not None:
            self.cycle = v
        stage, phase, cycle = self.stage, self.phase, self.cycle
        if stage is None or phase is None or cycle is None:
            return []  # stage_order_ok (and the bookkeeping) have no value yet
        rank = RANK.get(stage, -1)
        starting = phase == "start" and rank >= 0
        reached = self.reached
        highest = reached.get(cycle, -1)
        ok = not starting or rank == 0 or highest >= rank - 1
        if starting:
            known = cycle in reached
            reached[cycle] = highest if highest > rank else rank
            if not known and len(reached) > KEEP:
                del reached[next(iter(reached))]
        return [Output("stage_order_ok", tick, ok, ts_ns)]


class StageOrderAsSpecified:
    """The stage-order spec as straight-line Python that keeps the language's values:
    what a generator emitting one Python function per spec could at best produce, short
    of proving in-place updates safe. Same inputs and outputs as the SpecRunner (inputs
    type-checked and held, NoVal until each has a value, ``x[1]`` is ⊥ on the first
    tick), but no call per operator: each stream is one inline expression. Its map and
    list are immutable as the spec says: every ``Map.insert`` / ``Map.remove`` builds a
    new :class:`MapV` and every ``List.append`` / ``List.tail`` a new tuple, where
    :class:`StageOrderByHand` updates one dict in place. Not part of RAP: the bench's
    yardstick for what generated source could reach."""

    __slots__ = ("cycle", "order1", "phase", "reached1", "stage", "tick")

    def __init__(self) -> None:
        self.stage: object = NOVAL
        self.phase: object = NOVAL
        self.cycle: object = NOVAL
        self.reached1: Any = BOTTOM  # reached[1]
        self.order1: Any = BOTTOM  # order[1]
        self.tick = 0

    def _empty(self) -> Any:
        return MapV()

    def step(self, inputs: dict[str, Any], ts_ns: int | None = None) -> list[Output]:
        tick = self.tick
        self.tick = tick + 1
        v = inputs.get("stage", NOVAL)
        if v is not NOVAL:
            if type(v) is not str:
                raise TypeError(f"stage: expected Str, got {v!r}")
            self.stage = v
        v = inputs.get("phase", NOVAL)
        if v is not NOVAL:
            if type(v) is not str:
                raise TypeError(f"phase: expected Str, got {v!r}")
            self.phase = v
        v = inputs.get("cycle", NOVAL)
        if v is not NOVAL:
            if type(v) is not str:
                raise TypeError(f"cycle: expected Str, got {v!r}")
            self.cycle = v
        stage, phase, cycle = self.stage, self.phase, self.cycle
        if stage is NOVAL or phase is NOVAL or cycle is NOVAL:
            return []
        rank = RANK.get(stage, -1)  # type: ignore[call-overload]
        starting = phase == "start" and rank >= 0
        r1 = self.reached1
        reached_before = self._empty() if r1 is BOTTOM else r1
        known = cycle in reached_before
        highest = reached_before[cycle] if known else -1
        ok = not starting or rank == 0 or highest >= rank - 1
        o1 = self.order1
        order_before = () if o1 is BOTTOM else o1
        grown = (*order_before, cycle) if starting and not known else order_before
        evict = len(grown) > KEEP
        order = grown[1:] if evict else grown
        raised = (
            self._insert(reached_before, cycle, highest if highest > rank else rank)
            if starting
            else reached_before
        )
        self.reached1 = self._remove(raised, grown[0]) if evict else raised
        self.order1 = order
        return [Output("stage_order_ok", tick, ok, ts_ns)]

    @staticmethod
    def _insert(m: Any, k: str, v: int) -> Any:
        new = MapV(m)
        new[k] = v
        return new

    @staticmethod
    def _remove(m: Any, k: str) -> Any:
        new = MapV(m)
        del new[k]
        return new


class StageOrderPersistent(StageOrderAsSpecified):
    """:class:`StageOrderAsSpecified` with the map held in a persistent hash trie
    (``immutables.Map``): still immutable, but an insert or remove shares all but
    O(log n) of the old map instead of copying it."""

    __slots__ = ()

    def _empty(self) -> Any:
        return immutables.Map()

    @staticmethod
    def _insert(m: Any, k: str, v: int) -> Any:
        return m.set(k, v)

    @staticmethod
    def _remove(m: Any, k: str) -> Any:
        return m.delete(k)


def stage_trace(cycles: int, seed: int = 7) -> list[dict[str, Any]]:
    """One record per tick, as the fabric maps rap.StageTrace (stage, phase, cycle), for
    ``cycles`` MAPLE-K cycles: monitor, analyse, then (70%) plan, legitimate, sometimes
    (10%) a rejected plan proposed again, and execute; each stage a start and an end
    record. A third of the cycles overlap the next one's monitor stage; one in fifty
    loses a start record (a skipped stage: out of order); one record in twenty comes
    from a node without a stage (``stage`` is ``""``)."""
    rng = random.Random(seed)
    out: list[dict[str, Any]] = []
    carry: list[dict[str, Any]] = []

    def rec(stage: str, phase: str, cid: str) -> dict[str, Any]:
        return {"stage": stage, "phase": phase, "cycle": cid}

    for c in range(cycles):
        cid = rng.getrandbits(128).to_bytes(16, "big").hex()
        stages = ["monitor", "analyse"]
        if rng.random() < 0.7:
            stages += ["plan", "legitimate"] * (2 if rng.random() < 0.1 else 1) + ["execute"]
        recs = [rec(s, p, cid) for s in stages for p in ("start", "end")]
        if rng.random() < 0.02:
            del recs[2 * rng.randrange(1, len(stages))]  # a start record goes missing
        if carry:  # the previous cycle's tail, after this cycle's monitor stage
            recs = recs[:2] + carry + recs[2:]
            carry = []
        if rng.random() < 0.33 and c + 1 < cycles:
            carry, recs = recs[-2:], recs[:-2]
        for r in recs:
            if rng.random() < 0.05:
                out.append(rec("", rng.choice(("start", "end")), cid))
            out.append(r)
    return out + carry


class Streams20ByHand:
    """bench/trust/streams20.dsrv, by hand (``None``: no value yet; every stream is
    lifted, so once it has a value it has one on every tick)."""

    __slots__ = ("a", "a_hist", "b", "f", "f_hist", "mode", "s01_hist", "tick")

    def __init__(self) -> None:
        self.a: int | None = None
        self.b: int | None = None
        self.f: float | None = None
        self.mode: str | None = None
        self.a_hist: int | None = None  # held a one tick ago
        self.f_hist: tuple[float | None, float | None] = (None, None)  # two ago, one ago
        self.s01_hist: int | None = None
        self.tick = 0

    def step(self, inputs: dict[str, Any], ts_ns: int | None = None) -> list[Output]:
        tick = self.tick
        self.tick = tick + 1
        a1, f2, p01 = self.a_hist, self.f_hist[0], self.s01_hist
        v = inputs.get("a")
        if v is not None:
            self.a = v
        v = inputs.get("b")
        if v is not None:
            self.b = v
        v = inputs.get("f")
        if v is not None:
            self.f = v
        v = inputs.get("mode")
        if v is not None:
            self.mode = v
        a, b, f, mode = self.a, self.b, self.f, self.mode
        out: list[Output] = []
        add = out.append
        ab = a is not None and b is not None
        s01 = s02 = s04 = s07 = s11 = s12 = s13 = None
        s03 = s09 = s14 = None
        s05 = s10 = s15 = s18 = None
        if ab:
            s01 = a + b  # type: ignore[operator]
            add(Output("s01", tick, s01, ts_ns))
            s02 = a * 2 - b  # type: ignore[operator]
            add(Output("s02", tick, s02, ts_ns))
        if f is not None:
            s03 = f * 0.5 + 1.0
            add(Output("s03", tick, s03, ts_ns))
        if ab:
            s04 = a > b  # type: ignore[operator]
            add(Output("s04", tick, s04, ts_ns))
        if f is not None:
            s05 = f >= 10.0
            add(Output("s05", tick, s05, ts_ns))
        add(Output("s06", tick, 0 if a1 is None else a1, ts_ns))
        if a is not None:
            s07 = a - (a if a1 is None else a1)
            add(Output("s07", tick, s07, ts_ns))
        if ab:
            add(Output("s08", tick, a if s04 else b, ts_ns))
        if f is not None and mode is not None:
            s09 = f * 2.0 if mode == "fast" else f
            add(Output("s09", tick, s09, ts_ns))
        if ab and f is not None:
            s10 = s04 and s05
            add(Output("s10", tick, s10, ts_ns))
        if s01 is not None:
            r = abs(s01) % 7
            s11 = -r if s01 < 0 else r
            add(Output("s11", tick, s11, ts_ns))
            s12 = (0 if p01 is None else p01) + s01
            add(Output("s12", tick, s12, ts_ns))
            s13 = s12 > 100
            add(Output("s13", tick, s13, ts_ns))
        if s09 is not None:
            s14 = s03 - s09  # type: ignore[operator]
            add(Output("s14", tick, s14, ts_ns))
            if s10 is not None:
                s15 = s14 < 0.0 or s10
                add(Output("s15", tick, s15, ts_ns))
        if s01 is not None:
            add(Output("s16", tick, s11 if s13 else -s11, ts_ns))  # type: ignore[operator]
            q = abs(s02) // 3  # type: ignore[arg-type]
            add(Output("s17", tick, -q if s02 < 0 else q, ts_ns))  # type: ignore[operator]
        if s07 is not None:
            s18 = s07 != 0
            add(Output("s18", tick, s18, ts_ns))
        if s03 is not None:
            add(Output("s19", tick, (0.0 if f2 is None else f2) + s03, ts_ns))
        if s15 is not None and s18 is not None:
            add(Output("s20", tick, (not s15) or s18, ts_ns))
        self.a_hist = a
        self.f_hist = (self.f_hist[1], f)
        self.s01_hist = s01
        return out


def streams20_trace(ticks: int, seed: int = 11) -> list[dict[str, Any]]:
    """Each tick sets one or two of the four inputs, at random: a and b most often,
    mode rarely (sample and hold does the rest)."""
    rng = random.Random(seed)
    out: list[dict[str, Any]] = []
    for _ in range(ticks):
        rec: dict[str, Any] = {}
        while not rec:
            if rng.random() < 0.5:
                rec["a"] = rng.randint(-60, 60)
            if rng.random() < 0.4:
                rec["b"] = rng.randint(-60, 60)
            if rng.random() < 0.4:
                rec["f"] = rng.randint(0, 80) / 4
            if rng.random() < 0.1:
                rec["mode"] = rng.choice(("fast", "slow"))
        out.append(rec)
    return out
