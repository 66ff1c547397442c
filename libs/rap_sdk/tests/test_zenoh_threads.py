"""Zenoh's thread pools (``ZenohConfig.runtime``), each case in a fresh process: the
setting is read once per process, when its first session opens."""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = """
import os, sys, anyio
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port
from rap_sdk.errors import FabricError

async def main(runtime, linked):
    kw = {} if runtime == "default" else {"runtime": None}
    try:
        async with ZenohFabric(ZenohConfig(**kw)) as a:
            if linked:  # a second session linked to the first, and a sample across
                await send_across(a, kw)
            # a pool's threads start on their own time (late on a loaded machine): the
            # listing counts once it has some and stays the same for 0.2 s (at most 10 s)
            seen, same = None, 0
            for _ in range(200):
                now = zenoh_threads()
                same = same + 1 if now and now == seen else 0
                if same == 4:
                    break
                seen = now
                await anyio.sleep(0.05)
    except FabricError as exc:
        print("error:", exc)
        return
    print(" ".join(seen or []))

async def send_across(a, kw):
    port = free_port()
    async with ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"], **kw)) as b:
        sub = b.subscribe("probe/x")
        async with ZenohFabric(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"], **kw)) as c:
            await c.wait_matched("probe/x", timeout=10.0)
            await c.publish("probe/x", b"x")
            with anyio.fail_after(10):
                async for _ in sub:
                    break

def zenoh_threads():
    names = sorted(
        open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")
    )
    return [n for n in names if n[:3] in ("rx-", "tx-", "net", "acc", "app")]

anyio.run(main, sys.argv[1], len(sys.argv) > 2)
"""


def _zenoh_threads(runtime: str, env_value: str | None = None, *, linked: bool = False) -> str:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if env_value is not None:
        env["ZENOH_RUNTIME"] = env_value
    out = subprocess.run(
        [sys.executable, "-c", PROBE, runtime, *(["linked"] if linked else [])],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return out.stdout.strip()


def test_default_runs_zenoh_on_one_worker_thread_until_a_link_sends() -> None:
    assert _zenoh_threads("default").split() == ["rx-0"]


def test_default_writes_links_on_a_thread_of_its_own() -> None:
    """The thread that reads a link may wait for room in a send queue (congestion control
    ``block``); were it the one thread that empties the queue, it would wait for itself
    until Zenoh closed the link (make faults, the fuzz over TLS)."""
    names = _zenoh_threads("default", linked=True).split()
    assert "tx-0" in names
    assert "tx-1" not in names
    assert {n.split("-")[0] for n in names} == {"rx", "tx"}  # rx-1..: blocking work
    old = "(rx: (worker_threads: 1), tx: (handover: rx), net: (handover: rx))"
    assert "tx-0" not in _zenoh_threads("default", old, linked=True).split()


def test_runtime_none_keeps_zenohs_own_pools() -> None:
    names = _zenoh_threads("none").split()  # a pool's threads start when first used
    assert "acc-0" in names
    assert "app-0" in names
    assert "rx-0" not in names


def test_environment_variable_wins() -> None:
    names = _zenoh_threads("default", "(app: (worker_threads: 2))").split()
    assert "app-0" in names
    assert "app-1" in names


def test_unparseable_setting_is_an_error_that_names_it() -> None:
    out = _zenoh_threads("default", "two threads please")
    assert out.startswith("error: Zenoh could not start its threads with ZENOH_RUNTIME=")
    assert "'two threads please'" in out
    assert "fix or unset it" in out
