"""rap generate: a periodic thread of a component becomes a ``@node.every`` handler with
a user region, and the generated package runs it on its period."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from rap_cli.app import app
from typer.testing import CliRunner

runner = CliRunner()

MODEL = """\
system: ticking
compute_nodes: {here: {}}
components:
  robot:
    role: managed
    external: true
    node: here
    ports:
      go: {direction: out, kind: event, topic: go}
      seen: {direction: in, kind: event, topic: seen}
  m:
    stage: monitor
    node: here
    ports:
      go: {direction: in, kind: event, topic: go}
      seen: {direction: out, kind: event, topic: seen}
    threads:
      poll: {dispatch: {kind: periodic, rate_hz: 50}}
      go: {dispatch: {kind: periodic, rate_hz: 100}}
      burst: {dispatch: {kind: sporadic, rate_hz: 50}}
      idle: {dispatch: {kind: periodic}}
"""

TICKS_TEST = """
import pytest
from rap_sdk.testing import Harness

from ticking.nodes import m

pytestmark = pytest.mark.anyio


async def test_the_periodic_thread_runs_on_its_period() -> None:
    assert [(p.name, p.period) for p in m.node.periodic] == [
        ("on_poll", 0.02),
        ("on_go_2", 0.01),
    ]
    async with Harness(system="t") as h:
        group = await h.start(m.node)
        first = await h.expect_event("polled")
        again = await h.expect_event("polled", after=h.records.index(first) + 1)
        assert first.envelope.cycle != again.envelope.cycle
    stats = group["m"].stats
    assert stats.ticks >= 2
    assert stats.failed == 0
"""


def _rap(*args: str, cwd: Path) -> tuple[int, str]:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        result = runner.invoke(app, list(args))
    finally:
        os.chdir(old)
    return result.exit_code, result.output


def test_a_periodic_thread_generates_a_handler_that_runs(tmp_path: Path) -> None:
    (tmp_path / "model.yaml").write_text(MODEL)
    code, out = _rap("generate", "model.yaml", "--package", "ticking", cwd=tmp_path)
    assert code == 0, out
    module = tmp_path / "ticking" / "nodes" / "m.py"
    text = module.read_text()
    assert "@node.every(0.02)\nasync def on_poll(ctx: Context) -> None:" in text
    # a thread named as an input port: its handler gets a name of its own
    assert "@node.every(0.01)\nasync def on_go_2(ctx: Context) -> None:" in text
    assert '@node.on_event("go")\nasync def on_go(' in text
    # sporadic, or periodic without a rate: nothing new
    assert text.count("@node.every(") == 2
    assert "on_burst" not in text
    assert "on_idle" not in text
    # the user's code in the thread's region survives regeneration, and runs
    region = "    # region user: on_poll\n"
    assert region in text
    module.write_text(text.replace(region, f'{region}    await ctx.emit("polled")\n'))
    code, out = _rap("generate", "model.yaml", cwd=tmp_path)
    assert code == 0, out
    assert f'{region}    await ctx.emit("polled")\n' in module.read_text()
    (tmp_path / "tests" / "test_mine_ticks.py").write_text(TICKS_TEST)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "3 passed" in run.stdout  # the generated tests, and the one above
