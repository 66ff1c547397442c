"""No payload kills the checker: every decode boundary rejects bad input with a reason,
counts it by reason, and the checker goes on (and still answers good input).

The fabric side runs on the in-memory fabric (deterministic); MQTT through a mosquitto
of the test's own; the command line as a user runs it. Spec and trace files that are
not text are in test_cli.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import aiomqtt
import anyio
import msgspec
import pytest
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream
from hypothesis import given, settings
from hypothesis import strategies as st
from rap_schemas import (
    Empty,
    Rejection,
    Stage,
    StageTrace,
    TrustSpecStatus,
    TrustSpecUpdate,
    Verdict,
    keys,
)
from rap_schemas.limits import MAX_DEPTH, MAX_SAMPLE_BYTES
from rap_sdk import MemoryBus, MemoryFabric, Sealer
from rap_sdk.envelope import typed_decoder
from trust_checker.config import FabricConfig, FabricInput, MqttConfig, ServiceConfig
from trust_checker.errors import TextFileError
from trust_checker.io.codec import MAX_PAYLOAD, CodecError, decode_json, decode_payload
from trust_checker.io.specs import load_text
from trust_checker.lang import load_spec
from trust_checker.service import open_service

from services.trust_checker.tests.io_support import RecordingSink, mosquitto

SYS = "hard"
NODE = "trust_hard"
CYCLE = bytes(range(16))
SPEC = """\
in stage: Str
in blob
in ev_go
out n: Int
n = default(n[1], 0) + 1
"""
_open_rejection = typed_decoder(Rejection)
_open_status = typed_decoder(TrustSpecStatus)


def deep_msgpack(depth: int) -> bytes:
    """``[[[...1...]]]``, ``depth`` arrays deep, as msgpack."""
    return b"\x91" * depth + b"\x01"


def deep_json(depth: int) -> bytes:
    return b"[" * depth + b"1" + b"]" * depth


def with_field(message: msgspec.Struct, name: str, raw: bytes) -> bytes:
    """``message`` as msgpack with one more field ``name`` whose value is ``raw``
    (already encoded): a field the schema does not know, so the decoder skips it."""
    marker = b"\x00MARKER\x00"
    doc = {**msgspec.to_builtins(message, builtin_types=(bytes,)), name: marker}
    encoded = msgspec.msgpack.encode(doc)
    placeholder = msgspec.msgpack.encode(marker)
    assert encoded.count(placeholder) == 1
    return encoded.replace(placeholder, raw)


def record(node: str = "analysis") -> StageTrace:
    return StageTrace(
        node=node,
        handler="detect",
        phase="start",
        trigger=b"\x01" * 16,
        trigger_key=keys.event(SYS, "new-data"),
        cycle=CYCLE,
        ts=1,
        stage=Stage.ANALYSE,
    )


# -- the fabric -----------------------------------------------------------------------


@pytest.mark.anyio
async def test_no_sample_on_the_fabric_kills_the_checker() -> None:
    bus = MemoryBus()
    sealer = Sealer("robot")
    trace_key = keys.trace(SYS, "analysis")
    blob_key = keys.data(SYS, "blob")
    verdict_key = keys.event(SYS, "verdict")
    go_key = keys.event(SYS, "go")
    config = ServiceConfig(
        node=NODE,
        fabric=FabricConfig(system=SYS, inputs={"blob": FabricInput(blob_key)}),
    )
    sink = RecordingSink()
    records: list[Rejection] = []

    async def send_raw(key: str, type_: str, body: bytes) -> None:
        payload, _ = sealer.seal(key, type_, body)
        await robot.publish(key, payload)

    changed = anyio.Event()

    async def collect(sub: Any) -> None:
        nonlocal changed
        async for sample in sub:
            records.append(_open_rejection(sample.payload).body)
            changed.set()

    async with (
        MemoryFabric(bus=bus) as robot,
        MemoryFabric(bus=bus) as fab,
        open_service(config, load_text(SPEC), fabric=fab, sinks=[sink]) as service,
        anyio.create_task_group() as tg,
    ):
        transport = service.fabric
        assert transport is not None
        log_sub = robot.subscribe(keys.log(SYS, NODE))
        tg.start_soon(collect, log_sub)
        bad_utf8 = msgspec.msgpack.encode(record()).replace(b"analysis", b"analys\xff\xfe")
        junk: list[tuple[str, str, bytes]] = [
            # trace records: deep in a field the decoder skips, past its nesting guard
            (trace_key, StageTrace.TYPE, with_field(record(), "junk", deep_msgpack(100_000))),
            (trace_key, StageTrace.TYPE, bad_utf8),  # a string that is not UTF-8
            (trace_key, StageTrace.TYPE, deep_msgpack(900)),  # not a record at all
            # an event whose body is a rap.Verdict nested past the guard
            (verdict_key, Verdict.TYPE, with_field(Empty(), "plan", deep_msgpack(5000))),
            # explicit inputs, decoded without a type: depth-checked before anything else
            (blob_key, "t.Blob/1", deep_msgpack(MAX_DEPTH + 1)),
            (blob_key, "t.Blob/1", deep_msgpack(900)),  # deeper than Python would recurse
            (blob_key, "t.Blob/1", deep_msgpack(100_000)),
            (blob_key, "t.Blob/1", b"\x81\x91\x01\x01"),  # {[1]: 1}: a key that is a list
            (blob_key, "t.Blob/1", b"\xa2\xff\xfe"),  # a str that is not UTF-8
            (blob_key, "t.Blob/1", b"\x01" * (MAX_SAMPLE_BYTES + 1)),  # too large
        ]
        for key, type_, body in junk:
            await send_raw(key, type_, body)
        await robot.publish(trace_key, b"\x93\x01")  # not an envelope
        # and the checker still answers good input
        payload, _ = sealer.seal_message(go_key, Empty())
        await robot.publish(go_key, payload)
        await send_raw(blob_key, "t.Blob/1", msgspec.msgpack.encode({"a": [1, 2], 3: b"\xab"}))
        payload, _ = sealer.seal_message(trace_key, record(), cycle=CYCLE)
        await robot.publish(trace_key, payload)
        with anyio.fail_after(10):
            await sink.wait_for(3)
            await service.session.wait_idle()
            while len(records) < 3:
                changed = anyio.Event()
                await changed.wait()
        log_sub.close()
        tg.cancel_scope.cancel()
    assert [(o.stream, o.tick, o.value) for o in sink.outs] == [("n", i, i + 1) for i in range(3)]
    assert service.session.stats.ticks == 3
    rejections = transport.stats.rejections
    assert rejections.total == len(junk) + 1
    assert rejections.by_reason == {  # counted by reason (its kind: digits as N)
        "undecodable envelope": 3,  # past the decoder's nesting guard
        "invalid envelope: Expected `object`, got `array`": 1,
        "invalid rap.StageTrace/N body: a string is not valid UTF-N": 1,
        "invalid rap.StageTrace/N body: Expected `object`, got `array`": 1,
        "t.Blob/N body nests lists or maps more than N levels deep; flatten it": 2,
        "t.Blob/N: a map key is a tuple - use string": 1,
        "t.Blob/N body: a string is not valid UTF-N": 1,
        "sample of N bytes is over the limit of N - send smaller messages": 1,
    }
    # rate-limited reports: one rap.Rejection record per key
    assert {r.key for r in records} == {trace_key, verdict_key, blob_key}
    assert all(r.node == NODE for r in records)


@pytest.mark.anyio
async def test_garbage_on_the_swap_queryable_is_refused_and_counted() -> None:
    bus = MemoryBus()
    sealer = Sealer("operator")
    swap_key = keys.admin(SYS, NODE, "swap")
    config = ServiceConfig(node=NODE, fabric=FabricConfig(system=SYS))
    async with (
        MemoryFabric(bus=bus) as peer,
        MemoryFabric(bus=bus) as fab,
        open_service(config, load_text(SPEC), fabric=fab) as service,
    ):
        transport = service.fabric
        assert transport is not None
        deep, _ = sealer.seal(
            swap_key, TrustSpecUpdate.TYPE, with_field(Empty(), "x", deep_msgpack(100_000))
        )
        wrong, _ = sealer.seal_message(swap_key, Empty())
        for junk in (b"junk", deep_msgpack(100_000), deep, wrong, b"\x00" * (MAX_SAMPLE_BYTES + 1)):
            (reply,) = await peer.query(swap_key, junk, timeout=5.0)
            assert not reply.ok
            assert b"swap request" in reply.payload
            assert b" - send a sealed rap.TrustSpecUpdate/1" in reply.payload
        # specs that tripped the lexer (superscript digits are digits to str.isdigit, not
        # to int()) and a tuple field past int()'s digit limit: refused, the checker lives
        for text in ("out b: Int\nb = \u00b2\n", "\u00b9", "out b: Int\nb = t." + "9" * 5000):
            odd, _ = sealer.seal_message(swap_key, TrustSpecUpdate(spec=text))
            (reply,) = await peer.query(swap_key, odd, timeout=5.0)
            assert not _open_status(reply.payload).body.ok
        good, _ = sealer.seal_message(swap_key, TrustSpecUpdate(spec="in ev_go\nout m\nm = 1\n"))
        (reply,) = await peer.query(swap_key, good, timeout=5.0)
        assert _open_status(reply.payload).body.ok
    assert transport.stats.rejections.total == 5
    assert transport.stats.swap_queries == 9
    assert service.session.stats.swaps == 1
    assert service.runner.outputs == ("m",)


# -- MQTT -----------------------------------------------------------------------------


@pytest.mark.anyio
async def test_no_payload_on_mqtt_kills_the_checker(tmp_path: Path) -> None:
    spec = "in x\nout n: Int\nn = default(n[1], 0) + 1\n"
    async with mosquitto(tmp_path) as broker:
        config = ServiceConfig(mqtt=MqttConfig(port=broker.port, timeout=5.0))
        async with (
            open_service(config, load_text(spec)) as service,
            aiomqtt.Client("127.0.0.1", broker.port, timeout=5.0) as client,
        ):
            transport = service.mqtt
            assert transport is not None
            await client.subscribe("n")
            await client.subscribe("trust/status")
            junk = [
                deep_json(500),  # about 1 KB
                deep_json(200_000),  # past the decoder's nesting guard
                b'{"value": ' + deep_json(MAX_DEPTH) + b"}",
                b'{"List": [' * 40 + b"1" + b"]}" * 40,
                b'"\xff"',
                b" " * (MAX_PAYLOAD + 1),
            ]
            for payload in junk:
                await client.publish("x", payload)
            update = b'{"spec": "in x", "junk": ' + deep_json(200_000) + b"}"
            await client.publish("trust/spec", update)
            await client.publish("trust/spec", b"\xff\xfe")
            await client.publish("x", b"[1, [2]]")  # a good input, after all of that
            got: list[tuple[str, Any]] = []
            with anyio.fail_after(10):
                async for message in client.messages:
                    got.append((message.topic.value, json.loads(bytes(message.payload))))
                    if len(got) == 3:
                        break
    assert got[-1] == ("n", {"value": 1})
    statuses = [p for t, p in got if t == "trust/status"]
    assert [s["ok"] for s in statuses] == [False, False]
    assert "nested too deeply" in statuses[0]["problems"][0]
    assert service.session.stats.ticks == 1
    rejections = transport.stats.rejections
    assert rejections.total == len(junk) + 2
    assert rejections.by_reason == {
        "the value nests lists or maps more than N levels deep; flatten it": 3,
        "payload: nested too deeply": 1,
        "payload: a string is not valid UTF-N": 1,
        "payload of N bytes is larger than the N allowed - send a smaller value": 1,
        "spec update on 'trust/spec' refused: spec update: nested too deeply": 1,
        "spec update on 'trust/spec' refused: spec update: undecodable: JSON is malformed: "
        "invalid character": 1,
    }


async def _read_until(stream: TextReceiveStream, text: str, seen: list[str]) -> None:
    async for chunk in stream:
        seen.append(chunk)
        if text in "".join(seen):
            return
    raise AssertionError(f"{text!r} never came:\n{''.join(seen)}")


@pytest.mark.anyio
async def test_deep_json_does_not_kill_python_m_trust_checker_mqtt(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text("in x\nout n: Int\nn = default(n[1], 0) + 1\n")
    async with mosquitto(tmp_path) as broker:
        proc: Process = await anyio.open_process(
            [
                *(sys.executable, "-m", "trust_checker", str(tmp_path / "s.dsrv")),
                *("--mqtt", f"127.0.0.1:{broker.port}"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        async with proc, aiomqtt.Client("127.0.0.1", broker.port, timeout=5) as client:
            assert proc.stdout is not None
            assert proc.stderr is not None
            err: list[str] = []
            out: list[str] = []
            try:
                with anyio.fail_after(20):
                    await _read_until(TextReceiveStream(proc.stderr), "ready:", err)
                    await client.subscribe("n")
                    await client.publish("x", deep_json(500))
                    await client.publish("x", deep_json(200_000))
                    await client.publish("trust/spec", b'{"spec": ' + deep_json(200_000) + b"}")
                    await client.publish("x", "7")
                    async for message in client.messages:
                        assert json.loads(bytes(message.payload)) == {"value": 1}
                        break
                    await _read_until(TextReceiveStream(proc.stdout), "n[0] = Int(1)", out)
                    await _read_until(TextReceiveStream(proc.stderr), "rejected", err)
            finally:
                proc.terminate()
                with anyio.fail_after(10):
                    code = await proc.wait()
        assert code == 0, "".join(err)
        assert proc.returncode == 0


# -- files and the codec ---------------------------------------------------------------


def test_a_binary_spec_file_is_refused_with_its_place(tmp_path: Path) -> None:
    path = tmp_path / "bin.dsrv"
    path.write_bytes(b"in x\nout y\ny = x \x80\n")
    with pytest.raises(TextFileError) as err:
        load_spec(path)
    assert str(err.value) == (
        f"{path}:3:7: the spec is not UTF-8 text (byte 0x80) - is it a binary file? give "
        "the spec in text form"
    )
    assert (err.value.line, err.value.column) == (3, 7)


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
    lambda inner: st.lists(inner) | st.dictionaries(st.text(), inner),
    max_leaves=30,
)


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.binary(max_size=300),
        _json.map(lambda v: json.dumps(v).encode()),
        st.tuples(
            st.sampled_from(["[", '{"a":', '{"List": [', '{"value": ']), st.integers(0, 3000)
        ).map(lambda t: (t[0] * t[1]).encode()),
        st.integers(0, 3000).map(deep_json),
    )
)
def test_the_codec_rejects_any_junk_with_a_reason(payload: bytes) -> None:
    """A stream value, or CodecError with a reason: never anything else."""
    reason = "taken"
    try:
        decode_payload(payload)
    except CodecError as exc:
        reason = exc.reason
    assert reason


@settings(max_examples=100, deadline=None)
@given(st.integers(MAX_DEPTH + 1, 50_000))
def test_decode_json_checks_depth_before_converting(depth: int) -> None:
    doc: Any = 1
    for _ in range(depth):
        doc = [doc]
    with pytest.raises(CodecError, match="more than 32 levels deep"):
        decode_json(doc)


@pytest.mark.anyio
async def test_a_refused_spec_with_a_huge_line_makes_a_short_status_and_ticks_go_on() -> None:
    """A spec of the largest size allowed, one line deep in parentheses: refused, and what
    comes back (and goes to the log) quotes an excerpt of the line, not the line."""
    from trust_checker.errors import EXCERPT
    from trust_checker.io.specs import MAX_SPEC_CHARS

    bus = MemoryBus()
    sealer = Sealer("operator")
    swap_key = keys.admin(SYS, NODE, "swap")
    config = ServiceConfig(node=NODE, fabric=FabricConfig(system=SYS))
    line = "out b: Int\nb = " + "(" * (MAX_SPEC_CHARS - 40)
    async with (
        MemoryFabric(bus=bus) as peer,
        MemoryFabric(bus=bus) as fab,
        open_service(config, load_text(SPEC), fabric=fab) as service,
    ):
        update, _ = sealer.seal_message(swap_key, TrustSpecUpdate(spec=line))
        (reply,) = await peer.query(swap_key, update, timeout=10.0)
        status = _open_status(reply.payload).body
        assert not status.ok
        assert status.problems
        assert all(len(p) < 2 * EXCERPT + 400 for p in status.problems)
        assert service.session.stats.swaps_rejected == 1


def test_a_problem_quotes_an_excerpt_of_a_long_line_with_the_caret_in_place() -> None:
    from trust_checker.errors import EXCERPT, Problem

    text = "x" * 5000 + "@" + "y" * 5000
    shown = str(Problem("spec", 2, 5001, "unexpected character '@'", text)).splitlines()
    assert len(shown[1]) <= 4 + EXCERPT + 6
    caret = shown[2].index("^")
    assert shown[1][caret] == "@"
    short = str(Problem("spec", 1, 3, "bad", "ab@cd")).splitlines()
    assert short[1:] == ["    ab@cd", "      ^"]
