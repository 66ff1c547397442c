"""Unmodified RPIO 0.4.3 nodes as stages of RAP's lidar-occlusion loop
(docs/migrating-from-rpio.md).

Each case runs RAP's loop (lidar_occlusion.nodes, the knowledge service, the in-memory
fabric) with ONE stage replaced by its stand-in from lidar_occlusion.rpio, and the RPIO
node of that stage (bench/loop/rpio_peer.py's rpclpy node, run by the peer's own
interpreter in bench/.rpio-venv with robosapiensio==0.4.3 from PyPI) on a redis-server of
the test's own: the plan reaches the robot, in the cycle of the scan that caused it, with
the stages in order, and the RPIO node handled the request without an error.

The peer venv is built once by bench.loop.peer_venv.ensure_venv() (20 s on the machine
this was written on; pip's own estimate is 1-3 min); without PyPI the tests skip (fail under
RAP_REQUIRE_SERVICES=1). The tests of the adapter's failure handling drive a fake RPIO
stage with redis-py, which lets them send what no rpclpy node would.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import time
from collections.abc import AsyncIterator, Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import anyio
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from lidar_occlusion import nodes, rpio
from lidar_occlusion.scans import occluded_scan
from rap_bridges.core import Backoff
from rap_bridges.rpio import RpioConfig, RpioStage
from rap_cli.testing import model_copy, rap_up
from rap_schemas import (
    LidarMask,
    PlanProposal,
    SpinCommand,
    SpinPlan,
    StageTrace,
    Verdict,
    keys,
)
from rap_sdk import Node
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import (
    Harness,
    OutputLines,
    Record,
    free_port,
    missing_service,
    require_binary,
)
from redis.asyncio import Redis

from bench.loop.peer_venv import PeerVenvError, ensure_venv

# the first test may build the peer venv (see above); each case itself takes a few seconds
pytestmark = [pytest.mark.anyio, pytest.mark.redis, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[1]
PEER = REPO / "bench" / "loop" / "rpio_peer.py"
RPIO_MODEL = REPO / "examples" / "lidar_occlusion" / "rpio_analysis.yaml"
SYSTEM = "lo"
ROBOT = "tb1"
PLAN_TOPIC = f"{ROBOT}/spin_config"


@pytest.fixture(scope="module")
def rpio_python() -> Path:
    """The peer venv's python (built when missing)."""
    try:
        return ensure_venv(quiet=True)
    except PeerVenvError as exc:
        missing_service(f"the RPIO peer venv cannot be built: {exc}")


# -- servers and the RPIO node ------------------------------------------------------------


class RedisServer:
    """A redis-server of the test's own on a free loopback port (keeps nothing)."""

    def __init__(self, directory: Path) -> None:
        self.binary = require_binary("redis-server", hint="apt-get install redis-server")
        self.directory = directory
        self.port = free_port()
        self.proc: Any = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    async def start(self) -> None:
        self.proc = await anyio.open_process(
            [
                *(self.binary, "--bind", "127.0.0.1", "--port", str(self.port)),
                *("--save", "", "--appendonly", "no", "--dir", str(self.directory)),
                *("--logfile", ""),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        out = OutputLines(self.proc, timeout=10)
        async with anyio.create_task_group() as tg:
            tg.start_soon(out.pump)
            await out.line("Ready to accept connections")
            tg.cancel_scope.cancel()

    async def stop(self) -> None:
        if self.proc is not None:
            proc, self.proc = self.proc, None
            with anyio.CancelScope(shield=True):
                proc.terminate()
                await proc.wait()
                await proc.aclose()


@contextlib.asynccontextmanager
async def redis_server(directory: Path) -> AsyncIterator[RedisServer]:
    server = RedisServer(directory)
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


async def subscribed(url: str, channel: str, *, timeout: float = 20.0) -> None:
    """Until some client subscribes to ``channel`` (the RPIO node's readiness: rpclpy
    subscribes in its listener, after it said nothing we could wait on)."""
    client = Redis.from_url(url)
    try:
        with anyio.fail_after(timeout):
            while True:
                counts = dict(await client.pubsub_numsub(channel))
                if counts.get(channel.encode(), 0) > 0:
                    return
                await anyio.sleep(0.02)  # polling another process's state: no event to await
    finally:
        await client.aclose()


@contextlib.asynccontextmanager
async def rpio_node(
    python: Path, role: str, redis: RedisServer, directory: Path, *, variant: str = "redis",
    mqtt_port: int = 0,
) -> AsyncIterator[dict[str, Any]]:  # fmt: skip
    """The unmodified RPIO node of ``role`` (rpclpy, in the peer venv) until the block
    ends; the dict then holds its own count of what it handled (``handled``, ``errors``)."""
    stats_file = directory / f"{role}.stats.json"
    argv = [str(python), str(PEER), "node", "--role", role, "--variant", variant]
    argv += ["--stats", str(stats_file), "--redis-port", str(redis.port)]
    argv += ["--mqtt-port", str(mqtt_port)]
    stats: dict[str, Any] = {}
    async with await anyio.open_process(argv, stderr=subprocess.STDOUT) as proc:
        out = OutputLines(proc, timeout=30)
        async with anyio.create_task_group() as tg:
            tg.start_soon(out.pump)
            try:
                await out.line("READY")
                yield stats
            finally:
                with anyio.CancelScope(shield=True):
                    proc.terminate()  # the node writes its stats and exits
                    with anyio.fail_after(10):
                        await proc.wait()
                tg.cancel_scope.cancel()
        if stats_file.exists():
            stats.update(json.loads(stats_file.read_text()))
        stats["output"] = str(out)


# -- the loop -----------------------------------------------------------------------------

ROLES = {
    "monitor": ("Monitor", "/Scan"),
    "analysis": ("Analysis", "new_data"),
    "planner": ("Plan", "anomaly"),
    "legitimate": ("Legitimate", "new_plan"),
    "executor": ("Execute", "isLegit"),
}
"""RAP stage -> (the RPIO node's role in rpio_peer.py, the channel it listens on)."""
STAGE_ORDER = ["monitor", "analyse", "plan", "legitimate", "execute"]


def loop_with(stage: str, config: RpioConfig) -> tuple[list[Node], RpioStage]:
    """RAP's five stages with ``stage`` replaced by RPIO's stand-in."""
    loop = nodes.build(ROBOT)
    stand_in = getattr(rpio.build(ROBOT, config=config), stage)
    rap = {
        "monitor": loop.monitor,
        "analysis": loop.analyse,
        "planner": loop.plan,
        "legitimate": loop.legitimate,
        "executor": loop.execute,
    }
    rap[stage] = stand_in.node
    return list(rap.values()), stand_in


@contextlib.asynccontextmanager
async def running(members: list[Node]) -> AsyncIterator[Harness]:
    async with Harness(system=SYSTEM, timeout=10) as h:
        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))
        await h.start(*members)
        yield h


def cycle_stages(h: Harness, cycle: bytes) -> list[str]:
    starts: list[StageTrace] = [t for t in h.traces() if t.started and t.cycle == cycle]
    return [t.stage.value if t.stage else "" for t in starts]


@pytest.mark.parametrize("stage", ["monitor", "analysis", "planner", "legitimate", "executor"])
async def test_the_loop_closes_with_one_stage_being_the_unmodified_rpio_node(
    stage: str, rpio_python: Path, tmp_path: Path
) -> None:
    role, listens = ROLES[stage]
    async with (
        redis_server(tmp_path) as redis,
        rpio_node(rpio_python, role, redis, tmp_path) as peer,
    ):
        await subscribed(redis.url, listens)
        members, stand_in = loop_with(stage, RpioConfig(url=redis.url, timeout=5.0))
        async with contextlib.aclosing(stand_in), running(members) as h:
            scan = await h.publish(f"{ROBOT}/scan", occluded_scan(-0.4, 0.8))
            plan_rec = await h.expect_data(PLAN_TOPIC)
            plan = plan_rec.decode(SpinPlan)
            # in the scan's cycle, the five stages in causal order, RPIO's among them
            assert plan_rec.envelope is not None
            assert plan_rec.envelope.cycle == scan.uid
            await h.wait_for(lambda r: "execute" in cycle_stages(h, scan.uid))
            assert cycle_stages(h, scan.uid) == STAGE_ORDER
            if stage == "planner":  # RPIO's plan: one fixed turn (RAP's: both ends and back)
                assert [(c.omega, c.duration) for c in plan.commands] == [(1.0, 0.5)]
                assert plan.period == 8.0
            else:  # RAP's plan for the +-0.4 rad sector, through RPIO's stage unchanged
                assert len(plan.commands) == 3
                assert sum(c.omega * c.duration for c in plan.commands) == pytest.approx(0)
            if stage == "analysis":  # the mask is RPIO's: the beams with no return
                mask = h.of(keys.Kind.EVENT, "anomaly")[0].decode(LidarMask)
                ranges = occluded_scan(-0.4, 0.8).values()
                assert list(mask.occluded) == [1 if math.isinf(r) else 0 for r in ranges]
            assert not h.rejections()
            assert stand_in.stats.answered >= 1
            assert stand_in.stats.rejections.total == 0
    assert peer.get("errors") == 0, peer.get("output")
    assert peer.get("handled", 0) >= 1, peer.get("output")


# -- the adapter's handling of what an RPIO side may do ----------------------------------
# A fake RPIO stage (redis-py in the test) answers as the test says, which no rpclpy node
# would: malformed, stale or no answers, bad knowledge.

Answer = Callable[[Redis, dict[str, Any]], Any]


@contextlib.asynccontextmanager
async def fake_stage(url: str, listens: str, answer: Answer) -> AsyncIterator[list[dict[str, Any]]]:
    """Subscribes to ``listens`` and calls ``answer(client, event)`` for each event; yields
    the events it got."""
    client = Redis.from_url(url)
    pubsub: Any = client.pubsub(ignore_subscribe_messages=True)
    await pubsub.subscribe(listens)
    seen: list[dict[str, Any]] = []

    async def serve() -> None:
        async for msg in pubsub.listen():
            if msg["type"] == "message":
                event = json.loads(msg["data"])
                seen.append(event)
                await answer(client, event)

    try:
        async with anyio.create_task_group() as tg:
            tg.start_soon(serve)
            yield seen
            tg.cancel_scope.cancel()
    finally:
        with anyio.CancelScope(shield=True):
            await pubsub.aclose()
            await client.aclose()


def rpclpy_event(seq: int, **extra: Any) -> bytes:
    """An event as rpclpy's publish_event sends it."""
    return json.dumps(
        {"seq": seq, **extra, "uid": "0a1b2c3d", "timestamp": "2026-01-01T00:00:00"}
    ).encode()


def proposal(**kw: Any) -> PlanProposal[SpinPlan]:
    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)], period=8.0)
    fields: dict[str, Any] = {
        "plan_uid": os.urandom(16),
        "plan_type": plan.TYPE,
        "plan": plan,
        "proposer": "planner",
        "created": time.time_ns(),
    }
    fields.update(kw)
    return PlanProposal(**fields)


async def judge(h: Harness, p: PlanProposal[SpinPlan] | None = None) -> Verdict[Any]:
    """Propose ``p`` to the Legitimate stand-in; its verdict."""
    sent = await h.emit("new-plan", p or proposal())
    rec = await h.wait_for(
        lambda r: (
            r.kind is keys.Kind.EVENT
            and r.name == "verdict"
            and r.envelope is not None
            and r.envelope.cause == sent.uid
        )
    )
    return rec.decode(Verdict[Any])


@contextlib.asynccontextmanager
async def legit_stand_in(url: str, **config: Any) -> AsyncIterator[tuple[Harness, RpioStage]]:
    """RPIO's Legitimate stand-in alone, on the test's Redis."""
    stand_in = rpio.build(ROBOT, config=RpioConfig(url=url, **config)).legitimate
    async with contextlib.aclosing(stand_in), running([stand_in.node]) as h:
        yield h, stand_in


async def test_malformed_answers_are_rejected_with_a_reason_and_the_real_one_is_taken(
    tmp_path: Path,
) -> None:
    """Whatever comes on the answer's channel, the stage counts what is not an answer,
    says why, and takes the real answer after it; it tells RAP's cycle to the RPIO side
    in the event it fires (uid: the trigger's uid, rap_cycle)."""
    junk = [
        b"not json",
        b"\xff\xfe",
        b"[1, 2]",
        b'{"seq": %d}',  # no uid nor timestamp: not an rpclpy event
        b'{"seq": %d, "uid": 5, "timestamp": "x"}',
        b'{"seq": %d, "uid": "u", "timestamp": "t", "pad": "' + b"x" * 3000 + b'"}',
        b"[" * 1500,  # nests past the parser's depth
    ]

    async def answer(client: Redis, event: dict[str, Any]) -> None:
        for raw in junk:
            await client.publish("isLegit", raw.replace(b"%d", str(event["seq"]).encode()))
        await client.publish("isLegit", rpclpy_event(event["seq"]))

    async with (
        redis_server(tmp_path) as redis,
        fake_stage(redis.url, "new_plan", answer) as seen,
        legit_stand_in(redis.url, max_bytes=2000) as (h, stand_in),
    ):
        p = proposal()
        sent_at = len(h.records)
        verdict = await judge(h, p)
        assert verdict.approved, verdict.reason
        assert verdict.proposal is not None
        assert verdict.proposal.plan_uid == p.plan_uid
        st = stand_in.stats
        assert st.rejections.total == len(junk)
        reasons = " | ".join(st.rejections.by_reason)
        for part in (
            "not a JSON object",
            "not UTF-N",
            "is not an rpclpy event",
            "over the limit",
            "nests too deeply",
        ):
            assert part in reasons, reasons
        assert (st.calls, st.answered, st.unanswered) == (1, 1, 0)
        # the event the RPIO side got: rpclpy's fields, the request's number, RAP's ids
        trigger = h.records[sent_at].envelope
        assert trigger is not None
        [event] = seen
        assert event["uid"] == trigger.uid.hex()
        assert event["rap_cycle"] == (trigger.cycle or trigger.uid).hex()
        assert event["seq"] == 1
        assert event["plan_uid"] == p.plan_uid.hex()
        datetime.fromisoformat(event["timestamp"])
        # what the stage found in RPIO's knowledge: the plan it was asked to judge
        client = Redis.from_url(redis.url)
        raw = await client.get("directions")
        await client.aclose()
        assert raw is not None
        directions = json.loads(raw)
        assert directions["commands"] == [{"omega": 1.0, "duration": 0.5}]
        assert directions["seq"] == 1


async def test_no_stale_or_absent_answer_approves_a_plan(tmp_path: Path) -> None:
    """A Legitimate stage that says nothing rejects: an answer to another request is
    passed over (then the time runs out), and no RPIO node at all is noticed at once."""

    async def stale(client: Redis, event: dict[str, Any]) -> None:
        await client.publish("isLegit", rpclpy_event(event["seq"] + 1000))

    async with redis_server(tmp_path) as redis:
        async with legit_stand_in(redis.url, timeout=0.3) as (h, stand_in):
            t0 = time.monotonic()
            verdict = await judge(h)
            assert not verdict.approved
            assert "no RPIO node subscribes to 'new_plan'" in verdict.reason
            assert time.monotonic() - t0 < 0.3  # not after the timeout: at once
            assert stand_in.stats.absent == 1
            async with fake_stage(redis.url, "new_plan", stale):
                verdict = await judge(h)
            assert not verdict.approved
            assert "no isLegit from the RPIO stage within 0.3 s" in verdict.reason
            assert h.of(keys.Kind.EVENT, "plan-rejected")  # the planner's cue to replan
            st = stand_in.stats
            assert (st.stale, st.unanswered, st.answered) == (1, 1, 0)


async def test_a_lost_redis_fails_calls_until_it_is_back(tmp_path: Path) -> None:
    """Redis gone: the request fails with the reason (the plan is rejected); back: the
    next request connects again, after the backoff's pause."""

    async def ok(client: Redis, event: dict[str, Any]) -> None:
        await client.publish("isLegit", rpclpy_event(event["seq"]))

    async with redis_server(tmp_path) as redis, legit_stand_in(redis.url) as (h, stand_in):
        stand_in.backoff = Backoff(initial=0.05, max=0.05, jitter=0)
        async with fake_stage(redis.url, "new_plan", ok):
            assert (await judge(h)).approved
        await redis.stop()
        verdict = await judge(h)
        assert not verdict.approved
        assert "RPIO side" in verdict.reason
        await redis.start()  # the same port, an empty server
        async with fake_stage(redis.url, "new_plan", ok):
            # the next call waits out the backoff's pause (0.05 s, within its timeout)
            verdict = await judge(h)
            assert verdict.approved, verdict.reason
        assert stand_in.stats.unreachable == 1
        assert stand_in.stats.connects == 2


BAD_MASKS = {
    "not json": (b"{oops", "not an RPIO mask"),
    "a flag of 2": (b'{"seq": %d, "occluded": [2]}', "Expected `int` <= N"),
    "a flag as text": (b'{"seq": %d, "occluded": ["1"]}', "Expected `int`, got `str`"),
    "too few flags": (b'{"seq": %d, "occluded": [0, 1]}', "flags for a scan of N beams"),
    "pickled": (b"\x80\x04\x95\x00", "pickled object"),
    "another request's": (b'{"seq": 999, "occluded": []}', "of request N, not of N"),
}


@pytest.mark.parametrize("bad", list(BAD_MASKS))
async def test_bad_knowledge_from_the_rpio_stage_is_refused_and_the_next_cycle_runs(
    bad: str, tmp_path: Path
) -> None:
    """The RPIO Analysis's mask is decoded into a rap.LidarMask/2 or refused with the
    reason (no anomaly emitted); the next scan's good mask goes through."""
    raw, reason = BAD_MASKS[bad]

    async def answer(client: Redis, event: dict[str, Any]) -> None:
        seq = event["seq"]
        if seq == 1:
            await client.set("lidar_mask", raw.replace(b"%d", str(seq).encode()))
        else:
            written = await client.get("laser_scan")
            assert written is not None
            scan = json.loads(written)
            flags = [1 if math.isinf(r) else 0 for r in scan["ranges"]]
            await client.set("lidar_mask", json.dumps({"seq": seq, "occluded": flags}))
        await client.publish("anomaly", rpclpy_event(seq))

    loop = nodes.build(ROBOT)
    async with redis_server(tmp_path) as redis, fake_stage(redis.url, "new_data", answer):
        stand_in = rpio.build(ROBOT, config=RpioConfig(url=redis.url)).analysis
        async with contextlib.aclosing(stand_in), running([loop.monitor, stand_in.node]) as h:
            await h.publish(f"{ROBOT}/scan", occluded_scan(-0.4, 0.8, stamp=1))
            await h.wait_for(lambda r: any(t.ended for t in h.traces("analysis")))
            assert stand_in.stats.rejections.total == 1
            [why] = stand_in.stats.rejections.by_reason
            assert reason in why
            assert not h.of(keys.Kind.EVENT, "anomaly")
            await h.publish(f"{ROBOT}/scan", occluded_scan(-0.4, 0.8, stamp=2))
            mask = (await h.expect_event("anomaly")).decode(LidarMask)
            assert sum(mask.occluded) > 40
            assert stand_in.stats.answered == 1


# -- events over MQTT (RPIO's HelloWorld setup: events and messages on a broker) ---------


@contextlib.asynccontextmanager
async def mosquitto(directory: Path) -> AsyncIterator[tuple[int, OutputLines]]:
    """A mosquitto of the test's own on a free loopback port, logging every SUBSCRIBE
    (which is how the test knows the RPIO node listens)."""
    binary = require_binary("mosquitto", hint="apt-get install mosquitto")
    port = free_port()
    conf = directory / "mosquitto.conf"
    text = f"listener {port} 127.0.0.1\nallow_anonymous true\nlog_dest stderr\nlog_type all\n"
    if os.geteuid() == 0:
        text += "user root\n"
    conf.write_text(text)
    async with await anyio.open_process(
        [binary, "-c", str(conf)], stderr=subprocess.STDOUT
    ) as proc:
        out = OutputLines(proc, timeout=20)
        async with anyio.create_task_group() as tg:
            tg.start_soon(out.pump)
            try:
                await out.line("running")
                yield port, out
            finally:
                with anyio.CancelScope(shield=True):
                    proc.terminate()
                    await proc.wait()
                tg.cancel_scope.cancel()


@pytest.mark.parametrize("stage", ["legitimate", "executor"])
async def test_the_loop_closes_with_rpio_events_over_mqtt(
    stage: str, rpio_python: Path, tmp_path: Path
) -> None:
    role, listens = ROLES[stage]
    async with (
        redis_server(tmp_path) as redis,
        mosquitto(tmp_path) as (port, log),
        rpio_node(rpio_python, role, redis, tmp_path, variant="mqtt", mqtt_port=port) as peer,
    ):
        await log.line(f"{listens} (QoS 0)")  # the RPIO node subscribed
        config = RpioConfig(url=redis.url, events=f"mqtt://127.0.0.1:{port}", timeout=5.0)
        members, stand_in = loop_with(stage, config)
        async with contextlib.aclosing(stand_in), running(members) as h:
            scan = await h.publish(f"{ROBOT}/scan", occluded_scan(-0.4, 0.8))
            plan_rec = await h.expect_data(PLAN_TOPIC)
            assert plan_rec.envelope is not None
            assert plan_rec.envelope.cycle == scan.uid
            assert len(plan_rec.decode(SpinPlan).commands) == 3
            assert stand_in.stats.answered == 1
            assert stand_in.stats.absent == 0  # MQTT cannot tell: nothing counted so
    assert peer.get("errors") == 0, peer.get("output")
    assert peer.get("handled", 0) >= 1, peer.get("output")


# -- declared in the model, run by rap up ------------------------------------------------


@pytest.mark.zenoh
@pytest.mark.slow
async def test_rap_up_runs_the_rpio_analysis_the_model_declares(
    rpio_python: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """examples/lidar_occlusion/rpio_analysis.yaml as a user runs it: rap up starts the
    RPIO Redis and RPIO's Analysis node from the peer venv (run:), the runner the stand-in
    (module: lidar_occlusion.rpio:analysis with its config:); the simulator's occlusion is
    found by RPIO's Analysis and the plan reaches the robot."""
    require_binary("redis-server", hint="apt-get install redis-server")
    run = tmp_path / "run"
    copy = model_copy(RPIO_MODEL, tmp_path)
    text = copy.read_text()
    assert text.count("6390") == 3
    assert "{model_dir}/../.." in text
    # a free port for the RPIO Redis; the peer venv and script of this checkout
    text = text.replace("6390", str(free_port())).replace("{model_dir}/../..", str(REPO))
    copy.write_text(text)
    async with rap_up(copy, run):
        monkeypatch.setenv(CONFIG_ENV, str(run / "edge" / "zenoh-client.json5"))
        async with Harness(system="demo", fabric="zenoh", timeout=40) as h:

            def occluded(r: Record) -> bool:
                if r.kind is not keys.Kind.EVENT or r.name != "anomaly":
                    return False
                return sum(r.decode(LidarMask).occluded) > 0

            anomaly = await h.wait_for(occluded)  # from 6 s of sim time on
            assert anomaly.envelope is not None
            assert anomaly.envelope.source == "analysis"
            plan = await h.wait_for(
                lambda r: (
                    r.kind is keys.Kind.DATA
                    and r.name == PLAN_TOPIC
                    and bool(r.decode(SpinPlan).commands)
                ),
                after=h.records.index(anomaly),
            )
            assert plan.envelope is not None
            assert plan.envelope.source == "executor"
        up = json.loads((run / "edge" / "up.json").read_text())
        names = {c["name"] for c in up["children"]}
        assert {"rpio_redis", "rpio_analysis", "runner"} <= names
