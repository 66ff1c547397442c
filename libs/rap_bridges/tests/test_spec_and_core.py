"""The spec's checks, the backoff, the buffer policies and the metrics."""

from __future__ import annotations

import random
from typing import Any

import msgspec
import pytest
from prometheus_client.registry import CollectorRegistry
from rap_bridges import Backoff, Bridge, BridgeSpec, buffer_policy, decode_spec
from rap_bridges.metrics import METRICS, BridgeCollector
from rap_bridges.tcp import encode_frame
from rap_sdk import MemoryFabric, Overflow

from libs.rap_bridges.tests.contract import KEY, Reading

MQTT = {"protocol": "mqtt", "url": "mqtt://127.0.0.1:1883", "address": "a/b"}


def test_a_good_spec_has_defaults() -> None:
    spec = BridgeSpec(**MQTT)  # type: ignore[arg-type]
    assert (spec.format, spec.qos, spec.buffer, spec.overflow) == (
        "envelope",
        1,
        1000,
        "drop-oldest",
    )
    assert (spec.host, spec.port, spec.tls) == ("127.0.0.1", 1883, False)
    assert BridgeSpec(protocol="mqtt", url="mqtts://broker", address="t").port == 8883
    assert BridgeSpec(protocol="tcp", url="tcp://127.0.0.1:0", serve=True).port == 0


@pytest.mark.parametrize(
    ("fields", "says"),
    [
        ({"url": "http://x:1"}, "scheme must be mqtt:// or mqtts://"),
        ({"url": "mqtt://"}, "has no host"),
        ({"url": "mqtt://u:pw@x:1"}, "holds credentials"),
        ({"url": "mqtt://x:1/topic"}, "put the topic, channel, queue or path in address"),
        ({"address": ""}, "needs an address"),
        ({"serve": True}, "serve applies to tcp and websocket only"),
        ({"password_env": "PW"}, "a password needs a username"),
        ({"username": "u", "password_env": "A", "password_file": "f"}, "not both"),
        ({"cert": "c.pem"}, "cert and key go together"),
        ({"ca": "ca.pem"}, "not a TLS URL - write mqtts://127.0.0.1:1883"),
    ],
)
def test_a_bad_spec_says_what_to_write(fields: dict[str, Any], says: str) -> None:
    with pytest.raises(ValueError, match=says.replace("?", r"\?")):
        BridgeSpec(**{**MQTT, **fields})


def test_decoding_names_the_field() -> None:
    with pytest.raises(msgspec.ValidationError, match=r"\$.qos"):
        decode_spec(b'{"protocol": "mqtt", "url": "mqtt://h:1", "address": "t", "qos": 3}')
    with pytest.raises(msgspec.ValidationError, match="unknown field"):
        decode_spec(b'{"protocol": "tcp", "url": "tcp://h:1", "topic": "t"}')
    with pytest.raises(msgspec.ValidationError, match="tcp and websocket only"):
        decode_spec(b'{"protocol": "mqtt", "url": "mqtt://h:1", "address": "t", "serve": true}')
    with pytest.raises(msgspec.ValidationError, match=r"\$.buffer"):
        decode_spec(b'{"protocol": "tcp", "url": "tcp://h:1", "buffer": 0}')


def test_the_overflow_policies_map_onto_the_inbox() -> None:
    def policy(overflow: str) -> tuple[int, Overflow, bool]:
        p = buffer_policy(BridgeSpec(**MQTT, buffer=7, overflow=overflow))  # type: ignore[arg-type]
        return p.capacity, p.overflow, p.block

    assert policy("drop-oldest") == (7, Overflow.LATEST, False)
    assert policy("drop-newest") == (7, Overflow.FIFO, False)
    assert policy("block") == (7, Overflow.FIFO, True)


def test_backoff_grows_with_jitter_up_to_its_max_and_resets() -> None:
    b = Backoff(initial=0.1, max=1.0, multiplier=2.0, jitter=0.2, rng=random.Random(1))
    pauses = [b.next() for _ in range(8)]
    bases = [0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0, 1.0]
    for pause, base in zip(pauses, bases, strict=True):
        assert base * 0.8 <= pause <= base * 1.2
    assert len({round(p / base, 6) for p, base in zip(pauses, bases, strict=True)}) > 1
    b.reset()
    assert 0.08 <= b.next() <= 0.12
    with pytest.raises(ValueError, match="jitter"):
        Backoff(jitter=1.5)
    with pytest.raises(ValueError, match="initial <= max"):
        Backoff(initial=2, max=1)


def test_a_frame_is_length_prefixed_with_a_json_header_map() -> None:
    data = encode_frame(b"xyz", {"rap-cycle": "00"})
    header = b'{"rap-cycle":"00"}'
    assert data == (2 + len(header) + 3).to_bytes(4, "big") + len(header).to_bytes(2, "big") + (
        header + b"xyz"
    )
    assert encode_frame(b"") == b"\x00\x00\x00\x02\x00\x00"


def test_json_and_raw_need_the_message_type() -> None:
    with pytest.raises(ValueError, match="needs the port's message type"):
        Bridge("b", BridgeSpec(**MQTT, format="json"), MemoryFabric(), KEY, direction="in")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="an in bridge publishes on one key"):
        Bridge("b", BridgeSpec(**MQTT), MemoryFabric(), "rap/s/data/*", direction="in")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="empty chunk"):
        Bridge("b", BridgeSpec(**MQTT), MemoryFabric(), "rap//x", direction="out")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="wildcard"):
        Bridge(
            "b",
            BridgeSpec(**{**MQTT, "address": "a/#"}),  # type: ignore[arg-type]
            MemoryFabric(),
            KEY,
            direction="out",
            message=Reading,
        )


def test_the_metrics_are_exported_with_labels() -> None:
    b = Bridge("b1", BridgeSpec(**MQTT), MemoryFabric(), KEY, direction="out", message=Reading)  # type: ignore[arg-type]
    b.stats.sent = 5
    b.stats.rejections.reject("k", "invalid test.Reading/1 JSON: bad")
    registry = CollectorRegistry(auto_describe=False)
    registry.register(BridgeCollector([b], system="s"))
    labels = {
        "system": "s",
        "compute_node": "",
        "bridge": "b1",
        "protocol": "mqtt",
        "direction": "out",
    }
    assert registry.get_sample_value("rap_bridge_sent_total", labels) == 5
    assert registry.get_sample_value("rap_bridge_connected", labels) == 0
    assert (
        registry.get_sample_value(
            "rap_bridge_rejected_total",
            {**labels, "reason": "invalid test.Reading/N JSON: bad"},
        )
        == 1
    )
    names = {m.name for m in registry.collect()}
    assert {n.removesuffix("_total") for n in METRICS} == names


@pytest.mark.parametrize("field", ["ca", "cert"])
def test_a_dds_bridge_with_tls_files_says_so(field: str) -> None:
    extra = {"cert": "c.pem", "key": "k.pem"} if field == "cert" else {"ca": "ca.pem"}
    with pytest.raises(ValueError, match="a dds bridge takes no credentials or TLS"):
        BridgeSpec(protocol="dds", url="dds://0", address="/scan", format="cdr", **extra)
    kafka = {"protocol": "kafka", "url": "kafka://h:9092", "address": "t", **extra}
    with pytest.raises(ValueError, match="a kafka bridge takes no credentials or TLS"):
        BridgeSpec(**kafka)  # type: ignore[arg-type]
