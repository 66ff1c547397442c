"""A plan's share running on MemoryFabric: events in, events out, a graceful stop."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from functools import partial

import anyio
import pytest
from maplek_runner import LoadError, fabric_config, run_plan
from rap_schemas import LaserScan, keys, pack_ranges, parse_plan
from rap_schemas.limits import MESSAGE_HEADROOM
from rap_sdk import NodeGroup, ZenohConfig
from rap_sdk.testing import Harness

from services.maplek_runner.tests import sample_nodes  # the name plans use (see plans.py)
from services.maplek_runner.tests.plans import PLAN

pytestmark = pytest.mark.anyio

SCAN = LaserScan(
    stamp=1,
    frame_id="base_link",
    angle_min=-math.pi,
    angle_increment=0.1,
    range_min=0.1,
    range_max=12.0,
    ranges=pack_ranges([1.0, math.inf]),
)


@pytest.fixture(autouse=True)
def fresh_config() -> Iterator[None]:
    yield
    sample_nodes.relay.config = sample_nodes.RelayConfig()


async def test_a_share_runs_its_components_until_stopped() -> None:
    doc = parse_plan(PLAN, "p.yaml")
    stop = anyio.Event()
    async with Harness(system="demo") as h, anyio.create_task_group() as tg:
        group: NodeGroup = await tg.start(
            partial(run_plan, doc, "laptop", fabric=h.fabric, stop=stop)
        )
        assert [rt.node.name for rt in group.runtimes] == ["echo", "relay"]

        ping = await h.publish("ping", SCAN)
        pong = await h.expect_data("pong")
        assert pong.decode(LaserScan) == SCAN
        assert pong.envelope is not None
        assert pong.envelope.cycle == ping.uid

        tick = await h.emit("tick")
        tack = await h.expect_event("tack")  # the plan's config, not the Node's default
        assert tack.envelope is not None
        assert tack.envelope.cause == tick.uid
        assert not h.of(keys.Kind.EVENT, "tock")
        assert not h.rejections()

        for _ in range(20):  # queued when the stop comes: still handled
            await h.emit("tick")
        stop.set()
    assert group["relay"].stats.handled == 21
    assert group["echo"].stats.handled == 1


async def test_two_compute_nodes_of_one_plan_share_a_fabric() -> None:
    doc = parse_plan(PLAN)
    stop = anyio.Event()
    async with Harness(system="demo") as h, anyio.create_task_group() as tg:
        with h.fabric.watch_liveliness(keys.pattern("demo", keys.Kind.ALIVE)) as watch:
            for node in ("laptop", "robot"):
                await tg.start(partial(run_plan, doc, node, fabric=h.fabric, stop=stop))
            alive = set()
            with anyio.fail_after(5):
                while len(alive) < 3:
                    change = await watch.get()
                    alive.add(keys.parse(change.key).name)
        assert alive == {"echo", "relay", "silent"}
        stop.set()


async def test_the_system_can_be_overridden() -> None:
    stop = anyio.Event()
    async with Harness(system="other") as h, anyio.create_task_group() as tg:
        await tg.start(
            partial(
                run_plan, parse_plan(PLAN), "laptop", fabric=h.fabric, system="other", stop=stop
            )
        )
        await h.publish("ping", SCAN)
        await h.expect_data("pong")
        stop.set()


async def test_a_share_that_cannot_load_raises_before_running() -> None:
    async with Harness(system="demo") as h:
        with pytest.raises(LoadError, match="compute node 'desk' is not in the plan"):
            await run_plan(parse_plan(PLAN), "desk", fabric=h.fabric)


def test_cli_endpoints_replace_the_plans() -> None:
    plan = parse_plan(
        "system: s\ncompute_nodes:\n"
        "  a: {listen: [tcp/0.0.0.0:7447], connect: [tcp/10.0.0.2:7447]}\n"
        "  b: {}\n"
    ).plan
    assert fabric_config(plan, "a") == ZenohConfig(
        listen=["tcp/0.0.0.0:7447"], connect=["tcp/10.0.0.2:7447"]
    )
    assert fabric_config(plan, "a", listen=["tcp/127.0.0.1:1"]) == ZenohConfig(
        listen=["tcp/127.0.0.1:1"], connect=["tcp/10.0.0.2:7447"]
    )
    assert fabric_config(plan, "a", connect=["tcp/127.0.0.1:2"]).connect == ["tcp/127.0.0.1:2"]
    assert fabric_config(plan, "b") == ZenohConfig()  # the fabric's own default
    with pytest.raises(LoadError, match="compute nodes are: a, b"):
        fabric_config(plan, "c")


def test_the_models_sample_limit_reaches_the_session() -> None:
    plan = parse_plan("system: s\ncompute_nodes: {a: {}}\nfabric: {max_sample_bytes: 65536}\n")
    conf = fabric_config(plan.plan, "a")
    assert conf.max_sample_bytes == 65536
    link = json.loads(conf.to_json5())["transport"]["link"]
    assert link["rx"]["max_message_size"] == 65536 + MESSAGE_HEADROOM
