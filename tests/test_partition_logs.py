"""A link that goes silent leaves a trace: stopping the knowledge service's process for
5 s (SIGSTOP: its sockets stay open, it just stops answering, as behind a partition)
makes the runner log the lost link and the lost node, and their return."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import anyio
import pytest
from rap_schemas import keys
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
PLAN = REPO / "examples/lidar_occlusion/model.yaml"


async def _alive(fabric: ZenohFabric, name: str, up: bool, timeout: float) -> None:
    with fabric.watch_liveliness(keys.alive("demo", name)) as watch, anyio.fail_after(timeout):
        while (await fabric.alive(keys.alive("demo", name))) != (
            [keys.alive("demo", name)] if up else []
        ):
            await watch.get()


async def test_a_silent_link_is_logged_with_its_return(tmp_path: Path) -> None:
    kb_ep, runner_ep = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    log = (tmp_path / "runner.log").open("wb")
    async with (
        await anyio.open_process(
            [sys.executable, "-m", "knowledge", "--system", "demo", "--listen", kb_ep],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        ) as kb,
        await anyio.open_process(
            [
                *(sys.executable, "-m", "maplek_runner", str(PLAN), "--node", "robot"),
                *("--listen", runner_ep, "--connect", kb_ep),
            ],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
        ) as runner,
        ZenohFabric(ZenohConfig(connect=[runner_ep])) as fabric,
    ):
        try:
            await _alive(fabric, "monitor", True, 30)
            await anyio.sleep(1.0)  # the runner has seen the service by now
            kb.send_signal(signal.SIGSTOP)
            await anyio.sleep(5.0)  # the partition under test
            kb.send_signal(signal.SIGCONT)
            text = ""
            with anyio.fail_after(20):
                while "node knowledge is alive again" not in text:
                    await anyio.sleep(0.2)  # polling the other process's log file
                    text = (tmp_path / "runner.log").read_text(errors="replace")
        finally:
            for proc in (runner, kb):
                if proc.returncode is None:
                    proc.send_signal(signal.SIGCONT)
                    proc.terminate()
                    with anyio.move_on_after(10):
                        await proc.wait()
                    if proc.returncode is None:
                        proc.kill()
    log.close()
    text = (tmp_path / "runner.log").read_text(errors="replace")
    assert "lost (0 peer(s) still linked)" in text or "link to peer" in text, text
    assert "node knowledge lost its liveliness" in text, text
    assert "is back (reconnected)" in text, text
    assert "node knowledge is alive again" in text, text
