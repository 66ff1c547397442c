"""``python -m bench.knowledge [--quick] [--report-only]``: knowledge figures in one run,
written to bench/results/knowledge.json and the knowledge section of
docs/benchmarks.md; exits 1 when a budget is missed."""

from __future__ import annotations

import asyncio
import json
import shutil
import sys
import tempfile
import time
from typing import Any

import anyio
import redis.asyncio as aioredis
import zenoh
from rap_schemas import keys
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import free_port

from ..procs import spawn
from ..report import (
    hardware_line,
    pct,
    run_suite,
    summary_us,
    table,
)

ROUNDS = 5
BUDGETS = {
    "replicated_read_p50_us": 20.0,
    "durable_write_vs_query_rtt_p50": 1.5,
    "history_10k_p50_ms": 20.0,
}


def step(msg: str) -> None:
    print(f"  {msg}", file=sys.stderr, flush=True)


async def timed(n: int, fn: Any) -> list[int]:
    out = []
    for i in range(n):
        t0 = time.perf_counter_ns()
        await fn(i)
        out.append(time.perf_counter_ns() - t0)
    return out


async def measure(quick: bool) -> dict[str, Any]:
    n = 2000 if quick else 20000
    m: dict[str, Any] = {}
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        async with spawn(
            [
                sys.executable,
                "-m",
                "knowledge",
                "--system",
                "bench",
                "--connect",
                ep,
                "--history-max",
                "20000",
                "--log-level",
                "WARNING",
            ]
        ):
            await fabric.wait_matched(keys.kb("bench", "_keys"), queryable=True, timeout=30)
            async with KnowledgeClient(
                fabric=fabric, system="bench", writer="bench", timeout=10
            ) as kb:
                await kb.write("r", 42, durable=True)
                await kb.read("r", int)  # replicate
                step("replicated read")
                m["replicated read"] = summary_us(await timed(n, lambda i: kb.read("r", int)))
                d = {"r": 42}

                async def dict_get(i: int) -> None:
                    d["r"]

                m["dict lookup"] = summary_us(await timed(n, dict_get))
                step("writes")
                m["write (non-durable)"] = summary_us(
                    await timed(n // 4, lambda i: kb.write("w", i))
                )
                step("durable writes and raw zenoh query round trips, interleaved")
                durable: list[int] = []
                raw: list[int] = []
                ratios: list[float] = []
                async with RawQuerier() as rq:
                    per_round = n // 10 // ROUNDS
                    for _ in range(ROUNDS):
                        d = await timed(per_round, lambda i: kb.write("d", i, durable=True))
                        r = await timed(per_round, lambda i: rq.query())
                        durable += d
                        raw += r
                        ratios.append(pct(d, 0.5) / pct(r, 0.5))
                m["write (durable)"] = summary_us(durable)
                m["raw zenoh query RTT"] = summary_us(raw)
                m["durable vs raw query, per-round p50 ratios"] = [round(x, 3) for x in ratios]
                step("history of 10 000 records")
                last = 0
                for i in range(10_000):
                    last = await kb.write("h", i)
                deadline = time.monotonic() + 60
                while (await kb.history("h", limit=1))[-1].version != last:
                    if time.monotonic() > deadline:
                        raise RuntimeError("service did not apply the history writes")
                    await anyio.sleep(0.01)  # completion poll, outside the measurement
                hist: list[int] = []
                for _ in range(10 if quick else 30):
                    t0 = time.perf_counter_ns()
                    got = await kb.history("h", limit=10_000)
                    hist.append(time.perf_counter_ns() - t0)
                    assert len(got) == 10_000
                m["history 10 000 records"] = summary_us(hist)
                step("4 KiB write throughput")
                value, count = b"x" * 4096, (2000 if quick else 20000)
                t0 = time.perf_counter_ns()
                for i in range(count):
                    last = await kb.write("t", value + i.to_bytes(4, "big"))
                while (await kb.history("t", limit=1))[-1].version != last:  # noqa: ASYNC110
                    await anyio.sleep(0.005)  # completion poll: at most 5 ms of the run
                secs = (time.perf_counter_ns() - t0) / 1e9
                m["4 KiB write throughput"] = {"writes_per_s": round(count / secs), "n": count}
    m.update(await redis_baselines(n))
    return m


class RawQuerier:
    """The baseline: raw zenoh-python ``get`` from asyncio to a queryable in another
    process that answers from its loop (bench.knowledge.peer)."""

    async def __aenter__(self) -> RawQuerier:
        self.loop = asyncio.get_running_loop()
        lport = free_port()
        conf = {
            "mode": "peer",
            "listen": {"endpoints": [f"tcp/127.0.0.1:{lport}"]},
            "connect": {"endpoints": []},
            "scouting": {"multicast": {"enabled": False}},
        }
        self.session = await anyio.to_thread.run_sync(
            zenoh.open, zenoh.Config.from_json5(json.dumps(conf))
        )
        self._peer = spawn([sys.executable, "-m", "bench.knowledge.peer", f"tcp/127.0.0.1:{lport}"])
        await self._peer.__aenter__()
        querier = self.session.declare_querier("bench/raw/query")
        while not querier.matching_status.matching:  # noqa: ASYNC110
            await anyio.sleep(0.01)  # discovery only, outside the measurement
        for _ in range(50):
            await self.query()  # warm-up
        return self

    async def query(self) -> None:
        loop = self.loop
        fut: asyncio.Future[None] = loop.create_future()

        def done() -> None:
            if not fut.done():
                fut.set_result(None)

        self.session.get(
            "bench/raw/query",
            zenoh.handlers.Callback(
                lambda r: None, lambda: loop.call_soon_threadsafe(done), indirect=False
            ),
            payload=b"x" * 64,
        )
        await fut

    async def __aexit__(self, *exc: object) -> None:
        await self._peer.__aexit__(None, None, None)
        await anyio.to_thread.run_sync(self.session.close)


async def redis_baselines(n: int) -> dict[str, Any]:
    binary = shutil.which("redis-server")
    if binary is None:
        return {"redis": "redis-server not installed: rows omitted"}
    port = free_port()
    with tempfile.TemporaryDirectory() as d:
        async with spawn(
            [
                binary,
                "--bind",
                "127.0.0.1",
                "--port",
                str(port),
                "--save",
                "",
                "--appendonly",
                "no",
                "--dir",
                d,
                "--logfile",
                "",
            ],
            ready="Ready to accept connections",
        ):
            client = aioredis.Redis(host="127.0.0.1", port=port)
            await client.set("r", b"42")
            step("redis baselines")
            out = {
                "redis GET": summary_us(await timed(n // 4, lambda i: client.get("r"))),
                "redis SET": summary_us(await timed(n // 4, lambda i: client.set("w", i))),
            }
            await client.aclose()
            return out


def render(m: dict[str, Any], v: dict[str, Any], hw: dict[str, Any]) -> str:
    rows = [
        [name, s["p50_us"], s["p99_us"], s["n"]]
        for name, s in m.items()
        if isinstance(s, dict) and "p50_us" in s
    ]
    tput = m["4 KiB write throughput"]
    parts = [
        "## Knowledge (`make bench-knowledge`)",
        "",
        f"Hardware: {hardware_line(hw)}",
        "",
        "The knowledge service runs in its own process (memory backend); the client "
        "reads from its local replica and writes on the stream (non-durable) or through "
        "the service (durable). Baselines in the same run: a dict lookup, redis.asyncio "
        "GET/SET against a redis-server on loopback, and a raw zenoh-python query round "
        "trip into asyncio against a queryable that answers from its loop. Durable writes "
        "and raw round trips run interleaved in 5 rounds; their budget ratio is the median "
        "of the per-round p50 ratios.",
        "",
        table(["operation", "p50 µs", "p99 µs", "n"], rows),
        "",
        f"4 KiB writes: {tput['writes_per_s']:,} writes/s (client writes until the "
        "service has applied the last one).",
        "",
        "Budgets:",
        "",
        table(
            ["budget", "measured", "limit", ""],
            [[k, x["value"], x["budget"], "ok" if x["ok"] else "MISSED"] for k, x in v.items()],
        ),
    ]
    return "\n".join(parts)


def verdicts(m: dict[str, Any]) -> dict[str, Any]:
    values = {
        "replicated_read_p50_us": m["replicated read"]["p50_us"],
        # median of per-round ratios, each pair measured back to back
        "durable_write_vs_query_rtt_p50": round(
            pct(m["durable vs raw query, per-round p50 ratios"], 0.5), 2
        ),
        "history_10k_p50_ms": round(m["history 10 000 records"]["p50_us"] / 1000, 2),
    }
    return {k: {"value": x, "budget": BUDGETS[k], "ok": x <= BUDGETS[k]} for k, x in values.items()}


def main() -> int:
    return run_suite("knowledge", lambda quick: anyio.run(measure, quick), verdicts, render)


if __name__ == "__main__":
    raise SystemExit(main())
