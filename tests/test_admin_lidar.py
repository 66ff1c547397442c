"""Operating the lidar loop while it runs under ``rap up --all``, with the ``rap`` admin
verbs as an operator types them: ``rap status --json`` lists every component alive with
its compute node; a config set, a pause/resume and a swap (state handed over) take effect
with no ``new-data`` event lost or handled twice (every event the monitor emitted between
two barriers is handled by the analysis, counted); snapshots are kept in knowledge.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_cli.testing import model_copy, rap_command, rap_up
from rap_schemas import keys
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import Harness

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(180)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
RUNNING = {
    "monitor": "robot",
    "executor": "robot",
    "analysis": "edge",
    "planner": "edge",
    "legitimate": "edge",
}


class Rap:
    """``rap VERB ... -m MODEL --run-dir RUN`` as subprocesses."""

    def __init__(self, model: Path, run: Path) -> None:
        self.where = ["-m", str(model), "--run-dir", str(run)]

    async def __call__(self, *argv: str, ok: bool = True) -> str:
        proc = await anyio.run_process([rap_command(), *argv, *self.where], check=False)
        out = proc.stdout.decode() + proc.stderr.decode()
        if ok:
            assert proc.returncode == 0, f"rap {' '.join(argv)}: exit {proc.returncode}\n{out}"
        return out

    async def status(self) -> dict[str, dict[str, Any]]:
        proc = await anyio.run_process(
            [rap_command(), "status", "--json", *self.where], check=False
        )
        rows = json.loads(proc.stdout.decode())
        return {r["name"]: r for r in rows}


async def _settled(rap: Rap, component: str) -> dict[str, Any]:
    """The component's status once its inbox is empty and its count stands still."""
    last = -1
    with anyio.fail_after(20):
        while True:
            st = (await rap.status())[component]
            if st.get("inbox", 0) == 0 and st.get("handled", 0) == last and st["state"] != "active":
                return st
            last = st.get("handled", 0)
            await anyio.sleep(0.3)


def _new_data(h: Harness) -> int:
    return sum(1 for r in h.records if r.kind is keys.Kind.EVENT and r.name == "new-data")


async def test_status_config_pause_swap_and_snapshots_on_the_running_lidar_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    copy = model_copy(MODEL, tmp_path)
    rap = Rap(copy, run)
    async with rap_up(copy, run) as out:
        # rap status: every component alive, on its compute node
        with anyio.fail_after(30):
            while True:
                rows = await rap.status()
                if all(
                    rows.get(n, {}).get("state") not in (None, "gone", "starting") for n in RUNNING
                ):
                    break
                await anyio.sleep(0.5)
        assert {n: rows[n]["compute_node"] for n in RUNNING} == RUNNING, rows
        assert {rows[n]["stage"] for n in RUNNING} == {
            "monitor",
            "analyse",
            "plan",
            "legitimate",
            "execute",
        }
        table = await rap("status")
        assert "analysis" in table
        assert "edge" in table

        monkeypatch.setenv(CONFIG_ENV, str(run / "edge" / "zenoh-client.json5"))
        async with Harness(system=SYSTEM, fabric="zenoh", timeout=30) as h:
            await h.expect_event("new-data")  # the loop runs and the harness sees it
            # barrier 1: no new-data comes while the monitor is paused
            assert "paused" in await rap("pause", "monitor")
            before = await _settled(rap, "analysis")
            n0, h0 = _new_data(h), before["handled"]

            assert "resumed" in await rap("resume", "monitor")
            await h.expect_event("new-data", after=len(h.records))
            # a config set takes effect; a bad value is refused with its path
            await rap("config", "set", "analysis", "threshold=0.35")
            bad = await rap("config", "set", "analysis", "window=0", ok=False)
            assert "$.window" in bad, bad
            assert ">= 1" in bad, bad
            assert "unchanged" in bad, bad
            # pause/resume the analysis under the running loop
            await rap("pause", "analysis")
            await anyio.sleep(0.5)
            paused = (await rap.status())["analysis"]
            assert paused["state"] == "paused", paused
            await rap("resume", "analysis")
            # swap it for a fresh instance, its mask window handed over
            swapped = await rap("swap", "analysis", "lidar_occlusion.nodes:fresh_analysis")
            assert "state handed over" in swapped, swapped
            await h.expect_event("new-data", after=len(h.records))
            await anyio.sleep(1.0)

            # barrier 2
            await rap("pause", "monitor")
            after = await _settled(rap, "analysis")
            n1, h1 = _new_data(h), after["handled"]
            await rap("resume", "monitor")
        assert n1 - n0 > 5, "the loop ran between the barriers"
        assert h1 - h0 == n1 - n0, (
            f"the monitor emitted {n1 - n0} new-data events between the barriers and "
            f"the analysis handled {h1 - h0}"
        )
        assert after["dropped"] == 0, after
        assert after["swaps"] == 1, after
        assert after["implementation"] == "lidar_occlusion.nodes:fresh_analysis", after
        conf = json.loads(await rap("config", "get", "analysis", "--json"))
        assert conf["threshold"] == 0.35  # carried over the swap
        assert conf["window"] == 3

        # snapshots are kept in knowledge, and restored from it
        snap = await rap("snapshot", "analysis")
        assert "admin/snapshot/analysis" in snap, snap
        restored = await rap("restore", "analysis")
        assert "restored the snapshot of lidar_occlusion.nodes:fresh_analysis" in restored

        # a runner killed and restarted by rap up resumes the analysis from it
        state = json.loads((run / "edge" / "up.json").read_text())
        (runner,) = [c for c in state["children"] if c["name"] == "runner"]
        os.kill(runner["pid"], signal.SIGKILL)
        await out.line("analysis: resumed the state of its snapshot", timeout=30)
