"""The lidar-occlusion model on two hosts: ``rap up --node edge`` in one network namespace,
``rap up --node robot`` in another, joined by a veth pair. The loop closes across the
link; cutting the link for 5 s is logged by both routers (the loss while it is down, the
return after) and the loop resumes afterwards.

The hosts are network namespaces this test creates (it needs root and iproute2's ``ip``;
without them it is skipped, or fails when ``RAP_REQUIRE_SERVICES=1``). It watches the
loop from inside the robot's namespace: this file doubles as the observer,
``python test_two_hosts.py ENDPOINT SYSTEM``, a Zenoh client of the robot's router that
prints one JSON line per event and data sample of the system.

The simulator runs a world whose occlusion changes every 2 s (the model's default world
has a single one, from 6 s to 36 s of sim time), so that there is something new to
handle once the link is back.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any, NoReturn

import anyio
import msgspec
import pytest
import yaml
from anyio.abc import TaskStatus
from rap_sdk.testing import HostsUnavailable, OutputLines, TwoHosts, stop_process, two_hosts

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
PLAN_TOPIC = "tb1/spin_config"
CUT = 5.0
"""Seconds the link stays down (the routers' lease is 3 s: they notice)."""

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(150)]


# -- the observer (python test_two_hosts.py ENDPOINT SYSTEM, inside a namespace) ----------


async def _observe(endpoint: str, system: str) -> None:
    from rap_schemas import Envelope, Verdict, keys
    from rap_sdk import ZenohConfig, ZenohFabric

    envelope = msgspec.msgpack.Decoder(Envelope)
    verdict = msgspec.msgpack.Decoder(Verdict[Any])
    out = sys.stdout

    def say(**line: Any) -> None:
        out.write(json.dumps({"t": time.monotonic(), **line}) + "\n")
        out.flush()

    config = ZenohConfig(mode="client", listen=[], connect=[endpoint])
    async with ZenohFabric(config) as fabric:

        async def follow(kind: keys.Kind, *, task_status: TaskStatus[None]) -> None:
            with fabric.subscribe(keys.pattern(system, kind)) as sub:
                task_status.started()
                async for sample in sub:
                    name = keys.parse(sample.key).name
                    approved = None
                    if kind is keys.Kind.EVENT and name == "verdict":
                        body = envelope.decode(sample.payload).body
                        approved = verdict.decode(body).approved
                    say(kind=kind.value, name=name, approved=approved)

        async with anyio.create_task_group() as tg:
            for kind in (keys.Kind.EVENT, keys.Kind.DATA):
                await tg.start(partial(follow, kind))
            say(kind="ready", name=endpoint, approved=None)


# -- two hosts: network namespaces and a veth pair ------------------------------------------


def _unavailable(problem: str) -> NoReturn:
    """Skip: this machine cannot make the hosts; fail instead where they are required."""
    from rap_sdk.testing import REQUIRE_SERVICES

    if os.environ.get(REQUIRE_SERVICES) == "1":
        pytest.fail(f"{problem} ({REQUIRE_SERVICES}=1: the two-host test must run)")
    pytest.skip(problem)


@pytest.fixture
def hosts() -> Iterator[TwoHosts]:
    """Two namespaces and a veth pair (rap_sdk.testing.two_hosts); a failed clean-up
    fails the test."""
    try:
        with two_hosts("rap", 231) as h:
            yield h
    except HostsUnavailable as exc:
        _unavailable(str(exc))


# -- output of other processes, line by line ------------------------------------------------


@dataclass(frozen=True, slots=True)
class Seen:
    """One line of the observer."""

    t: float
    """``time.monotonic()`` in the observer: one clock for every namespace."""
    kind: str
    name: str
    approved: bool | None


class Watch:
    """What the observer saw."""

    def __init__(self, lines: OutputLines) -> None:
        self.lines = lines

    @property
    def seen(self) -> list[Seen]:
        return [Seen(**json.loads(line)) for line in self.lines.lines]

    async def first(self, pred: Callable[[Seen], bool], since: float) -> Seen:
        def match(line: str) -> bool:
            s = Seen(**json.loads(line))
            return s.t >= since and pred(s)

        return Seen(**json.loads(self.lines.lines[await self.lines.first(match)]))

    async def loop_closes(self, since: float, timeout: float) -> tuple[Seen, Seen, Seen]:
        """An anomaly (raised on the edge), then an approving verdict (the edge), then the
        plan at the robot, all seen at or after ``since``."""
        try:
            with anyio.fail_after(timeout):
                a = await self.first(lambda s: s.kind == "event" and s.name == "anomaly", since)
                v = await self.first(lambda s: s.name == "verdict" and bool(s.approved), a.t)
                p = await self.first(lambda s: s.kind == "data" and s.name == PLAN_TOPIC, v.t)
        except TimeoutError:
            counts: dict[str, int] = {}
            for s in self.seen:
                if s.t >= since:
                    what = f"{s.kind} {s.name}" + ("" if s.approved is None else f" {s.approved}")
                    counts[what] = counts.get(what, 0) + 1
            raise AssertionError(f"no loop closed within {timeout:g} s; seen: {counts}") from None
        return a, v, p


# -- rap up in a namespace -------------------------------------------------------------------


def _rap() -> str:
    rap = Path(sys.executable).with_name("rap")
    assert rap.exists(), f"{rap}: the rap command is not installed next to {sys.executable}"
    return str(rap)


def _local_endpoint(node_dir: Path) -> str:
    """The router's loopback endpoint, where the node's processes connect."""
    text = (node_dir / "zenoh-router.json5").read_text()
    conf = json.loads("\n".join(x for x in text.splitlines() if not x.lstrip().startswith("//")))
    for ep in conf["listen"]["endpoints"]:
        host = ep.split("/", 1)[1].rsplit(":", 1)[0]
        if host.startswith("127.") or host in ("[::1]", "localhost"):
            return str(ep)
    raise AssertionError(f"{node_dir}: the router listens on no loopback endpoint: {conf}")


def _model_with_world(tmp_path: Path) -> Path:
    """The case's model, its simulator in the default world with an occlusion that
    changes every 2 s."""
    from sim_world.world import default_world_path

    world = yaml.safe_load(default_world_path().read_text())
    world["occlusions"] = [{"robot": "tb1", "mode": "random", "period": 2.0, "t_start": 1.0}]
    world_path = tmp_path / "changing.yaml"
    world_path.write_text(yaml.safe_dump(world))
    model = yaml.safe_load(MODEL.read_text())
    run = model["components"]["robot"]["run"]
    run[run.index("--world") + 1] = str(world_path)
    out = tmp_path / "model.yaml"
    out.write_text(yaml.safe_dump(model, sort_keys=False))
    return out


@contextlib.asynccontextmanager
async def _rap_up(
    ns: str, model: Path, node: str, run_dir: Path, edge_ip: str
) -> AsyncIterator[None]:
    """``rap up MODEL --node NODE`` inside namespace ``ns``, until it says the node is up;
    ``rap down`` on exit (it must stop it)."""
    argv = [*("ip", "netns", "exec", ns), _rap(), "up", str(model), "--node", node]
    argv += ["--address", f"edge={edge_ip}", "--run-dir", str(run_dir)]
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT) as proc,
        anyio.create_task_group() as tg,
    ):
        out = OutputLines(proc)
        tg.start_soon(out.pump)
        try:
            with anyio.fail_after(30):
                await out.line(f"compute node {node} is up")
            yield
            down = [_rap(), "down", str(model), "--node", node, "--run-dir", str(run_dir)]
            res = await anyio.run_process(down, check=False, stderr=subprocess.STDOUT)
            assert res.returncode == 0, res.stdout.decode()
            with anyio.fail_after(30):
                assert await proc.wait() == 0, "\n".join(out.lines[-50:])
        finally:
            await stop_process(proc)  # a failure: it still stops what it started
            tg.cancel_scope.cancel()


@contextlib.asynccontextmanager
async def _observer(ns: str, endpoint: str, stderr: Path) -> AsyncIterator[Watch]:
    """The observer in namespace ``ns``, a client of the router at ``endpoint``."""
    argv = [*("ip", "netns", "exec", ns), sys.executable, __file__, endpoint, SYSTEM]
    with stderr.open("wb") as err:
        async with (
            await anyio.open_process(argv, stderr=err) as proc,
            anyio.create_task_group() as tg,
        ):
            lines = OutputLines(proc, timeout=600)  # the callers' deadlines rule
            tg.start_soon(lines.pump)
            try:
                watch = Watch(lines)
                with anyio.fail_after(30):
                    await watch.first(lambda s: s.kind == "ready", 0.0)
                yield watch
            finally:
                await stop_process(proc, grace=10)
                tg.cancel_scope.cancel()


# -- what the routers logged ------------------------------------------------------------------

_STAMP = "%Y-%m-%d %H:%M:%S,%f"


def _router_zid(log: str) -> str:
    m = re.search(r"rap\.router: router (\w+) listening on", log)
    assert m is not None, log
    return m[1]


def _links(log: str, peer: str) -> list[tuple[datetime, str]]:
    """When the router's link to router ``peer`` came up, was lost, was restored."""
    pattern = re.compile(
        rf"^(\S+ \S+) \w+ rap\.router: link to {peer} (up|lost|restored) \(router", re.M
    )
    return [(datetime.strptime(m[1], _STAMP), m[2]) for m in pattern.finditer(log)]


async def test_the_loop_closes_across_two_hosts_and_resumes_after_a_cut(
    hosts: TwoHosts, tmp_path: Path
) -> None:
    model = _model_with_world(tmp_path)
    runs = {"edge": tmp_path / "edge", "robot": tmp_path / "robot"}
    async with contextlib.AsyncExitStack() as stack:
        for node, ns in (("edge", hosts.edge), ("robot", hosts.robot)):
            up = _rap_up(ns, model, node, runs[node], hosts.edge_ip)
            await stack.enter_async_context(up)
        endpoint = _local_endpoint(runs["robot"] / "robot")
        watch = await stack.enter_async_context(
            _observer(hosts.robot, endpoint, tmp_path / "observer.err")
        )
        # the loop closes across the link: anomaly (edge), verdict (edge), plan (robot)
        await watch.loop_closes(0.0, timeout=30)

        cut, cut_wall = time.monotonic(), datetime.now()
        await anyio.run_process(["ip", "-n", hosts.robot, "link", "set", hosts.robot_dev, "down"])
        await anyio.sleep(CUT)  # the outage under test
        await anyio.run_process(["ip", "-n", hosts.robot, "link", "set", hosts.robot_dev, "up"])
        restored, restored_wall = time.monotonic(), datetime.now()

        # the robot went on scanning, but nothing of the edge's reached it meanwhile
        during = [s for s in watch.seen if cut + 1.0 < s.t < restored]
        assert any(s.name == "tb1/scan" for s in during), during
        assert not [s for s in during if s.name in ("anomaly", "verdict")], during
        # and over the restored link the loop closes again
        await watch.loop_closes(restored, timeout=30)
    # both routers logged the loss while the link was down, and its return after
    logs = {n: (runs[n] / n / "logs" / "router.log").read_text(errors="replace") for n in runs}
    for node, other in (("robot", "edge"), ("edge", "robot")):
        links = _links(logs[node], _router_zid(logs[other]))
        assert [what for _, what in links[:3]] == ["up", "lost", "restored"], logs[node]
        (_, _), (lost, _), (back, _) = links[:3]
        assert cut_wall < lost < restored_wall, (cut_wall, lost, restored_wall, logs[node])
        assert back > restored_wall, (restored_wall, back, logs[node])


if __name__ == "__main__":
    anyio.run(_observe, sys.argv[1], sys.argv[2])
