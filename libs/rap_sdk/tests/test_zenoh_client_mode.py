"""Sessions in client mode behind a Zenoh router (how ``rap up`` runs every process of
a compute node), and the Zenoh config overlay that makes them clients."""

from __future__ import annotations

import json

import anyio
import pytest
import zenoh
from rap_schemas.limits import MAX_MESSAGE_BYTES, MESSAGE_HEADROOM
from rap_sdk import FabricError, ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port, node_overlay

pytestmark = pytest.mark.anyio


async def test_a_client_delivers_the_first_samples_on_each_new_key() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    client = ZenohConfig(mode="client", listen=[], connect=[ep])
    async with (
        ZenohFabric(ZenohConfig(mode="router", listen=[ep])),
        ZenohFabric(client) as sub_f,
        ZenohFabric(client) as pub_f,
    ):
        with sub_f.subscribe("first/**") as sub:
            await anyio.sleep(0.5)  # the subscription reaches the router
            for i in range(3):  # new keys: nothing told the publisher of a match yet
                await pub_f.publish(f"first/key{i}", b"one")
                await pub_f.publish(f"first/key{i}", b"two")
            got = []
            with anyio.fail_after(5):
                while len(got) < 6:
                    got.append((await sub.get()).key)
    assert sorted(got) == sorted(f"first/key{i}" for i in range(3) for _ in range(2))


def test_the_sample_limit_reaches_zenoh() -> None:
    for conf, limit in [
        (ZenohConfig(), MAX_MESSAGE_BYTES),
        (ZenohConfig(max_sample_bytes=1 << 20), 1 << 20),
    ]:
        zconf = zenoh.Config.from_json5(conf.to_json5())
        rx = json.loads(zconf.get_json("transport/link/rx/max_message_size"))
        assert rx == limit + MESSAGE_HEADROOM


def test_the_overlay_makes_a_client_that_never_listens() -> None:
    text = "// the node's client config\n" + json.dumps(
        {"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7446"]}, "x": {"y": 1}}
    )
    conf = node_overlay(ZenohConfig(), text)
    assert conf.mode == "client"
    assert conf.listen == []
    assert conf.connect == ["tcp/127.0.0.1:7446"]
    assert conf.extra == {"x": {"y": 1}}


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("{", "not a JSON Zenoh config"),
        ("[]", "a Zenoh config is a JSON object"),
        ('{"mode": "satellite"}', "is not peer, client or router"),
        ('{"connect": {"endpoints": "tcp/x:1"}}', "must be a list of endpoints"),
    ],
)
def test_a_bad_overlay_is_refused_with_the_reason(text: str, says: str) -> None:
    with pytest.raises(FabricError, match=says):
        node_overlay(ZenohConfig(), text, source="node.json5")
