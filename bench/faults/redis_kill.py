"""Scenario 2: the Redis under the knowledge service killed (SIGKILL) and started again.

``rap up --all`` of the lidar model with ``knowledge: {backend: redis}`` on a
redis-server of our own (append-only, an fsync per write, its own folder and free port).
A probe writes numbered durable writes all along (bench/faults/probe.py); Redis is
killed, left down for a while, and started again on the same port and folder. Measured:
how long after Redis is back the first write is acknowledged again (the service
reconnected), acknowledged writes missing afterwards (target: 0), and writes the
service reported as not stored that are stored all the same (target: 0). Writes whose
outcome nobody could know (no answer in time, ``unknown``) are counted apart."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import anyio

from .common import RedisServer, ScenarioError, rap_up, say, write_model
from .probe import Probe

__all__ = ["run_redis_kill"]

RECONNECT_S = 30.0


async def run_redis_kill(folder: Path, *, down: list[float], settle: float) -> dict[str, Any]:
    say(f"redis kill: {len(down)} kill(s), down {', '.join(f'{d:g} s' for d in down)}")
    redis = RedisServer(folder / "redis")
    await redis.start()
    cycles: list[dict[str, Any]] = []
    try:
        model = write_model(folder, backend="redis", redis_url=redis.url)
        async with rap_up(model, folder / "run") as up:
            probe = Probe(up.router("edge"), run="redis")
            try:
                async with probe:
                    await anyio.sleep(settle)  # acknowledged writes before the first kill
                    for seconds in down:
                        await redis.kill()
                        t_kill = time.monotonic()
                        say(f"  killed redis-server; down for {seconds:g} s")
                        await anyio.sleep(seconds)  # the outage under test
                        await redis.start()
                        t_back = time.monotonic()
                        n_back = max(probe.result.outcomes, default=-1)
                        acked = await probe.acknowledged_after(n_back, RECONNECT_S)
                        cycle = {
                            "down_s": seconds,
                            "failed_writes": probe.failed_between(t_kill, t_back + 0.01),
                            "first_ack_after_back_s": None
                            if acked is None
                            else round(acked - t_back, 3),
                        }
                        cycles.append(cycle)
                        say(
                            f"  redis back; first acknowledged write "
                            f"{cycle['first_ack_after_back_s']} s later"
                        )
                        await anyio.sleep(settle)
                await anyio.sleep(2.0)  # a write reported failed must not appear later
                writes = await probe.verify()
            finally:
                await probe.close()
            messages = [
                str(r.get("message", ""))[:160]
                for r in up.jsonl("edge", "knowledge")
                if "redis store" in str(r.get("message", ""))
            ]
    finally:
        await redis.stop()
    if not cycles:
        raise ScenarioError("no Redis kill was carried out")
    reconnected = all(c["first_ack_after_back_s"] is not None for c in cycles)
    say(
        f"  redis: {writes['acknowledged']} acknowledged, {writes['acknowledged_lost']} lost, "
        f"{writes['refused_but_applied']} reported failed but applied"
    )
    return {
        "cycles": cycles,
        "reconnected": reconnected,
        "writes": writes,
        "knowledge_log_redis_lines": len(messages),
        "knowledge_log_examples": messages[:3],
        "ok": reconnected
        and writes["acknowledged_lost"] == 0
        and writes["refused_but_applied"] == 0,
    }
