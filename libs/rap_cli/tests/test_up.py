"""``rap up``, ``rap down`` and ``rap health`` as processes, over real Zenoh on loopback.

Each test writes a small model and a module of Nodes next to it (rap up puts the
model's folder on the processes' PYTHONPATH), runs ``rap up`` as a child process and
joins the fabric as a Zenoh client of a node's router (``RAP_ZENOH_CONFIG`` pointing at
the node's client config, as every process rap up starts does)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_cli.up import _zombie, router_id
from rap_schemas import Pose2D, keys
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import Harness, OutputLines, Record, stop_process

pytestmark = pytest.mark.anyio

RAP = str(Path(sys.executable).with_name("rap"))
UP_TIMEOUT = 30.0

NODES = """\
from rap_schemas import Pose2D
from rap_sdk import Context, Node

mon = Node("mon", stage="monitor")


@mon.on_data("x/in")
async def on_in(ctx: Context, pose: Pose2D) -> None:
    await ctx.emit("seen")


ana = Node("ana", stage="analyse")


@ana.on_event("seen")
async def on_seen(ctx: Context) -> None:
    await ctx.emit("done")
"""

ONE_NODE = """\
system: probe
compute_nodes:
  a: {}
knowledge:
  backend: memory
components:
  mon:
    module: probe_nodes:mon
    stage: monitor
    node: a
"""

TWO_NODES = """\
system: probe2
compute_nodes:
  a: {}
  b: {}
knowledge:
  backend: memory
  node: a
components:
  mon:
    module: probe_nodes:mon
    stage: monitor
    node: a
  ana:
    module: probe_nodes:ana
    stage: analyse
    node: b
"""

RELAY_AND_BROKEN = """\
system: probe3
compute_nodes:
  relay: {}
  g: {}
knowledge:
  backend: memory
  node: g
components:
  ghost:
    module: probe_nodes:nobody
    stage: monitor
    node: g
"""


def _model(tmp_path: Path, text: str) -> Path:
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "probe_nodes.py").write_text(NODES, encoding="utf-8")
    path = folder / "model.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != CONFIG_ENV}
    env.update(extra)
    return env


def _state(run_dir: Path, node: str) -> dict[str, Any]:
    state: dict[str, Any] = json.loads((run_dir / node / "up.json").read_text(encoding="utf-8"))
    return state


def _pids(run_dir: Path, node: str) -> dict[str, int]:
    return {c["name"]: c["pid"] for c in _state(run_dir, node)["children"] if c["pid"]}


def _logs(run_dir: Path, node: str) -> str:
    return "\n".join(
        f"--- {p.name}\n{p.read_text(encoding='utf-8', errors='replace')[-2000:]}"
        for p in sorted((run_dir / node / "logs").glob("*.log"))
    )


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


async def _rap(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    with anyio.fail_after(UP_TIMEOUT):
        done = await anyio.run_process([RAP, *args], check=False, env=env or _env())
    return subprocess.CompletedProcess(
        done.args, done.returncode, done.stdout.decode(), done.stderr.decode()
    )


class RapUp(OutputLines):
    """A running ``rap up`` and its output lines so far."""

    def output(self) -> str:
        return str(self)


@contextlib.asynccontextmanager
async def rap_up(*args: str) -> AsyncIterator[RapUp]:
    proc = await anyio.open_process(
        [RAP, "up", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=_env()
    )
    up = RapUp(proc, timeout=UP_TIMEOUT)
    try:
        async with anyio.create_task_group() as tg:
            tg.start_soon(up.pump)
            try:
                yield up
            finally:
                await stop_process(proc, grace=20)  # the test failed: do not leave it running
                tg.cancel_scope.cancel()
    finally:
        await proc.aclose()


@contextlib.asynccontextmanager
async def observer(
    monkeypatch: pytest.MonkeyPatch, run_dir: Path, node: str, system: str
) -> AsyncIterator[Harness]:
    """A harness that is a Zenoh client of ``node``'s router."""
    with monkeypatch.context() as m:
        m.setenv(CONFIG_ENV, str(run_dir / node / "zenoh-client.json5"))
        async with Harness(system=system, fabric="zenoh", timeout=UP_TIMEOUT) as h:
            yield h


POSE = Pose2D(x=1.0, y=2.0, theta=0.5)


async def _round_trip(h: Harness, topic: str, event: str) -> Record:
    """Publish on data ``topic`` and await ``event``. The first try must come back: a
    Zenoh client's first samples on a new key reach the router even before it has
    learnt of the subscribers (``ZenohFabric`` does not hold them back in client mode)."""
    after = len(h.records)
    await h.publish(topic, POSE)
    return await h.expect_event(event, after=after)


@pytest.mark.zenoh
async def test_up_health_restart_and_down(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = _model(tmp_path, ONE_NODE)
    run_dir = tmp_path / "run"
    async with rap_up(str(model), "--node", "a", "--run-dir", str(run_dir)) as up:
        await up.line("compute node a is up")
        pids = _pids(run_dir, "a")
        assert set(pids) == {"router", "knowledge", "manager", "runner"}, up.output()
        router_conf = (run_dir / "a" / "zenoh-router.json5").read_text(encoding="utf-8")
        assert '"mode": "router"' in router_conf
        assert (run_dir / "a" / "logs" / "router.log").exists()

        async with observer(monkeypatch, run_dir, "a", "probe") as h:
            alive = keys.pattern("probe", keys.Kind.ALIVE)
            with h.fabric.watch_liveliness(alive) as watch:
                want = {"mon", "knowledge", "manager"}  # the runner's stage, the services
                seen: set[str] = set()
                with anyio.move_on_after(UP_TIMEOUT):
                    while not want <= seen:
                        change = await watch.get()
                        if change.alive:
                            seen.add(keys.parse(change.key).name)
                assert want <= seen, (seen, up.output(), _logs(run_dir, "a"))
                await h.fabric.wait_matched(keys.data("probe", "x/in"), timeout=UP_TIMEOUT)
                await _round_trip(h, "x/in", "seen")

                # rap health through the router of the running rap up (its up.json)
                health = await _rap("health", str(model), "--node", "a", "--run-dir", str(run_dir))
                assert health.returncode == 0, health
                assert "alive: mon, knowledge" in health.stdout

                again = await _rap("up", str(model), "--run-dir", str(run_dir))
                assert again.returncode == 2, again
                assert "compute node a is already up" in again.stderr

                # kill -9 the runner: rap up logs it and starts it again
                os.kill(pids["runner"], signal.SIGKILL)
                at = await up.line("runner exited with code -9 (killed by SIGKILL)")
                assert "restarting it in 0.5 s (restart 1)" in up.lines[at]
                await up.line("started runner", after=at)
                with anyio.fail_after(UP_TIMEOUT):
                    while (change := await watch.get()).alive or "mon" not in change.key:
                        pass  # mon's token goes with the killed runner ...
                    while not (change := await watch.get()).alive or "mon" not in change.key:
                        pass  # ... and comes back with the new one
            await h.fabric.wait_matched(keys.data("probe", "x/in"), timeout=UP_TIMEOUT)
            await _round_trip(h, "x/in", "seen")

        runner = next(c for c in _state(run_dir, "a")["children"] if c["name"] == "runner")
        assert runner["restarts"] == 1
        assert runner["pid"] not in (None, pids["runner"])
        pids["runner-again"] = runner["pid"]
        log = (run_dir / "a" / "logs" / "runner.log").read_text(encoding="utf-8")
        assert "exited with code -9" in log

        down = await _rap("down", str(model), "--run-dir", str(run_dir))
        assert down.returncode == 0, down
        assert "stopped" in down.stdout
        with anyio.fail_after(UP_TIMEOUT):
            assert await up.proc.wait() == 0, up.output()
    stops = [i for i, line in enumerate(up.lines) if "| stopped " in line]
    order = [up.lines[i].split("| stopped ")[1].split()[0] for i in stops]
    assert order == ["runner", "manager", "knowledge", "router"], up.output()
    assert all(_gone(pid) for pid in pids.values()), pids
    assert _state(run_dir, "a")["state"] == "stopped"

    again = await _rap("down", str(model), "--run-dir", str(run_dir))
    assert again.returncode == 0, again
    assert "nothing to stop" in again.stdout
    health = await _rap("health", str(model), "--node", "a", "--run-dir", str(run_dir))
    assert health.returncode == 2, health
    assert "no rap up runs compute node a" in health.stderr


@pytest.mark.zenoh
async def test_two_nodes_route_through_their_routers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = _model(tmp_path, TWO_NODES)
    run_dir = tmp_path / "run"
    async with rap_up(str(model), "--all", "--run-dir", str(run_dir)) as up:
        await up.line("compute node b is up")
        # b's router links to a's: b connects to a's local endpoint
        b_conf = json.loads(
            "\n".join(
                line
                for line in (run_dir / "b" / "zenoh-router.json5").read_text().splitlines()
                if not line.startswith("//")
            )
        )
        assert b_conf["connect"]["endpoints"] == [_state(run_dir, "a")["router"]]
        # the test is a client of b's router; mon runs on a, ana on b
        async with observer(monkeypatch, run_dir, "b", "probe2") as h:
            health = await _rap(
                "health",
                str(model),
                "--node",
                "b",
                env=_env(**{CONFIG_ENV: str(run_dir / "b" / "zenoh-client.json5")}),
            )
            assert health.returncode == 0, health
            assert "alive: ana" in health.stdout
            await h.fabric.wait_matched(keys.data("probe2", "x/in"), timeout=UP_TIMEOUT)
            await h.fabric.wait_matched(keys.event("probe2", "seen"), timeout=UP_TIMEOUT)
            seen = await _rap(
                "health", str(model), "--node", "a", "--run-dir", str(run_dir), "--timeout", "20"
            )
            assert seen.returncode == 0, seen
            done = await _round_trip(h, "x/in", "done")  # mon on a, then ana on b
            assert done.envelope is not None
            assert done.envelope.source == "ana"
            seen_env = h.of(keys.Kind.EVENT, "seen")[-1].envelope
            assert seen_env is not None
            assert seen_env.source == "mon"
        up.proc.send_signal(signal.SIGTERM)
        with anyio.fail_after(UP_TIMEOUT):
            assert await up.proc.wait() == 0, up.output()
    assert "received SIGTERM" in up.output()


@pytest.mark.zenoh
async def test_a_relay_node_runs_its_router_and_a_broken_child_is_restarted(
    tmp_path: Path,
) -> None:
    model = _model(tmp_path, RELAY_AND_BROKEN)
    run_dir = tmp_path / "run"
    async with rap_up(str(model), "--all", "--run-dir", str(run_dir)) as up:
        await up.line("compute node g is up")
        assert set(_pids(run_dir, "relay")) == {"router"}
        # the runner cannot import its Node: it exits 2, and is restarted with backoff
        at = await up.line("g/runner exited with code 2", "restarting it in 0.5 s (restart 1)")
        await up.line("g/runner exited with code 2", "restarting it in 1 s (restart 2)", after=at)
        relay = await _rap("health", str(model), "--node", "relay", "--run-dir", str(run_dir))
        assert relay.returncode == 0, relay
        assert "no Nodes to check" in relay.stdout
        g = await _rap(
            "health", str(model), "--node", "g", "--run-dir", str(run_dir), "--timeout", "1"
        )
        assert g.returncode == 1, g
        assert "not alive within 1 s: ghost (alive: knowledge)" in g.stderr
        # a router killed comes back with the same Zenoh id: the other router knows it again
        os.kill(_pids(run_dir, "relay")["router"], signal.SIGKILL)
        at = await up.line("relay/router exited with code -9")
        await up.line("relay/router", "listening on", after=at)
        await up.line("g/router", f"link to {router_id('probe3', 'relay')} restored", after=at)
        pids = {**_pids(run_dir, "relay"), **{f"g/{k}": v for k, v in _pids(run_dir, "g").items()}}
        up.proc.send_signal(signal.SIGTERM)
        with anyio.fail_after(UP_TIMEOUT):
            assert await up.proc.wait() == 0, up.output()
    assert all(_gone(pid) for pid in pids.values()), pids


@pytest.mark.zenoh
async def test_a_router_that_cannot_listen_fails_rap_up(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        model = _model(
            tmp_path, ONE_NODE.replace("a: {}", f"a: {{listen: [tcp/127.0.0.1:{port}]}}")
        )
        result = await _rap("up", str(model))
    assert result.returncode == 1, result
    err = result.stderr.strip().splitlines()[-1]
    assert err.startswith("rap: error: the router of compute node a exited with code 1"), err
    assert "Address already in use" in err
    assert "started runner" not in result.stdout  # nothing but the router was started
    state = _state(model.parent / ".rap" / "probe", "a")
    assert state["state"] == "stopped"
    assert (model.parent / ".rap" / ".gitignore").read_text().endswith("*\n")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["up", "{model}", "--node", "a"], "model.yaml:5:12: Invalid enum value"),
        (["down", "{model}"], "model.yaml:5:12: Invalid enum value"),
        (["health", "{model}", "--node", "a"], "model.yaml:5:12: Invalid enum value"),
    ],
    ids=["up", "down", "health"],
)
async def test_a_model_error_exits_2_with_file_line_col(
    tmp_path: Path, args: list[str], message: str
) -> None:
    model = _model(tmp_path, ONE_NODE.replace("backend: memory", "backend: mongo"))
    result = await _rap(*(a.replace("{model}", str(model)) for a in args))
    assert result.returncode == 2, result
    assert result.stderr.startswith(f"rap: error: {model.parent}/{message}"), result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    assert not (model.parent / ".rap").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["up", "{model}", "--node", "z"], "--node 'z' is not a compute node of the model"),
        (["up", "{model}", "--node", "a", "--all"], "give --node or --all, not both"),
        (["up", "{model}", "--address", "a"], "--address 'a' is not NODE=HOST"),
        (["up", "{model}", "--log-level", "LOUD"], "--log-level 'LOUD' is not a logging level"),
        (["health", "{model}", "--connect", "nowhere"], "--connect 'nowhere' is not a Zenoh"),
    ],
    ids=["unknown-node", "node-and-all", "bad-address", "bad-level", "bad-endpoint"],
)
async def test_bad_usage_exits_2_with_one_line(
    tmp_path: Path, args: list[str], message: str
) -> None:
    model = _model(tmp_path, ONE_NODE)
    result = await _rap(*(a.replace("{model}", str(model)) for a in args))
    assert result.returncode == 2, result
    assert message in result.stderr, result.stderr
    assert result.stderr.count("\n") == 1, result.stderr


THREE = """\
system: s
compute_nodes:
  a: {listen: ["tcp/a:7447"]}
  b: {connect: ["tcp/a:7447"]}
  c: {}
  d: {listen: ["tcp/0.0.0.0:7500"]}
"""


def test_all_links_the_routers_into_one_graph(tmp_path: Path) -> None:
    from rap_cli.up import plan_run
    from rap_schemas import parse_plan

    doc = parse_plan(THREE, "m.yaml")
    here = dict.fromkeys(doc.plan.compute_nodes, "127.0.0.1")
    runs = {
        r.node: r
        for r in plan_run(
            doc, tmp_path / "m.yaml", list("abcd"), tmp_path, addresses=here, link=True
        )
    }
    listen = {n: r.router["listen"]["endpoints"] for n, r in runs.items()}
    connect = {n: r.router["connect"]["endpoints"] for n, r in runs.items()}
    assert listen["a"] == [runs["a"].local, "tcp/127.0.0.1:7447"]  # a node's name resolved
    assert listen["d"] == [runs["d"].local, "tcp/0.0.0.0:7500"]
    assert connect["a"] == []
    assert connect["b"] == ["tcp/127.0.0.1:7447"]  # the model's link to a: enough
    assert connect["c"] == [runs["a"].local]  # apart: linked to the first node
    assert connect["d"] == [runs["a"].local]
    assert len({r.local for r in runs.values()}) == 4
    for n, r in runs.items():
        assert r.client["mode"] == "client"
        assert r.client["connect"]["endpoints"] == [r.local]
        assert r.router["id"] == router_id("s", n)
        assert r.processes[0].name == "router"
    assert len({router_id("s", n) for n in "abcd"}) == 4

    alone = plan_run(doc, tmp_path / "m.yaml", ["c"], tmp_path)[0]
    assert alone.router["connect"]["endpoints"] == []


@pytest.mark.zenoh
async def test_processes_left_by_a_killed_rap_up_stop_a_new_one_until_rap_down(
    tmp_path: Path,
) -> None:
    model = _model(tmp_path, ONE_NODE)
    run_dir = model.parent / ".rap" / "probe"
    async with rap_up(str(model)) as up:
        await up.line("compute node a is up")
        pids = _pids(run_dir, "a")
        up.proc.kill()  # SIGKILL: rap up cannot stop its processes
        await up.proc.wait()
    assert not any(_gone(pid) for pid in pids.values())
    again = await _rap("up", str(model))
    assert again.returncode == 2, again
    assert "an earlier rap up died without stopping its processes" in again.stderr
    assert f"runner pid {pids['runner']}" in again.stderr
    down = await _rap("down", str(model))
    assert down.returncode == 0, down
    assert "left behind" in down.stdout
    # rap down waits until they have exited (a zombie whose parent is gone has)
    assert all(_gone(pid) or _zombie(pid) for pid in pids.values())
