"""``rap trace``: its usage errors, its rendering, and the command itself against a real
adaptation manager following a real loop over Zenoh on loopback."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import anyio
import pytest
from adaptation_manager import Manager, Registry
from adaptation_manager.views import CycleTrace, PlanView, TraceStep
from rap_cli.app import app
from rap_cli.trace_cli import render
from rap_schemas import keys
from rap_sdk import run_nodes
from rap_sdk.testing import Harness
from typer.testing import CliRunner

from services.adaptation_manager.tests.loop import Waiter, loop_nodes

S = "tracecli"


def _rap() -> str:
    rap = Path(sys.executable).with_name("rap")
    assert rap.exists(), f"{rap}: the rap command is not installed next to {sys.executable}"
    return str(rap)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        ([], "give a CYCLE"),
        (["abc", "--last"], "not both"),
        (["xyz", "-s", S, "-c", "tcp/127.0.0.1:1"], "is not a cycle's hex uid"),
        (["--executed", "abc", "-s", S], "--executed goes with --last"),
        (["--last", "-s", S], "where is the fabric?"),
    ],
)
def test_usage_errors_exit_2_with_one_line(args: list[str], says: str) -> None:
    result = CliRunner().invoke(app, ["trace", *args], env={"RAP_ZENOH_CONFIG": ""})
    assert result.exit_code == 2, result.output
    assert says in result.output
    assert result.output.startswith("rap: error: ")


def step(depth: int, node: str, stage: str, key: str, offset: float, sent: list[str]) -> TraceStep:
    return TraceStep(
        depth=depth,
        node=node,
        handler="h",
        stage=stage,
        trigger="00",
        trigger_key=key,
        trigger_source="" if depth == 0 else "x",
        trigger_ts=0,
        start=0,
        offset_ms=offset,
        wait_ms=None if depth == 0 else 0.5,
        duration_ms=1.0,
        ended=True,
        ok=True,
        error="",
        sent=sent,
    )


def test_render_indents_each_call_under_its_sender_and_shows_what_reached_the_robot() -> None:
    data, event = "rap/demo/data/tb1/spin_config", "rap/demo/event/verdict"
    trace = CycleTrace(
        system="demo",
        cycle="ab" * 16,
        state="executed",
        start=1_700_000_000_000_000_000,
        end=0,
        total_ms=3.0,
        root_key="rap/demo/data/tb1/scan",
        executed=True,
        steps=[
            step(0, "legitimate", "legitimate", "rap/demo/event/new-plan", 0.0, [event]),
            step(1, "executor", "execute", event, 2.0, [data]),
        ],
        plans=[
            PlanView(
                plan="cd" * 16,
                cycle="ab" * 16,
                status="executed",
                proposer="planner",
                legitimator="legitimate",
                executor="executor",
            )
        ],
        outstanding=[],
    )
    text = render(trace).splitlines()
    assert text[0] == f"cycle {'ab' * 16} (executed) of system demo"
    assert "started by data/tb1/scan" in text[1]
    legit = next(line for line in text if "legitimate.h" in line)
    execu = next(line for line in text if "executor.h" in line)
    assert execu.index("executor.h") == legit.index("legitimate.h") + 2  # one deeper
    assert "on event/verdict from x" in execu
    arrow = next(line for line in text if "->" in line)
    assert arrow.strip() == "-> data/tb1/spin_config at +3.000 ms"
    assert "event/verdict at" not in "\n".join(text)  # taken by the executor: no arrow
    assert text[-1].startswith(f"plan {'cd' * 8} executed (proposed by planner")


@pytest.mark.anyio
@pytest.mark.zenoh
@pytest.mark.slow
async def test_rap_trace_asks_the_manager_for_a_cycle() -> None:
    async with Harness(system=S, fabric="zenoh", timeout=10) as h:
        await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system=S, compute_node="edge"))
        waiter = Waiter()
        reg = Registry(S, on_change=waiter.hook)
        async with anyio.create_task_group() as tg:
            await tg.start(Manager(fabric=h.fabric, system=S, registry=reg).run)
            env = await h.send(keys.data(S, "scan"))
            await waiter.until(lambda: env.uid in reg.cycles and reg.cycles[env.uid].executed)
            base = [_rap(), "trace", "-s", S, "-c", h.endpoint]

            last = await anyio.run_process([*base, "--last", "--executed"], check=False)
            out = last.stdout.decode()
            assert last.returncode == 0, out + last.stderr.decode()
            assert f"cycle {env.uid.hex()} (executed)" in out
            assert re.search(r"execute +executor\.\S*act on event/verdict from legitimate", out)
            assert "-> data/spin_config at +" in out

            as_json = await anyio.run_process([*base, env.uid.hex()[:12], "--json"], check=False)
            assert as_json.returncode == 0, as_json.stderr.decode()
            doc = json.loads(as_json.stdout)
            nodes = [s["node"] for s in doc["steps"]]
            assert nodes == ["monitor", "analysis", "planner", "legitimate", "executor"]
            assert doc["plans"][0]["status"] == "executed"

            by_end = await anyio.run_process([*base, ".." + env.uid.hex()[-8:]], check=False)
            assert by_end.returncode == 0, by_end.stderr.decode()

            missing = await anyio.run_process([*base, "ffff"], check=False)
            assert missing.returncode == 1
            assert "no cycle ffff in the manager's history" in missing.stderr.decode()
            tg.cancel_scope.cancel()
        # no manager: a clear error
        gone = await anyio.run_process([*base, "--last", "--timeout", "1"], check=False)
        assert gone.returncode == 1
        assert "no adaptation manager of system" in gone.stderr.decode()


def test_rap_trace_help_has_an_example() -> None:
    result = subprocess.run(
        [_rap(), "trace", "--help"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0
    assert "Example: rap trace --last" in result.stdout.replace("`", "")
