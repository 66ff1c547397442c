"""``rap view``: a running loop streamed to Rerun, read back with Rerun's own reader.

The live test runs the lidar-occlusion loop in this process (the simulator in lockstep,
the five MAPLE-K nodes, knowledge) on a real Zenoh session, and ``rap view`` as a child
process that joins it as a Zenoh client, writing with ``--save`` or streaming with
``--connect-viewer`` to Rerun's own server (``rerun --save``, no window); a few malformed
samples go out beside the real ones. After Ctrl-C (SIGINT) the ``.rrd`` file is read
back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41; earlier versions had
``rerun.dataframe``). ``tests/test_view_lidar.py`` (slow) does the same under ``rap up``.

The other tests drive the decoding (``Translator``) with real sealed envelopes, the
Rerun thread's bounded queue (``Writer``) and the command's usage errors.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import warnings
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

import anyio
import msgspec
import numpy as np
import pytest
from rap_cli.view_cli import Log, Text, Translator, Writer, cycle_keys
from rap_schemas import (
    LaserScan,
    LidarMask,
    Odometry,
    Pose2D,
    Twist,
    keys,
    load_plan,
    pack_flags,
    pack_ranges,
)
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.envelope import Sealer
from rap_sdk.fabric import free_port
from rap_sdk.testing import OutputLines, stop_process

REPO = Path(__file__).resolve().parents[3]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
RAP = str(Path(sys.executable).with_name("rap"))

rerun = pytest.importorskip("rerun")
RrdReader = pytest.importorskip("rerun.chunk").RrdReader


@pytest.fixture(autouse=True)
def _no_analytics(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RERUN_ANALYTICS", "0")


# -- reading an .rrd back ----------------------------------------------------------------


def _rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every row of every entity in the recording, as {column: value} (timestamps left
    out; component values are their batches, lists)."""
    out: dict[str, list[dict[str, Any]]] = {}
    with warnings.catch_warnings():
        # what `rerun --save` writes has no footer (it streams): read whole, as Rerun says
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        chunks = RrdReader(path).stream().to_chunks()
    for chunk in chunks:
        rb = chunk.to_record_batch()
        cols = {
            name: rb.column(i).to_pylist()
            for i, name in enumerate(rb.schema.names)
            if name not in ("time", "log_time") and not name.startswith("rerun.")
        }
        rows = out.setdefault(chunk.entity_path, [])
        for r in range(rb.num_rows):
            rows.append({name: values[r] for name, values in cols.items()})
    return out


def _one(value: Any) -> Any:
    """A component batch of one value: the value."""
    assert isinstance(value, list), value
    assert len(value) == 1, value
    return value[0]


# -- the live loop ------------------------------------------------------------------------


def _bad_scan_body() -> bytes:
    """A LaserScan body whose ranges hold a NaN: the wire type refuses it."""
    return msgspec.msgpack.encode(
        {
            "stamp": 0,
            "frame_id": "base_link",
            "angle_min": 0.0,
            "angle_increment": 0.1,
            "range_min": 0.1,
            "range_max": 10.0,
            "ranges": pack_ranges([1.0, math.nan]),
        }
    )


def _rerun() -> str:
    exe = Path(sys.executable).with_name("rerun")
    assert exe.exists(), f"{exe}: rerun-sdk's viewer program is not installed next to Python"
    return str(exe)


@pytest.mark.anyio
@pytest.mark.zenoh
@pytest.mark.timeout(90)
@pytest.mark.parametrize("sink", ["save", "connect-viewer"])
async def test_view_shows_a_running_loop_linked_by_cycle(tmp_path: Path, sink: str) -> None:
    """``--save FILE``, or ``--connect-viewer URL`` of a Rerun server that saves what it
    receives (``rerun --save``: the viewer's own gRPC server, without a window)."""
    from lidar_occlusion.scenario import run_in_process
    from sim_world.world import default_world_path, load_world

    out = tmp_path / "view.rrd"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    world = load_world(default_world_path())
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    argv = [RAP, "view", "-m", str(MODEL), "-c", endpoint]
    async with AsyncExitStack() as stack:
        if sink == "save":
            argv += ["--save", str(out)]
        else:
            port = free_port()
            server = await anyio.open_process(
                [_rerun(), "--bind", "127.0.0.1", "--port", str(port), "--save", str(out)],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                env=env,
            )
            stack.push_async_callback(stop_process, server)
            served = OutputLines(server)
            tg0 = await stack.enter_async_context(anyio.create_task_group())
            tg0.start_soon(served.pump)
            await served.line("Listening for gRPC connections")
            argv += ["--connect-viewer", f"rerun+http://127.0.0.1:{port}/proxy"]
        fabric = await stack.enter_async_context(ZenohFabric(ZenohConfig(listen=[endpoint])))
        proc = await anyio.open_process(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env
        )
        try:
            async with anyio.create_task_group() as tg:
                lines = OutputLines(proc)
                tg.start_soon(lines.pump)
                await lines.line("viewing system demo")
                # rap view's subscriptions reached this session: what is published now
                # goes to it (every kind: it declares them all before saying so)
                for key in (
                    keys.data(SYSTEM, "tb1/scan"),
                    keys.event(SYSTEM, "anomaly"),
                    keys.trace(SYSTEM, "analysis"),
                    keys.log(SYSTEM, "x"),
                ):
                    await fabric.wait_matched(key, timeout=10)
                # bad samples among the real ones: none may stop the view
                sealer = Sealer("prankster")
                await fabric.publish(keys.data(SYSTEM, "junk"), b"\xc1 not msgpack")
                bad, _ = sealer.seal(
                    keys.data(SYSTEM, "tb9/scan"), LaserScan.TYPE, _bad_scan_body()
                )
                await fabric.publish(keys.data(SYSTEM, "tb9/scan"), bad)
                summary = await run_in_process(world, fabric=fabric, duration=12.0)
                assert summary["anomalies"] >= 1, summary
                assert summary["plans_executed"] >= 1, summary
                # the last sample: on Ctrl-C rap view takes what is still in flight,
                # so this one is in the recording, and everything before it
                end = keys.event(SYSTEM, "view-test-end")
                await fabric.publish(end, sealer.seal_message(end, None)[0])
                proc.send_signal(signal.SIGINT)
                with anyio.fail_after(30):
                    code = await proc.wait()
                tg.cancel_scope.cancel()
        finally:
            await stop_process(proc)
        if sink == "connect-viewer":
            server.send_signal(signal.SIGINT)  # the server closes its file
            with anyio.fail_after(30):
                await server.wait()
            tg0.cancel_scope.cancel()
    text = "\n".join(lines.lines)
    assert code == 0, text
    assert "2 rejected" in text, text
    assert "not msgpack" in text or "undecodable" in text, text
    assert "ranges[1]" in text, text  # the NaN scan's reason names the bad beam
    if sink == "save":
        assert f"wrote {out}" in text, text

    rows = _rows(out)
    assert rows["/maplek/events/view-test-end"]  # nothing lost at the end
    # the world of the model's simulator, static
    assert "/world/room" in rows, sorted(rows)
    assert "/world/obstacles/circles" in rows, sorted(rows)
    # scans in the world frame, the robot's pose and path
    scans = rows["/world/tb1/scan"]
    assert len(scans) >= 50, len(scans)  # 12 s of sim time at 5 Hz: 60 scans
    assert all(len(r["Points2D:positions"]) > 100 for r in scans[5:])
    poses = rows["/world/tb1/pose"]
    assert len(poses) >= 50
    x, y = _one(poses[-1]["Points2D:positions"])
    assert 0 < x < 10
    assert 0 < y < 8
    assert rows["/world/tb1/path"]
    assert rows["/data/clock"]
    # the anomaly, linked by cycle to the scan that started its cycle
    anomalies = rows["/maplek/events/anomaly"]
    assert anomalies
    a = anomalies[0]
    cycle_hex = _one(a["cycle_id"])
    assert cycle_hex
    assert _one(a["cause_id"])
    scan = next(r for r in scans if _one(r["uid"]) == cycle_hex)
    assert scan["cycle"] == a["cycle"] is not None  # the same number on the cycle timeline
    flagged = rows["/world/tb1/anomaly"]
    assert flagged
    assert len(flagged[0]["Points2D:positions"]) > 0
    # ... and the rest of the cycle: the anomaly's cause is the new-data event
    new_data = {_one(r["uid"]): r for r in rows["/maplek/events/new-data"]}
    assert _one(new_data[_one(a["cause_id"])]["cycle_id"]) == cycle_hex
    # plan, verdict and the plan at the robot, each in some anomaly's cycle
    cycles = {_one(r["cycle_id"]) for r in anomalies}
    for entity in ("/maplek/events/new-plan", "/maplek/events/verdict", "/world/tb1/plans"):
        assert any(_one(r["cycle_id"]) in cycles for r in rows[entity]), entity
    assert any("plan at the robot" in _one(r["TextLog:text"]) for r in rows["/maplek/tb1/cycles"])
    # the stages' trace records, one line per handler call
    for stage in ("monitor", "analyse", "plan", "legitimate", "execute"):
        assert rows[f"/maplek/{stage}"], stage
    assert any(_one(r["cycle_id"]) == cycle_hex for r in rows["/maplek/analyse"])


# -- decoding, without a fabric -----------------------------------------------------------


def _scan(n: int = 8, value: float = 2.0) -> LaserScan:
    return LaserScan(
        stamp=1_000_000_000,
        frame_id="base_link",
        angle_min=0.0,
        angle_increment=2 * math.pi / n,
        range_min=0.1,
        range_max=10.0,
        ranges=pack_ranges([value] * (n - 1) + [math.inf]),
    )


def _odom(x: float, y: float) -> Odometry:
    return Odometry(
        stamp=1_000_000_000,
        frame_id="odom",
        pose=Pose2D(x=x, y=y, theta=0.0),
        twist=Twist(linear=0.0, angular=0.0),
    )


def _by_entity(logs: list[Log]) -> dict[str, Log]:
    return {"/".join(log.entity): log for log in logs}


def test_a_scan_is_drawn_where_its_cycles_odometry_puts_the_robot() -> None:
    t = Translator(SYSTEM, cycle_keys(load_plan(MODEL).plan))
    sealer = Sealer("sim_world")
    scan_key, odom_key = keys.data(SYSTEM, "tb1/scan"), keys.data(SYSTEM, "tb1/odom")
    data, env = sealer.seal_message(scan_key, _scan())
    assert t.take(scan_key, data) == []  # waits for its pose
    odom, _ = sealer.seal_message(odom_key, _odom(3.0, 4.0), cycle=env.uid, cause=env.uid)
    logs = _by_entity(t.take(odom_key, odom))
    scan = logs["world/tb1/scan"]
    pts = scan.items[0].positions  # type: ignore[union-attr]
    assert pts.shape == (7, 2)  # the inf beam has no return
    assert np.allclose(np.hypot(pts[:, 0] - 3.0, pts[:, 1] - 4.0), 2.0, atol=1e-5)
    assert scan.cycle == 0
    assert logs["world/tb1/pose"].cycle == 0
    assert scan.sim_ns == 1_000_000_000  # the simulator's clock
    # an anomaly of that cycle is drawn around the same pose
    mask = LidarMask(angle_min=0.0, angle_increment=math.pi / 4, occluded=pack_flags([1] + [0] * 7))
    ev_key = keys.event(SYSTEM, "anomaly")
    ev, _ = sealer.seal_message(ev_key, mask, cycle=env.uid, cause=env.uid)
    logs = _by_entity(t.take(ev_key, ev))
    assert logs["maplek/events/anomaly"].cycle == 0
    values = logs["maplek/events/anomaly"].items[1].values  # type: ignore[union-attr]
    assert values["cycle_id"] == env.uid.hex()
    assert values["cause_id"] == env.uid.hex()
    (px, py) = logs["world/tb1/anomaly"].items[0].positions[0]  # type: ignore[union-attr]
    assert math.isclose(px, 3.35)
    assert math.isclose(py, 4.0)
    assert t.viewed == 3
    assert not t.rejected


def test_cycles_are_learned_without_a_model() -> None:
    t = Translator(SYSTEM)
    sealer = Sealer("sim_world")
    scan_key, odom_key = keys.data(SYSTEM, "tb1/scan"), keys.data(SYSTEM, "tb1/odom")
    numbers = []
    for _ in range(3):
        data, env = sealer.seal_message(scan_key, _scan())
        t.take(scan_key, data)
        odom, _ = sealer.seal_message(odom_key, _odom(1.0, 1.0), cycle=env.uid)
        numbers.append(_by_entity(t.take(odom_key, odom))["world/tb1/scan"].cycle)
    assert numbers == [0, 1, 2]
    assert scan_key in t.cycle_keys


def test_a_cycle_keeps_its_number_whatever_arrives_first() -> None:
    """Events of a cycle may overtake its scan (other keys, other routes): the scan, its
    odometry and its events still share one cycle number, and the scan's sim time."""
    t = Translator(SYSTEM, cycle_keys(load_plan(MODEL).plan))
    sim, mon = Sealer("sim_world"), Sealer("monitor")
    scan_key, odom_key = keys.data(SYSTEM, "tb1/scan"), keys.data(SYSTEM, "tb1/odom")
    ev_key = keys.event(SYSTEM, "new-data")
    first, _ = sim.seal_message(scan_key, _scan())  # an earlier cycle, in order
    t.take(scan_key, first)
    data, env = sim.seal_message(scan_key, _scan())
    odom, _ = sim.seal_message(odom_key, _odom(1.0, 1.0), cycle=env.uid, cause=env.uid)
    event, _ = mon.seal_message(ev_key, None, cycle=env.uid, cause=env.uid)
    early = t.take(ev_key, event)  # before its scan
    drawn = t.take(scan_key, data) + t.take(odom_key, odom)
    numbers = {"/".join(log.entity): log.cycle for log in early + drawn}
    assert numbers["maplek/events/new-data"] == numbers["world/tb1/pose"] == 1
    assert [log.cycle for log in drawn if log.entity == ("world", "tb1", "scan")] == [0, 1]
    late = t.take(ev_key, mon.seal_message(ev_key, None, cycle=env.uid, cause=env.uid)[0])
    assert late[0].sim_ns == 1_000_000_000  # the scan's stamp, once the scan is known


def _deep(n: int) -> bytes:
    return b"\x91" * n + b"\x00"  # n nested one-item msgpack arrays


def test_bad_samples_are_rejected_with_a_reason_and_counted() -> None:
    t = Translator(SYSTEM)
    sealer = Sealer("prankster")
    key = keys.data(SYSTEM, "tb1/scan")
    good, _ = sealer.seal_message(key, _scan())
    wrong_body, _ = sealer.seal(
        key, LaserScan.TYPE, msgspec.msgpack.encode(Pose2D(x=1, y=2, theta=0))
    )
    unknown_deep, _ = sealer.seal(keys.event(SYSTEM, "x"), "app.Deep/1", _deep(100))
    future = msgspec.msgpack.encode(
        {"uid": b"u" * 16, "ts": 2**62, "source": "s", "seq": 0, "type": "rap.Empty/1", "body": {}}
    )
    bad: list[tuple[str, bytes, str]] = [
        (key, b"", "undecodable"),
        (key, b"\xc1", "undecodable"),
        (key, good[: len(good) // 2], "undecodable"),
        (key, wrong_body, "invalid rap.LaserScan/2 body"),
        (
            keys.data(SYSTEM, "tb1/x"),
            sealer.seal(key, LaserScan.TYPE, _bad_scan_body())[0],
            "ranges[1]",
        ),
        (keys.event(SYSTEM, "x"), unknown_deep, "nest"),
        (keys.event(SYSTEM, "y"), future, "in the future"),
        ("not/a/rap/key", good, "bad key"),
        (key, b"\x00" * (5 << 20), "bytes"),
    ]
    for k, payload, why in bad:
        assert t.take(k, payload) == [], why
        assert any(why in reason for reason in t.rejected), (why, list(t.rejected))
    assert sum(t.rejected.values()) == len(bad)
    assert t.viewed == 0
    # and it carries on
    odom, _ = sealer.seal_message(keys.data(SYSTEM, "tb1/odom"), _odom(1.0, 1.0))
    assert t.take(key, good) == []
    assert t.take(keys.data(SYSTEM, "tb1/odom"), odom)
    assert t.viewed == 2


def test_other_messages_are_shown_by_their_type() -> None:
    from rap_schemas import Rejection, TrustOutput, TrustVerdict

    t = Translator(SYSTEM)
    sealer = Sealer("checker")
    cases: list[tuple[str, Any]] = [
        (
            keys.trust(SYSTEM, "latency_ok"),
            TrustOutput(stream="latency_ok", tick=3, ts=1, value=True),
        ),
        (keys.trust(SYSTEM, "mode"), TrustOutput(stream="mode", tick=3, ts=1, value="safe")),
        (keys.trust(SYSTEM, "ok/verdict"), TrustVerdict(stream="ok", tick=4, expr="a < 2")),
        (keys.log(SYSTEM, "planner"), Rejection(node="planner", key="k", reason="bad", ts=1)),
        (keys.data(SYSTEM, "tb1/cmd_vel"), Twist(linear=0.1, angular=0.0)),
    ]
    logs = {}
    for k, msg in cases:
        logs.update(_by_entity(t.take(k, sealer.seal_message(k, msg)[0])))
    assert logs["trust/latency_ok"].items[0].value == 1.0  # type: ignore[union-attr]
    assert "safe" in logs["trust/mode"].items[0].text  # type: ignore[union-attr]
    verdict = logs["trust/ok/verdict"].items[0]
    assert isinstance(verdict, Text)
    assert verdict.level == "WARN"
    assert "a < 2" in verdict.text
    assert "bad" in logs["log/planner"].items[0].text  # type: ignore[union-attr]
    assert "rap.Twist/1" in logs["data/tb1/cmd_vel"].items[0].text  # type: ignore[union-attr]


# -- the Rerun thread ----------------------------------------------------------------------


@pytest.fixture
def recording(tmp_path: Path) -> tuple[Any, Path]:
    path = tmp_path / "w.rrd"
    rec = rerun.RecordingStream("rap_view_test", recording_id="w")
    rec.save(path)
    return rec, path


def test_a_full_queue_drops_and_counts_and_close_writes_the_rest(
    recording: tuple[Any, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    rec, path = recording
    writer = Writer(rec, capacity=2)
    entered, release = threading.Event(), threading.Event()
    real = writer._log

    def slow(op: Log) -> None:  # the first log call waits: Rerun stuck on its sink
        entered.set()
        release.wait(10)
        real(op)

    monkeypatch.setattr(writer, "_log", slow)

    def batch(i: int) -> list[Log]:
        return [Log(("t",), (Text(f"line {i}"),), ts=1_700_000_000_000_000_000 + i)]

    assert writer.offer(batch(0))
    assert entered.wait(10)  # taken off the queue, held by the thread
    assert writer.offer(batch(1))
    assert writer.offer(batch(2))
    assert not writer.offer(batch(3))  # full: dropped, not waited for
    assert writer.dropped == 1
    release.set()
    assert writer.close(timeout=30) is None
    assert writer.logged == 3
    assert not writer.failed
    texts = [_one(r["TextLog:text"]) for r in _rows(path)["/t"]]
    assert texts == ["line 0", "line 1", "line 2"]


# -- usage -------------------------------------------------------------------------------


def _rap(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [RAP, "view", *args],
        capture_output=True,
        text=True,
        env={**os.environ, "RERUN_ANALYTICS": "0", **(env or {})},
        timeout=60,
        check=False,
    )


def test_usage_errors_say_what_to_do(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from rap_cli.app import app
    from typer.testing import CliRunner

    monkeypatch.delenv("RAP_ZENOH_CONFIG", raising=False)
    monkeypatch.delenv("RAP_SYSTEM", raising=False)
    monkeypatch.chdir(tmp_path)  # no model.yaml here
    runner = CliRunner()
    target = ["-s", SYSTEM, "-c", f"tcp/127.0.0.1:{free_port()}"]
    cases = [
        (["--save", "a.rrd", "--spawn", *target], "give one of --spawn, --connect-viewer, --save"),
        (["--save", str(tmp_path / "no" / "a.rrd"), *target], "does not exist - create it first"),
        (["--save", str(tmp_path), *target], "is a directory - give a file path"),
        (["--connect-viewer", "http//x", *target], "not a Rerun viewer URL"),
        (["--save", "a.rrd"], "which system?"),
        (["--save", "a.rrd", "--duration", "0", *target], "--duration 0: give seconds"),
        (["--world", "atlantis", "--save", "a.rrd", *target], "not a shipped world"),
    ]
    for args, said in cases:
        res = runner.invoke(app, ["view", *args])
        assert res.exit_code == 2, (args, res.output)
        assert "rap: error: " in res.output, res.output
        assert said in res.output, (args, res.output)
        assert "Traceback" not in res.output
    assert not (tmp_path / "a.rrd").exists()  # nothing written for a usage error
    # no option, and nowhere to show a viewer: it says how else
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform.startswith("linux"):
        res = runner.invoke(app, ["view", *target])
        assert res.exit_code == 2, res.output
        assert "cannot spawn a Rerun viewer here" in res.output
        assert "--save FILE.rrd" in res.output


def test_an_unreachable_fabric_is_an_error_not_a_hang(tmp_path: Path) -> None:
    r = _rap("--save", str(tmp_path / "a.rrd"), "-s", SYSTEM, "-c", f"tcp/127.0.0.1:{free_port()}")
    assert r.returncode == 1, r.stderr
    assert "cannot reach the fabric" in r.stderr
    assert "Traceback" not in r.stderr
