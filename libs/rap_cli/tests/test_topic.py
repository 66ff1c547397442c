"""``rap topic list|echo|hz``: key expressions, decoding by the envelope's type (and
refusing what is not an envelope, without stopping), rates; and the commands themselves
as processes, Zenoh clients of a session on loopback that publishes."""

from __future__ import annotations

import json
import math
import shlex
import shutil
import subprocess
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from rap_cli.topic_cli import RateWindow, decode_sample, hz_report, key_expr, render
from rap_schemas import LaserScan, Pose2D, keys, pack_ranges
from rap_sdk import Sealer, ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port
from rap_sdk.testing import stop_process

pytestmark = pytest.mark.anyio

SYSTEM = "tp"
RAP = str(Path(sys.executable).with_name("rap"))
sealer = Sealer("sim")
POSE = keys.data(SYSTEM, "tb1/pose")


def test_key_expressions_are_relative_to_the_system_or_full() -> None:
    assert key_expr("demo", "data/tb1/scan") == keys.data("demo", "tb1/scan")
    assert key_expr("demo", "event/**") == keys.pattern("demo", keys.Kind.EVENT)
    assert key_expr("demo", "event") == keys.pattern("demo", keys.Kind.EVENT)
    assert key_expr("demo", "**") == keys.system_pattern("demo")
    assert key_expr("demo", "trace/*") == keys.pattern("demo", keys.Kind.TRACE, "*")
    assert key_expr("demo", "rap/other/data/x") == keys.data("other", "x")
    for bad, why in [
        ("scan", "begin with a kind"),
        ("data/tb*/scan", "chunk"),
        ("rap/demo//x", "empty chunk"),
        ("", "empty key expression"),
    ]:
        with pytest.raises(ValueError, match=why):
            key_expr("demo", bad)


def _scan() -> LaserScan:
    return LaserScan(
        stamp=5,
        frame_id="tb1/base_link",
        angle_min=-math.pi,
        angle_increment=math.pi / 2,
        range_min=0.1,
        range_max=10.0,
        ranges=pack_ranges([1.0, 2.0, math.inf, 4.0]),
    )


def test_a_known_type_is_decoded_by_its_class_with_the_envelope() -> None:
    key = keys.data(SYSTEM, "tb1/scan")
    payload, env = sealer.seal_message(key, _scan(), cycle=b"\x01" * 16, cause=b"\x02" * 16)
    d = decode_sample(key, payload)
    assert d.rejected is None
    assert d.known
    assert d.body["frame_id"] == "tb1/base_link"
    assert d.body["ranges"] == pack_ranges([1.0, 2.0, math.inf, 4.0])
    out = d.to_json()
    assert (out["type"], out["source"], out["seq"]) == ("rap.LaserScan/2", "sim", env.seq)
    assert (out["uid"], out["cycle"], out["cause"]) == (env.uid.hex(), "01" * 16, "02" * 16)
    line = msgspec.json.encode(out)  # JSON-encodable as it is
    assert json.loads(line)["body"]["range_max"] == 10.0
    text = render(d)
    assert "rap.LaserScan/2" in text
    assert "source: sim" in text
    assert f"cycle: {'01' * 16}  cause: {'02' * 16}" in text
    assert "ranges: 0000803f" in text  # 16 bytes: shown as hex


def test_an_unknown_type_is_shown_as_plain_data() -> None:
    body = msgspec.msgpack.encode({"speed": 1.5, "tags": ["a", "b"], 7: b"\x00\xff"})
    payload, _ = sealer.seal(POSE, "acme.Weather/3", body)
    d = decode_sample(POSE, payload)
    assert d.rejected is None
    assert not d.known
    assert d.body == {"speed": 1.5, "tags": ["a", "b"], 7: b"\x00\xff"}
    out = json.loads(msgspec.json.encode(d.to_json()))
    assert out["body"] == {"speed": 1.5, "tags": ["a", "b"], "7": "AP8="}  # bytes: base64
    assert "unknown type" in render(d)
    assert "speed: 1.5" in render(d)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"\xc1\xc1 garbage", "not an envelope: undecodable"),
        (msgspec.msgpack.encode({"uid": 3}), "not an envelope: Expected `bytes`"),
        (b"", "not an envelope"),
        (b"\x91" * 100_000, "not an envelope"),  # nested arrays, deeper than any guard
    ],
)
def test_a_sample_that_is_not_an_envelope_is_rejected_with_the_reason(
    payload: bytes, reason: str
) -> None:
    d = decode_sample(POSE, payload)
    assert d.rejected is not None
    assert reason in d.rejected
    assert json.loads(msgspec.json.encode(d.to_json()))["rejected"] == d.rejected
    assert "REJECTED" in render(d)


def test_a_body_that_does_not_fit_its_type_and_an_oversized_sample_are_rejected() -> None:
    payload, _ = sealer.seal(POSE, Pose2D.TYPE, msgspec.msgpack.encode({"x": "left", "y": 0}))
    d = decode_sample(POSE, payload)
    assert d.rejected is not None
    assert "$.x" in d.rejected
    assert "[type rap.Pose2D/1 from sim]" in render(d)
    big = decode_sample(POSE, b"\x00" * 100, max_bytes=50)
    assert big.rejected == "100 bytes, over the limit of 50"


def test_rates_over_the_window() -> None:
    w = RateWindow(window=4)
    for t in (0.0, 0.1, 0.3, 0.4, 0.6, 0.7):  # the window keeps the last 4 intervals
        w.add(t)
    st = w.stats()
    assert st["n"] == 4
    gaps = [0.2, 0.1, 0.2, 0.1]
    assert st["mean"] == pytest.approx(0.15)
    assert st["rate_hz"] == pytest.approx(1 / 0.15)
    assert st["min"] == pytest.approx(0.1)
    assert st["max"] == pytest.approx(0.2)
    assert st["std"] == pytest.approx(math.sqrt(sum((g - 0.15) ** 2 for g in gaps) / 4))
    assert w.count == 6
    one = RateWindow()
    one.add(1.0)
    assert one.stats()["rate_hz"] is None
    lines = hz_report({"k": w, "j": one}, as_json=False)
    assert lines[0].startswith("j: - Hz")
    assert lines[1].startswith("k: 6.67 Hz  mean 150.0 ms  min 100.0 ms  max 200.0 ms")
    assert json.loads(hz_report({"k": w}, as_json=True)[0])["n"] == 4


# -- the commands, as processes ----------------------------------------------------------


async def _with_rap(
    argv: list[str],
    feed: Callable[[ZenohFabric, Any], Awaitable[None]],
    *,
    wait_key: str,
) -> tuple[int, str, str]:
    """Run ``rap ...`` as a client of a listening session; once its subscription has
    reached the session, ``feed(fabric, proc)`` publishes. Returns the exit code,
    standard output and standard error."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    argv = [RAP, *argv, "--connect", ep, "--system", SYSTEM]
    out: list[bytes] = []
    err: list[bytes] = []
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        proc = await anyio.open_process(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:

            async def drain(stream: Any, into: list[bytes]) -> None:
                async for chunk in stream:  # kept as it comes: a timeout still shows it
                    into.append(chunk)  # noqa: PERF401

            async with anyio.create_task_group() as tg:
                tg.start_soon(drain, proc.stdout, out)
                tg.start_soon(drain, proc.stderr, err)
                await fabric.wait_matched(wait_key, timeout=15)
                with anyio.fail_after(20):
                    await feed(fabric, proc)
                    await proc.wait()
        finally:
            await stop_process(proc)
    assert proc.returncode is not None
    return proc.returncode, b"".join(out).decode(), b"".join(err).decode()


@pytest.mark.zenoh
async def test_rap_topic_echo_decodes_and_survives_garbage() -> None:
    good, env = sealer.seal_message(POSE, Pose2D(x=1.0, y=2.0, theta=0.5))
    unknown, _ = sealer.seal(POSE, "acme.Weather/3", msgspec.msgpack.encode({"wind": 3}))
    after, _ = sealer.seal_message(POSE, Pose2D(x=3.0, y=4.0, theta=0.0))

    async def feed(fabric: ZenohFabric, proc: Any) -> None:
        for payload in (good, b"\xc1 not an envelope", unknown, after):
            await fabric.publish(POSE, payload)

    code, out, err = await _with_rap(
        ["topic", "echo", "data/**", "--json", "-n", "4"], feed, wait_key=POSE
    )
    assert code == 0, err
    assert "Traceback" not in err
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 4, out
    assert lines[0]["body"] == {"x": 1.0, "y": 2.0, "theta": 0.5}
    assert (lines[0]["type"], lines[0]["uid"], lines[0]["known_type"]) == (
        Pose2D.TYPE,
        env.uid.hex(),
        True,
    )
    assert lines[1]["key"] == POSE
    assert "not an envelope" in lines[1]["rejected"]
    assert lines[2]["body"] == {"wind": 3}
    assert lines[2]["known_type"] is False
    assert lines[3]["body"]["x"] == 3.0  # it carried on after the garbage


@pytest.mark.zenoh
async def test_rap_topic_echo_pretty() -> None:
    async def feed(fabric: ZenohFabric, proc: Any) -> None:
        await fabric.publish(POSE, b"\x00\x01")
        await fabric.publish(POSE, sealer.seal_message(POSE, Pose2D(x=1.0, y=2.0, theta=0.5))[0])

    code, out, err = await _with_rap(
        ["topic", "echo", "data/tb1/pose", "-n", "2"], feed, wait_key=POSE
    )
    assert code == 0, err
    assert f"{POSE}: REJECTED (2 bytes): not an envelope" in out
    assert f"{POSE}  {Pose2D.TYPE}" in out
    assert "    theta: 0.5" in out
    assert "1 of 2 sample(s) rejected" in err


@pytest.mark.zenoh
async def test_rap_topic_echo_ends_quietly_when_its_reader_goes() -> None:
    """``rap topic echo ... | head -n 3``: once head has gone, the next sample ends it
    with exit 0 and no traceback."""
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("no bash to run a pipeline with pipefail")
    ep = f"tcp/127.0.0.1:{free_port()}"
    echo = shlex.join([RAP, "topic", "echo", "data/**", "--connect", ep, "--system", SYSTEM])
    pipeline = f"set -o pipefail; {echo} | head -n 3 > /dev/null"
    sample = sealer.seal_message(POSE, Pose2D(x=1.0, y=2.0, theta=0.5))[0]
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        proc = await anyio.open_process([bash, "-c", pipeline], stderr=subprocess.PIPE)
        try:
            assert proc.stderr is not None
            await fabric.wait_matched(POSE, timeout=15)
            with anyio.fail_after(15):
                while proc.returncode is None:
                    await fabric.publish(POSE, sample)
                    await anyio.sleep(0.05)
            err = b"".join([chunk async for chunk in proc.stderr]).decode()
        finally:
            await stop_process(proc)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert "BrokenPipe" not in err


async def _publish_until_done(fabric: ZenohFabric, proc: Any) -> None:
    clock = keys.data(SYSTEM, "clock")
    token = fabric.declare_token(keys.alive(SYSTEM, "probe"))
    try:
        while proc.returncode is None:
            await fabric.publish(POSE, sealer.seal_message(POSE, Pose2D(x=0, y=0, theta=0))[0])
            await fabric.publish(clock, b"raw bytes")
            await anyio.sleep(0.05)
    finally:
        token.undeclare()


@pytest.mark.zenoh
async def test_rap_topic_list_shows_keys_kinds_types_and_alive_tokens() -> None:
    code, out, err = await _with_rap(
        ["topic", "list", "--for", "1.5", "--json"],
        _publish_until_done,
        wait_key=POSE,
    )
    assert code == 0, err
    rows = {r["key"]: r for r in json.loads(out)}
    pose = rows[POSE]
    assert (pose["kind"], pose["type"]) == ("data", Pose2D.TYPE)
    assert pose["count"] >= 2
    assert pose["rate_hz"] > 0
    clock = rows[keys.data(SYSTEM, "clock")]
    assert clock["type"] is None
    assert clock["not_envelopes"] == clock["count"] > 0
    alive = rows[keys.alive(SYSTEM, "probe")]
    assert (alive["kind"], alive["count"]) == ("alive", 0)


@pytest.mark.zenoh
async def test_rap_topic_hz_reports_each_key() -> None:
    code, out, err = await _with_rap(
        ["topic", "hz", "data/**", "--for", "2.5", "--json"],
        _publish_until_done,
        wait_key=POSE,
    )
    assert code == 0, err
    reports = [json.loads(line) for line in out.splitlines()]
    assert {r["key"] for r in reports} == {POSE, keys.data(SYSTEM, "clock")}, out
    last = [r for r in reports if r["key"] == POSE][-1]
    assert last["n"] >= 2
    assert last["count"] == last["n"] + 1
    assert last["min"] <= last["mean"] <= last["max"]
    assert last["rate_hz"] == pytest.approx(1 / last["mean"])


async def test_bad_usage_is_one_line_with_exit_2(tmp_path: Path) -> None:
    for argv, says in [
        (["topic", "echo", "scan", "--system", "d", "--connect", "tcp/127.0.0.1:1"], "kind"),
        (["topic", "echo", "data/x"], "which system?"),
        (["topic", "hz", "data/x", "-s", "d", "-c", "tcp/127.0.0.1:1", "--window", "0"], "window"),
        (["record", "--system", "d", "-c", "tcp/127.0.0.1:1"], "--output"),
        (["replay", str(tmp_path / "none.mcap"), "-s", "d", "-c", "tcp/127.0.0.1:1"], "no such"),
        (["replay", str(tmp_path), "--speed", "-1", "-s", "d"], "--speed"),
    ]:
        res = await anyio.run_process([RAP, *argv], check=False, cwd=tmp_path)
        err = res.stderr.decode()
        assert res.returncode == 2, (argv, err)
        assert err.startswith("rap: error:"), (argv, err)
        assert says in err, (argv, err)
        assert len(err.strip().splitlines()) == 1, err
