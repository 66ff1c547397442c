"""``python -m maplek_runner`` as a process: a bad plan exits 2 with one line; a good one
runs over real Zenoh, exchanges events with this process and stops on SIGTERM."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import anyio
import pytest
from rap_schemas import LaserScan, keys, pack_ranges
from rap_sdk.testing import Harness, free_port

from services.maplek_runner.tests.plans import PLAN, REPO

pytestmark = pytest.mark.anyio


async def _runner(*args: str) -> subprocess.CompletedProcess[bytes]:
    with anyio.fail_after(30):
        return await anyio.run_process(
            [sys.executable, "-m", "maplek_runner", *args], cwd=REPO, check=False
        )


@pytest.mark.parametrize(
    ("plan", "node", "message", "args"),
    [
        (PLAN.replace("stage: analyse", "stage: analyze"), "laptop", ":12:12: Invalid enum", []),
        (PLAN, "desk", ": compute node 'desk' is not in the plan; its compute nodes are", []),
        (PLAN.replace("sample_nodes:relay", "sample_nodes:rely"), "laptop", ":11:13: ", []),
        (PLAN, "laptop", "--listen '127.0.0.1:1' is not", ["--listen", "127.0.0.1:1"]),
        (
            PLAN.replace("  robot: {}", "  robot: {}\n  spare: {}"),
            "spare",
            ":5:3: the plan maps no components to compute node 'spare'",
            [],
        ),
    ],
    ids=["invalid-plan", "unknown-node", "import-error", "bad-endpoint", "nothing-to-run"],
)
async def test_a_bad_plan_exits_2_with_one_line(
    tmp_path: Path, plan: str, node: str, message: str, args: list[str]
) -> None:
    path = tmp_path / "plan.yaml"
    path.write_text(plan, encoding="utf-8")
    result = await _runner(str(path), "--node", node, *args)
    err = result.stderr.decode()
    assert result.returncode == 2, err
    prefix = "error: " if message.startswith("--") else f"error: {path}"
    assert err.startswith(prefix + message), err
    assert err.count("\n") == 1, err  # one line, no traceback
    assert not result.stdout


@pytest.mark.zenoh
async def test_the_runner_serves_its_share_over_zenoh_and_stops_on_sigterm(
    tmp_path: Path,
) -> None:
    port = free_port()
    path = tmp_path / "plan.yaml"
    path.write_text(
        PLAN.replace("  laptop: {}", "  laptop: {listen: ['tcp/127.0.0.1:1']}"), encoding="utf-8"
    )
    async with Harness(system="demo", fabric="zenoh", timeout=20) as h:
        with h.fabric.watch_liveliness(keys.pattern("demo", keys.Kind.ALIVE)) as watch:
            proc = await anyio.open_process(
                [
                    sys.executable,
                    "-m",
                    "maplek_runner",
                    str(path),
                    "--node",
                    "laptop",
                    "--connect",
                    h.endpoint,
                    "--listen",  # replaces the plan's (unusable) endpoint
                    f"tcp/127.0.0.1:{port}",
                ],
                cwd=REPO,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
            )
            try:
                alive: set[str] = set()
                with anyio.fail_after(20):
                    while alive != {"echo", "relay"}:
                        change = await watch.get()
                        assert change.alive, change
                        alive.add(keys.parse(change.key).name)
                await h.fabric.wait_matched(keys.data("demo", "ping"), timeout=20)
                await h.fabric.wait_matched(keys.event("demo", "tick"), timeout=20)

                scan = LaserScan(
                    stamp=7,
                    frame_id="base_link",
                    angle_min=-math.pi,
                    angle_increment=0.1,
                    range_min=0.1,
                    range_max=12.0,
                    ranges=pack_ranges([1.0, math.inf]),
                )
                ping = await h.publish("ping", scan)
                pong = await h.expect_data("pong")
                assert pong.decode(LaserScan) == scan
                assert pong.envelope is not None
                assert (pong.envelope.source, pong.envelope.cycle) == ("echo", ping.uid)
                tick = await h.emit("tick")
                tack = await h.expect_event("tack")
                assert tack.envelope is not None
                assert tack.envelope.cause == tick.uid

                proc.send_signal(signal.SIGTERM)
                gone: set[str] = set()
                with anyio.fail_after(20):
                    code = await proc.wait()
                    while gone != {"echo", "relay"}:
                        change = await watch.get()
                        assert not change.alive, change
                        gone.add(keys.parse(change.key).name)
            finally:
                if proc.returncode is None:
                    proc.kill()
                    await proc.wait()
                chunks = [chunk async for chunk in proc.stdout] if proc.stdout else []
                out = b"".join(chunks).decode()
                await proc.aclose()
    assert code == 0, out
    assert "running 2 component(s): echo (monitor, " in out, out
    assert f"ready: listening on tcp/127.0.0.1:{port}" in out, out
    assert "received SIGTERM; stopping" in out, out
    assert "relay stopped: 1 received, 1 handled" in out, out


@pytest.mark.zenoh
async def test_a_second_runner_of_the_same_share_refuses_to_start(tmp_path: Path) -> None:
    """Starting a runner twice doubled every command; now the second one says why and
    exits 1."""
    path = tmp_path / "plan.yaml"
    path.write_text(PLAN, encoding="utf-8")
    first_ep = f"tcp/127.0.0.1:{free_port()}"
    async with Harness(system="demo", fabric="zenoh", timeout=20) as h:
        with h.fabric.watch_liveliness(keys.pattern("demo", keys.Kind.ALIVE)) as watch:
            first = await anyio.open_process(
                [
                    *(sys.executable, "-m", "maplek_runner", str(path), "--node", "laptop"),
                    *("--connect", h.endpoint, "--listen", first_ep),
                ],
                cwd=REPO,
            )
            try:
                alive: set[str] = set()
                with anyio.fail_after(20):
                    while alive != {"echo", "relay"}:
                        alive.add(keys.parse((await watch.get()).key).name)
                # linked to the first (peers do not relay each other's declarations)
                second = await _runner(str(path), "--node", "laptop", "--connect", first_ep)
            finally:
                first.terminate()
                await first.wait()
                await first.aclose()
    err = second.stderr.decode()
    assert second.returncode == 1, err
    assert "error: node 'echo' is already running in system 'demo'" in err, err
    assert "Traceback" not in err
