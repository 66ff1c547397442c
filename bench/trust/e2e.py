"""End-to-end verdict latency over Zenoh: a StageTrace record published -> the checker's
rap.TrustOutput for it received, in the same process (one ZenohFabric session, loopback).

Rows (each in its own process, on its own system name so that only the row being
measured receives the records):

- ``echo``: the raw baseline, ``python -m bench.trust.peer echo``: every record opened
  and decoded like the checker's transport does, answered with a sealed TrustOutput;
- ``checker``: ``python -m trust_checker SPEC --fabric SYSTEM --connect EP`` as deployed
  (its console lines on stdout included, read and dropped here);
- ``checker, no console``: ``python -m bench.trust.peer session``: the same transport and
  session with no other sink (what the console output costs).

The records are the bench's MAPLE-K stage trace (bench/trust/by_hand.stage_trace), each
one tick of the stage-order spec and so one output, matched to its record by tick. The
rows run interleaved: for each round, for each rate, each row sends its share. Rates are
paced on absolute deadlines by the event loop's timer (about 1 ms resolution: at high
rates records leave in small bursts, as a MAPLE-K cycle's records do).
"""

from __future__ import annotations

import sys
import time
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio
from anyio.abc import TaskGroup
from rap_schemas import Stage, StageTrace, TrustOutput, keys
from rap_sdk import InboxPolicy, Overflow, Sealer, ZenohConfig, ZenohFabric
from rap_sdk.envelope import typed_decoder
from rap_sdk.fabric import Subscription, free_port

from ..procs import Proc, spawn
from ..report import pct
from .by_hand import StageOrderByHand, stage_trace

_open_output = typed_decoder(TrustOutput)
_INBOX = InboxPolicy(capacity=1 << 17, overflow=Overflow.FIFO, block=False)
NODE = "bench-node"


@dataclass
class Row:
    name: str
    system: str
    argv: list[str]
    ready: str
    stream: str
    sent_ns: list[int] = field(default_factory=list)
    """Send time of each record, by the tick it is at the receiver."""
    got_ns: dict[int, int] = field(default_factory=dict)
    got_val: dict[int, object] = field(default_factory=dict)
    sealer: Sealer = field(default_factory=lambda: Sealer(NODE))
    next_rec: int = 0
    want: set[int] = field(default_factory=set)
    """Ticks still awaited; ``done`` is set when the last one arrives."""
    done: anyio.Event = field(default_factory=anyio.Event)


def rows(spec: Path, endpoint: str) -> list[Row]:
    py = sys.executable
    return [
        Row("echo", "tb-echo", [py, "-m", "bench.trust.peer", "echo", "tb-echo", endpoint],
            "READY", "echo"),
        Row("checker", "tb-cli",
            [py, "-m", "trust_checker", str(spec), "--fabric", "tb-cli", "--connect", endpoint,
             "--log-level", "INFO"],
            "ready: inputs", "stage_order_ok"),
        Row("checker, no console", "tb-session",
            [py, "-m", "bench.trust.peer", "session", "tb-session", endpoint, str(spec)],
            "READY", "stage_order_ok"),
    ]  # fmt: skip


def _messages(n: int) -> tuple[list[dict[str, Any]], list[StageTrace]]:
    """``n`` records of the stage trace, as the fabric will map them and as sent."""
    recs = stage_trace(n // 6 + 10)[:n]
    out = []
    for i, r in enumerate(recs):
        out.append(
            StageTrace(
                node=NODE,
                handler="step",
                phase=r["phase"],
                trigger=i.to_bytes(16, "big"),
                trigger_key=f"rap/bench/event/{i}",
                cycle=bytes.fromhex(r["cycle"]),
                ts=0,
                stage=Stage(r["stage"]) if r["stage"] else None,
            )
        )
    return recs, out


def _check(row: Row, recs: list[dict[str, Any]]) -> int:
    """The verdicts received are the by-hand monitor's on the records sent (so each
    output was matched to its own record): AssertionError otherwise. Returns how many
    were compared."""
    ref = StageOrderByHand()
    n = 0
    for tick in range(row.next_rec):
        (want,) = ref.step(recs[tick % len(recs)])
        got = row.got_val.get(tick)
        if got is not None:
            n += 1
            if got is not want.value:
                raise AssertionError(
                    f"{row.name}: tick {tick} gave {got}, the by-hand monitor {want.value}"
                )
    return n


async def _drain(proc: Proc) -> None:
    """Read the process's output (console lines, logs) so it never blocks on a pipe."""
    try:
        while True:
            await proc.line()
    except (anyio.EndOfStream, anyio.ClosedResourceError, TimeoutError):
        return


async def _receive(row: Row, sub: Subscription) -> None:
    async for sample in sub:
        t = time.perf_counter_ns()
        msg: TrustOutput = _open_output(sample.payload).body
        row.got_ns.setdefault(msg.tick, t)
        row.got_val[msg.tick] = msg.value
        if msg.tick in row.want:
            row.want.discard(msg.tick)
            if not row.want:
                row.done.set()


@asynccontextmanager
async def _started(
    fabric: ZenohFabric, row: Row, tg: TaskGroup, stack: AsyncExitStack
) -> AsyncIterator[None]:
    sub = fabric.subscribe(keys.trust(row.system, row.stream), _INBOX)
    stack.callback(sub.close)
    tg.start_soon(_receive, row, sub)
    proc = await stack.enter_async_context(spawn(row.argv, ready=row.ready))
    tg.start_soon(_drain, proc)
    await fabric.wait_matched(keys.trace(row.system, NODE), timeout=30)
    yield


async def _send(
    fabric: ZenohFabric, row: Row, msgs: list[StageTrace], n: int, rate: float
) -> range:
    """``n`` records at ``rate`` per second; the ticks they are."""
    key = keys.trace(row.system, NODE)
    first = len(row.sent_ns)
    start = time.perf_counter()
    for j in range(n):
        delay = start + j / rate - time.perf_counter()
        if delay > 0:
            await anyio.sleep(delay)
        msg = msgs[row.next_rec % len(msgs)]
        row.next_rec += 1
        payload, _ = row.sealer.seal_message(key, msg)
        row.sent_ns.append(time.perf_counter_ns())
        await fabric.publish(key, payload)
    return range(first, first + n)


async def _settle(row: Row, ticks: range, timeout: float) -> None:
    """Until every tick in ``ticks`` is answered (at most ``timeout`` s)."""
    row.want = {t for t in ticks if t not in row.got_ns}
    if not row.want:
        return
    row.done = anyio.Event()
    with anyio.move_on_after(timeout):
        await row.done.wait()
    row.want = set()


def _stats(lat: list[int]) -> dict[str, Any]:
    if not lat:
        return {"p50_us": None, "p90_us": None, "p99_us": None, "n": 0}
    return {
        "p50_us": round(pct(lat, 0.5) / 1000, 1),
        "p90_us": round(pct(lat, 0.9) / 1000, 1),
        "p99_us": round(pct(lat, 0.99) / 1000, 1),
        "n": len(lat),
    }


async def measure(
    spec: Path, rates: list[float], seconds: float, rounds: int, say: Any
) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    per = {rate: max(50, int(rate * seconds / rounds)) for rate in rates}
    recs, msgs = _messages(20_000)
    lat: dict[tuple[str, float], list[int]] = {}
    lost: dict[tuple[str, float], int] = {}
    sent: dict[tuple[str, float], int] = {}
    async with ZenohFabric(ZenohConfig(listen=[endpoint])) as fabric:
        the_rows = rows(spec, endpoint)
        async with AsyncExitStack() as stack:
            tg = await stack.enter_async_context(anyio.create_task_group())
            stack.callback(tg.cancel_scope.cancel)
            for row in the_rows:
                say(f"starting {row.name}")
                await stack.enter_async_context(_started(fabric, row, tg, stack))
                warm = await _send(fabric, row, msgs, 300, 500.0)
                await _settle(row, warm, 15.0)
                if not any(t in row.got_ns for t in warm):
                    raise RuntimeError(f"{row.name}: no output for the warm-up records")
            for r in range(rounds):
                for rate in rates:
                    for row in the_rows:
                        ticks = await _send(fabric, row, msgs, per[rate], rate)
                        await _settle(row, ticks, 10.0)
                        k = (row.name, rate)
                        got = [row.got_ns[t] - row.sent_ns[t] for t in ticks if t in row.got_ns]
                        lat.setdefault(k, []).extend(got)
                        lost[k] = lost.get(k, 0) + len(ticks) - len(got)
                        sent[k] = sent.get(k, 0) + len(ticks)
                say(f"round {r + 1}/{rounds} done")
    checked = {row.name: _check(row, recs) for row in the_rows if row.stream != "echo"}
    out_rows = []
    for rate in rates:
        base = pct(lat[("echo", rate)], 0.5) if lat.get(("echo", rate)) else None
        for row in the_rows:
            k = (row.name, rate)
            s = _stats(lat.get(k, []))
            out_rows.append(
                {
                    "row": row.name,
                    "rate_hz": rate,
                    **s,
                    "sent": sent[k],
                    "lost": lost[k],
                    "p50_vs_echo": round(pct(lat[k], 0.5) / base, 2) if base and lat[k] else None,
                }
            )
    return {
        "rates_hz": rates,
        "rounds": rounds,
        "records_per_rate": per,
        "rows": out_rows,
        "verdicts_checked": checked,
    }
