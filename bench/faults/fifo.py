"""Scenario 4: events at 1 kHz for 10 minutes into a node's FIFO inbox, across processes.

The receiver is a process of its own (``python -m bench.faults.fifo ENDPOINT``): one
``rap_sdk.Node`` whose event route ``tick`` has a FIFO inbox (``InboxPolicy(capacity=1024,
overflow=Overflow.FIFO)``), run by ``run_nodes`` with ``gc_idle=True`` as the MAPLE-K runner
runs its nodes, on a Zenoh session listening on a free loopback port. Its handler notes
the envelope's ``seq`` (dense per sender and key: a gap is a lost event) and the latency
from the envelope's ``ts`` (the sender's wall clock when it sealed the event) to the
handler's call. It prints one JSON line per window (a minute in the full run): events,
p50, p99 and max latency; and a last line with the totals when it gets SIGTERM.

This process sends: a Zenoh peer session connected to the receiver, one sealed
``rap.Empty/1`` event every millisecond on ``rap/<system>/event/tick`` (paced against the
clock, so a late wake-up is caught up at once and the rate holds on average), after
``wait_matched``. It samples the receiver's RSS (``/proc``) every 10 s. Targets: 0
events lost (every ``seq`` handled once), RSS bounded (after the first window it grows
by at most ``RSS_GROWTH_MIB``) and no latency drift (the last window's p50 and p99 at
most ``DRIFT`` times the first's, or within ``DRIFT_FLOOR_MS`` of it)."""

from __future__ import annotations

import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

import anyio
import anyio.lowlevel
from rap_schemas import Empty, keys
from rap_sdk import (
    Context,
    InboxPolicy,
    Node,
    Overflow,
    Sealer,
    ZenohConfig,
    ZenohFabric,
    run_nodes,
)
from rap_sdk.fabric import free_port

from ..fuzz import procinfo
from ..report import ROOT, pct
from .common import ScenarioError, say

__all__ = ["run_fifo"]

SYSTEM = "faults"
TOPIC = "tick"
CAPACITY = 1024
RSS_GROWTH_MIB = 16.0
DRIFT = 1.5
DRIFT_FLOOR_MS = 0.5
GAPS_KEPT = 100_000


# -- the receiver (its own process) ------------------------------------------------------


class Window:
    def __init__(self) -> None:
        self.lat_ms: list[float] = []

    def line(self, index: int) -> dict[str, Any]:
        v = self.lat_ms
        return {
            "window": index,
            "events": len(v),
            "p50_ms": round(pct(v, 0.5), 3) if v else None,
            "p99_ms": round(pct(v, 0.99), 3) if v else None,
            "max_ms": round(max(v), 3) if v else None,
        }


def _print(rec: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(rec) + "\n")
    sys.stdout.flush()


async def receive(endpoint: str, window_s: float) -> None:
    node = Node("fifo_sink")
    # constant memory whatever the run's length: the next seq expected, and the gaps
    # (a late event fills one; one that fills none was handled before)
    expected = 0
    gaps: set[int] = set()
    gaps_lost = 0
    dup = 0
    win = Window()
    index = 0

    @node.on_event(TOPIC, policy=InboxPolicy(capacity=CAPACITY, overflow=Overflow.FIFO))
    async def tick(ctx: Context) -> None:
        nonlocal dup, expected, gaps_lost
        env = ctx.envelope
        win.lat_ms.append((time.time_ns() - env.ts) / 1e6)
        seq = env.seq
        if seq >= expected:
            for missing in range(expected, seq):
                if len(gaps) < GAPS_KEPT:
                    gaps.add(missing)
                else:
                    gaps_lost += 1
            expected = seq + 1
        elif seq in gaps:
            gaps.discard(seq)
        else:
            dup += 1

    conf = ZenohConfig(listen=[endpoint])
    async with (
        ZenohFabric(conf) as fabric,
        run_nodes([node], fabric=fabric, system=SYSTEM, gc_idle=True) as group,
    ):
        _print({"ready": endpoint})
        with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
            stop = anyio.Event()

            async def wait_signal() -> None:
                async for _ in signals:
                    stop.set()
                    return

            async with anyio.create_task_group() as tg:
                tg.start_soon(wait_signal)
                while not stop.is_set():
                    with anyio.move_on_after(window_s):
                        await stop.wait()
                    if win.lat_ms:
                        _print(win.line(index))
                    index += 1
                    win = Window()
                tg.cancel_scope.cancel()
        st = group["fifo_sink"].stats
        _print(
            {
                "final": True,
                "handled": st.handled,
                "distinct": st.handled - dup,
                "duplicates": dup,
                "highest_seq": expected - 1,
                "gaps_open": len(gaps) + gaps_lost,
                "dropped_by_inbox": st.dropped,
                "rejected": st.rejected,
                "failed": st.failed,
            }
        )


# -- the sender and the measurement (this process) -----------------------------------------


async def _send(fabric: ZenohFabric, rate: float, seconds: float) -> dict[str, Any]:
    key = keys.event(SYSTEM, TOPIC)
    sealer = Sealer("fifo_source")
    n = int(rate * seconds)
    start = time.monotonic()
    worst_behind = 0.0
    for i in range(n):
        due = start + i / rate
        now = time.monotonic()
        if due > now:
            await anyio.sleep(due - now)  # the 1 kHz pacing
        else:
            worst_behind = max(worst_behind, now - due)
        payload, _ = sealer.seal_message(key, Empty())
        await fabric.publish(key, payload)
        if i % 1000 == 999:
            await anyio.lowlevel.checkpoint()  # let the other tasks run now and then
    return {
        "sent": n,
        "send_seconds": round(time.monotonic() - start, 3),
        "worst_behind_ms": round(worst_behind * 1000, 1),
    }


async def run_fifo(
    folder: Path, *, seconds: float, rate: float = 1000.0, window: float, rss_every: float
) -> dict[str, Any]:
    say(f"fifo: {rate:g} events/s for {seconds:g} s into a FIFO inbox (another process)")
    await anyio.Path(folder).mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = [sys.executable, "-m", "bench.faults.fifo", endpoint, str(window)]
    err = await anyio.to_thread.run_sync((folder / "receiver.err").open, "wb")
    lines: list[dict[str, Any]] = []
    rss: list[tuple[float, int]] = []
    with err:
        proc = await anyio.open_process(argv, stderr=err, cwd=ROOT)
    async with proc, anyio.create_task_group() as tg:
        ready = anyio.Event()

        async def read() -> None:
            assert proc.stdout is not None
            buf = b""
            async for chunk in proc.stdout:
                *done, buf = (buf + chunk).split(b"\n")
                for raw in done:
                    rec = json.loads(raw)
                    if "ready" in rec:
                        ready.set()
                    else:
                        lines.append(rec)

        tg.start_soon(read)
        with anyio.fail_after(60):
            await ready.wait()
        t0 = time.monotonic()

        async def sample_rss() -> None:
            while True:
                snap = await procinfo.snapshot(proc.pid)
                if snap.get("alive"):
                    rss.append((round(time.monotonic() - t0, 1), int(snap["rss_kib"])))
                await anyio.sleep(rss_every)  # the sampling period

        conf = ZenohConfig(listen=[], connect=[endpoint])
        async with ZenohFabric(conf) as fabric:
            await fabric.wait_matched(keys.event(SYSTEM, TOPIC), timeout=30)
            tg.start_soon(sample_rss)

            async def progress() -> None:
                while True:
                    await anyio.sleep(60 if seconds > 60 else 5)  # a progress line
                    say(f"  {time.monotonic() - t0:.0f} s of {seconds:g} s")

            tg.start_soon(progress)
            sent = await _send(fabric, rate, seconds)
            await anyio.sleep(2.0)  # what is in flight arrives
        snap = await procinfo.snapshot(proc.pid)
        if snap.get("alive"):
            rss.append((round(time.monotonic() - t0, 1), int(snap["rss_kib"])))
        proc.send_signal(signal.SIGTERM)
        with anyio.move_on_after(30):
            await proc.wait()
        if proc.returncode is None:
            proc.kill()
        tg.cancel_scope.cancel()
    final = next((x for x in lines if x.get("final")), None)
    if final is None:
        tail = (folder / "receiver.err").read_text(errors="replace")[-2000:]
        raise ScenarioError(
            f"the receiver ended without its totals (exit {proc.returncode}):\n{tail}"
        )
    windows = [x for x in lines if "window" in x]
    return _verdict(sent, final, windows, rss, rate, seconds, window)


def _verdict(
    sent: dict[str, Any],
    final: dict[str, Any],
    windows: list[dict[str, Any]],
    rss: list[tuple[float, int]],
    rate: float,
    seconds: float,
    window: float,
) -> dict[str, Any]:
    lost = sent["sent"] - final["distinct"]
    full = [w for w in windows if w["events"] >= 0.5 * rate * window]
    drift: dict[str, Any] = {"windows_compared": len(full)}
    drift_ok = len(full) >= 2
    if len(full) >= 2:
        first, last = full[0], full[-1]
        for q in ("p50_ms", "p99_ms"):
            ok = last[q] <= max(first[q] * DRIFT, first[q] + DRIFT_FLOOR_MS)
            drift[q] = {"first": first[q], "last": last[q], "ok": ok}
            drift_ok = drift_ok and ok
    mib = [(t, k / 1024) for t, k in rss]
    after_first = [m for t, m in mib if t >= window]
    base = after_first[0] if after_first else (mib[0][1] if mib else 0.0)
    growth = (max(after_first) - base) if after_first else 0.0
    rss_out = {
        "start_mib": round(mib[0][1], 1) if mib else None,
        "max_mib": round(max(m for _, m in mib), 1) if mib else None,
        "end_mib": round(mib[-1][1], 1) if mib else None,
        "growth_after_first_window_mib": round(growth, 1),
        "samples": [[t, round(m, 1)] for t, m in mib],
        "ok": bool(mib) and growth <= RSS_GROWTH_MIB,
    }
    return {
        "rate_hz": rate,
        "seconds": seconds,
        "window_s": window,
        "inbox": {"policy": "fifo", "capacity": CAPACITY},
        **sent,
        "received": final,
        "lost": lost,
        "windows": windows,
        "drift": {**drift, "ok": drift_ok},
        "rss": rss_out,
        "ok": lost == 0 and final["duplicates"] == 0 and drift_ok and rss_out["ok"],
    }


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m bench.faults.fifo ENDPOINT WINDOW_SECONDS", file=sys.stderr)
        return 2
    anyio.run(receive, args[0], float(args[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
