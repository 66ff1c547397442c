"""Recordings (rap_cli.recording, ``rap record``, ``rap replay``): what crosses the fabric
is written to MCAP whole and published again byte for byte, with the recorded timing
scaled, filtered by key; a damaged file is replayed up to the damage and reported with
its offset; a write error is reported, not raised.

Fabric tests use two real Zenoh sessions on loopback (one listens, the other connects,
as another process would); the pacing and filter tests use MemoryFabric, where nothing
but the replay's own logic is at work."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from blockbuster import BlockBuster, blockbuster_ctx
from mcap.reader import make_reader
from rap_cli.recording import (
    ENVELOPE_ENCODING,
    PROFILE,
    RAW_ENCODING,
    Recorder,
    RecordingError,
    ReplayStats,
    read_recording,
    recording_summary,
    replay,
)
from rap_schemas import Envelope, Pose2D, SimTime, keys
from rap_sdk import InboxPolicy, MemoryFabric, Sealer, ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port
from rap_sdk.testing import OutputLines, stop_process

pytestmark = pytest.mark.anyio

SYSTEM = "rt"
RAP = str(Path(sys.executable).with_name("rap"))
BIG = InboxPolicy(capacity=10_000)


@contextlib.asynccontextmanager
async def two_sessions() -> AsyncIterator[tuple[ZenohFabric, ZenohFabric, str]]:
    """A listening session and one connected to it (as another process would be)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    async with (
        ZenohFabric(ZenohConfig(listen=[ep])) as a,
        ZenohFabric(ZenohConfig(listen=[], connect=[ep])) as b,
    ):
        yield a, b, ep


def traffic() -> list[tuple[str, bytes]]:
    """Envelopes on three keys of two kinds, and one sample that is not an envelope."""
    sealer = Sealer("sim")
    out: list[tuple[str, bytes]] = []
    pose, clock, ev = (
        keys.data(SYSTEM, "tb1/pose"),
        keys.data(SYSTEM, "clock"),
        keys.event(SYSTEM, "seen"),
    )
    for i in range(10):
        out.append((pose, sealer.seal_message(pose, Pose2D(x=i, y=-i, theta=0.1))[0]))
        out.append((clock, sealer.seal_message(clock, SimTime(t=i * 200_000_000))[0]))
        if i % 3 == 0:
            out.append((ev, sealer.seal_message(ev, None, cycle=b"c" * 16, cause=b"d" * 16)[0]))
    out.append((pose, b"\xc1 not msgpack at all"))
    return out


async def collect(sub: Any, n: int, timeout: float = 10.0) -> list[tuple[str, bytes]]:
    got: list[tuple[str, bytes]] = []
    with anyio.fail_after(timeout):
        while len(got) < n:
            s = await sub.get()
            got.append((s.key, s.payload))
    return got


@pytest.mark.zenoh
async def test_a_recording_replays_byte_identical(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    sent = traffic()
    async with two_sessions() as (a, b, _):
        # b records everything of the system that a publishes
        async with Recorder(path) as rec, anyio.create_task_group() as tg:
            await tg.start(rec.follow, b, [keys.system_pattern(SYSTEM)])
            for key in {k for k, _ in sent}:
                await a.wait_matched(key)
            t_before = time.time_ns()
            for key, payload in sent:
                await a.publish(key, payload)
            with anyio.fail_after(10):
                while rec.stats.samples < len(sent):  # noqa: ASYNC110 (a counter of the writer thread)
                    await anyio.sleep(0.02)
            tg.cancel_scope.cancel()
        st = rec.stats
        assert (st.samples, st.keys, st.not_envelopes, st.dropped) == (len(sent), 3, 1, 0)

        # read back: the same bytes on the same keys, in order per key
        recorded = list(read_recording(path, raw=True))
        assert [(r.key, r.data) for r in recorded] == sent
        assert all(t_before <= r.log_time <= time.time_ns() for r in recorded)
        # without raw: the envelopes only
        assert len(list(read_recording(path))) == len(sent) - 1

        # replay from b, received by a: the very bytes again
        with a.subscribe(keys.system_pattern(SYSTEM), BIG) as sub:
            for key in {k for k, _ in sent}:
                await b.wait_matched(key)
            stats = await replay(path, b, speed=0)
            got = await collect(sub, len(sent))
    assert got == sent
    assert stats.sent == len(sent)
    assert stats.keys == {k for k, _ in sent}


@pytest.mark.zenoh
async def test_the_mcap_file_names_keys_types_and_times(tmp_path: Path) -> None:
    """Any MCAP reader sees one channel per key with the envelope's type as the schema
    name, message encoding msgpack-envelope, log time = receipt, publish time = ts."""
    path = tmp_path / "run.mcap"
    sent = traffic()
    async with two_sessions() as (a, b, _):
        async with Recorder(path) as rec, anyio.create_task_group() as tg:
            await tg.start(rec.follow, b, [keys.system_pattern(SYSTEM)])
            for key in {k for k, _ in sent}:
                await a.wait_matched(key)
            for key, payload in sent:
                await a.publish(key, payload)
            with anyio.fail_after(10):
                while rec.stats.samples < len(sent):  # noqa: ASYNC110 (a counter of the writer thread)
                    await anyio.sleep(0.02)
            tg.cancel_scope.cancel()
    with path.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == PROFILE
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        assert summary.statistics.message_count == len(sent)
        channels = {
            (c.topic, c.message_encoding, summary.schemas[c.schema_id].name if c.schema_id else "")
            for c in summary.channels.values()
        }
        assert channels == {
            (keys.data(SYSTEM, "tb1/pose"), ENVELOPE_ENCODING, Pose2D.TYPE),
            (keys.data(SYSTEM, "clock"), ENVELOPE_ENCODING, SimTime.TYPE),
            (keys.event(SYSTEM, "seen"), ENVELOPE_ENCODING, "rap.Empty/1"),
            (keys.data(SYSTEM, "tb1/pose"), RAW_ENCODING, ""),
        }
        pose_schema = next(s for s in summary.schemas.values() if s.name == Pose2D.TYPE)
        assert pose_schema.encoding == "jsonschema"
        assert b'"theta"' in pose_schema.data
        for _, channel, message in reader.iter_messages():
            if channel.message_encoding == ENVELOPE_ENCODING:
                env = msgspec.msgpack.decode(message.data, type=Envelope)
                assert message.publish_time == env.ts
                assert message.sequence == env.seq
                assert message.log_time >= env.ts
    summary2 = recording_summary(path)
    assert summary2 is not None
    assert summary2.samples == len(sent)
    assert summary2.topics[keys.data(SYSTEM, "tb1/pose")] == 11


async def _write(path: Path, samples: list[tuple[str, bytes, int]]) -> None:
    async with Recorder(path) as rec:
        for key, data, t in samples:
            assert rec.offer(key, data, t)


def _clock_samples(n: int, step_ns: int, t0: int = 1_700_000_000 * 10**9) -> list[Any]:
    sealer = Sealer("sim")
    key = keys.data(SYSTEM, "clock")
    return [(key, sealer.seal_message(key, SimTime(t=i))[0], t0 + i * step_ns) for i in range(n)]


async def _timed_replay(path: Path, speed: float) -> list[float]:
    """Replay on a MemoryFabric; each sample's arrival, in s from the first."""
    async with MemoryFabric() as fabric:
        with fabric.subscribe(keys.system_pattern(SYSTEM), BIG) as sub:
            arrivals: list[float] = []

            async def take() -> None:
                async for _ in sub:  # until cancelled: a comprehension would lose them
                    arrivals.append(anyio.current_time())  # noqa: PERF401

            async with anyio.create_task_group() as tg:
                tg.start_soon(take)
                await replay(path, fabric, speed=speed)
                await anyio.wait_all_tasks_blocked()
                tg.cancel_scope.cancel()
    return [t - arrivals[0] for t in arrivals]


async def test_the_recorded_timing_is_kept_scaled_by_speed(tmp_path: Path) -> None:
    path = tmp_path / "clock.mcap"
    await _write(path, _clock_samples(7, 200_000_000))  # 1.2 s of recording
    # x4: never earlier than the recorded offsets / 4 (0, 0.05, ..., 0.3 s)
    fast = await _timed_replay(path, 4.0)
    assert len(fast) == 7
    for i, t in enumerate(fast):
        assert t >= i * 0.05 - 0.005, (i, fast)
    assert fast[-1] < 1.2, f"x4 took as long as the recording itself: {fast}"
    # x0: as fast as possible, in order
    asap = await _timed_replay(path, 0)
    assert len(asap) == 7
    assert asap[-1] < 0.3 * 4, asap  # far from the 1.2 s of the recording


async def test_only_and_exclude_choose_the_keys(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    sent = traffic()
    await _write(path, [(k, d, 1_000 + i) for i, (k, d) in enumerate(sent)])

    async def replayed(only: list[str], exclude: list[str]) -> tuple[set[str], ReplayStats]:
        async with MemoryFabric() as fabric:
            with fabric.subscribe(keys.system_pattern(SYSTEM), BIG) as sub:
                st = await replay(path, fabric, speed=0, only=only, exclude=exclude)
                got = {s.key for s in iter(sub.get_nowait, None)}
        return got, st

    pose, clock, seen = (
        keys.data(SYSTEM, "tb1/pose"),
        keys.data(SYSTEM, "clock"),
        keys.event(SYSTEM, "seen"),
    )
    assert (await replayed([], []))[0] == {pose, clock, seen}
    got, st = await replayed([keys.pattern(SYSTEM, keys.Kind.DATA)], [])
    assert got == {pose, clock}
    assert st.filtered == 4  # the four events
    got, st = await replayed([keys.pattern(SYSTEM, keys.Kind.DATA)], [clock])
    assert got == {pose}
    assert st.sent == 11  # ten poses and the sample that was not an envelope
    got, _ = await replayed([], [keys.pattern(SYSTEM, keys.Kind.DATA, "tb1/*")])
    assert got == {clock, seen}


async def test_a_cut_short_file_replays_what_it_holds_then_names_the_offset(
    tmp_path: Path,
) -> None:
    path = tmp_path / "run.mcap"
    samples = _clock_samples(3000, 1_000_000)
    # small chunks, so that a cut leaves whole chunks before it
    async with Recorder(path, chunk_bytes=16 << 10) as rec:
        for key, data, t in samples:
            assert rec.offer(key, data, t)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError) as info:
        list(read_recording(cut))
    err = info.value
    assert err.offset is not None
    assert 0 < err.offset <= len(data) // 2  # a cut between two records: at the cut
    assert f"byte {err.offset}" in err.message
    assert "cut short" in err.message
    assert 0 < err.samples < len(samples)
    # what was read before the cut is exactly the recording's start
    read: list[bytes] = []
    with contextlib.suppress(RecordingError):
        read.extend(s.data for s in read_recording(cut))
    assert read == [d for _, d, _ in samples[: len(read)]]
    # replay sends those, then raises
    st = ReplayStats()
    async with MemoryFabric() as fabric:
        with fabric.subscribe(keys.system_pattern(SYSTEM), InboxPolicy(capacity=5000)) as sub:
            with pytest.raises(RecordingError):
                await replay(cut, fabric, speed=0, stats=st)
            got = [s.payload for s in iter(sub.get_nowait, None)]
    assert st.sent == err.samples
    assert got == read


def test_a_damaged_chunk_and_a_file_that_is_not_mcap_are_named(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    anyio.run(_write, path, _clock_samples(200, 1_000_000))
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0xFF  # inside the (compressed) chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError) as info:
        list(read_recording(bad))
    assert "damaged record" in info.value.message or "cut short" in info.value.message
    assert info.value.offset is not None
    text = tmp_path / "notes.mcap"
    text.write_text("these are notes, not a recording\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(read_recording(text))
    with pytest.raises(RecordingError, match="cannot read it"):
        list(read_recording(tmp_path / "missing.mcap"))


async def test_recording_makes_no_blocking_call_on_the_loop(tmp_path: Path) -> None:
    """The file is opened, written and finished off the event loop (blockbuster raises
    on a blocking call made on it)."""
    sent = traffic()
    with blockbuster_ctx() as bb:
        assert isinstance(bb, BlockBuster)
        async with MemoryFabric() as fabric:
            async with Recorder(tmp_path / "run.mcap") as rec, anyio.create_task_group() as tg:
                await tg.start(rec.follow, fabric, [keys.system_pattern(SYSTEM)])
                for key, payload in sent:
                    await fabric.publish(key, payload)
                with anyio.fail_after(10):
                    while rec.stats.samples < len(sent):  # noqa: ASYNC110 (a counter of the writer thread)
                        await anyio.sleep(0.01)
                tg.cancel_scope.cancel()
    assert rec.stats.samples == len(sent)


async def test_overlapping_expressions_record_each_sample_once(tmp_path: Path) -> None:
    sent = traffic()
    path = tmp_path / "run.mcap"
    exprs = [keys.pattern(SYSTEM, keys.Kind.DATA), keys.system_pattern(SYSTEM)]
    async with MemoryFabric() as fabric:
        async with Recorder(path) as rec, anyio.create_task_group() as tg:
            await tg.start(rec.follow, fabric, exprs)
            for key, payload in sent:
                await fabric.publish(key, payload)
            with anyio.fail_after(10):
                while rec.stats.samples < len(sent):  # noqa: ASYNC110 (the writer's counter)
                    await anyio.sleep(0.01)
            await anyio.sleep(0.1)  # a second copy would be written by now
            tg.cancel_scope.cancel()
    assert sorted((r.key, r.data) for r in read_recording(path, raw=True)) == sorted(sent)


async def test_a_full_queue_drops_and_counts(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "run.mcap", max_queue=5, max_queued_bytes=1 << 20)
    # not opened: nothing drains the queue, so the sixth sample finds it full
    results = [rec.offer("k", b"x" * 10, i) for i in range(8)]
    assert results == [True] * 5 + [False] * 3
    assert rec.stats.dropped == 3
    assert rec.stats.queued == 5
    big = Recorder(tmp_path / "big.mcap", max_queue=100, max_queued_bytes=100)
    assert big.offer("k", b"x" * 60, 0)
    assert not big.offer("k", b"x" * 60, 0)  # past the byte bound
    assert big.stats.dropped == 1


LIMITED = """\
import os, resource, signal, sys
# a file past this size cannot grow (EFBIG), as on a full disk; with SIGXFSZ ignored the
# write fails with an error instead of killing the process
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
os.execv(sys.argv[2], sys.argv[2:])
"""


async def _run_rap_record(
    tmp_path: Path,
    out: Path,
    *,
    stop: signal.Signals | None,
    limit: int | None = None,
    duration: float | None = None,
) -> tuple[int, str, int]:
    """Run ``rap record`` as a client of a listening session that publishes clock
    samples; stop it with ``stop`` once it recorded some (or let it end). Returns its
    exit code, its standard error and the number of samples published."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    argv = [RAP, "record", "-o", str(out), "--connect", ep, "--system", SYSTEM]
    if duration is not None:
        argv += ["--duration", str(duration)]
    sealer = Sealer("sim")
    key = keys.data(SYSTEM, "clock")
    published = 0
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        if limit is not None:
            argv = [sys.executable, "-c", LIMITED, str(limit), *argv]
        proc = await anyio.open_process(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        try:
            async with anyio.create_task_group() as tg:
                lines = OutputLines(proc)
                tg.start_soon(lines.pump)
                await lines.line("recording", "rap/rt/**")
                await fabric.wait_matched(key, timeout=10)
                with anyio.fail_after(30):
                    while proc.returncode is None:
                        msg = SimTime(t=published)
                        payload = sealer.seal_message(key, msg)[0]
                        if limit is not None:  # bigger samples, to reach the limit soon
                            payload = sealer.seal(
                                key, "x.Padding/1", msgspec.msgpack.encode(os.urandom(2000))
                            )[0]
                        await fabric.publish(key, payload)
                        published += 1
                        if stop is not None and published == 50:
                            await anyio.sleep(0.5)  # the last ones reach the recorder
                            proc.send_signal(stop)
                            break
                        await anyio.sleep(0.005)
                    await proc.wait()
        finally:
            await stop_process(proc)
    assert proc.returncode is not None
    return proc.returncode, str(lines), published


@pytest.mark.zenoh
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
async def test_rap_record_stops_on_a_signal_and_finishes_the_file(
    tmp_path: Path, stop: signal.Signals
) -> None:
    out = tmp_path / "run.mcap"
    code, output, published = await _run_rap_record(tmp_path, out, stop=stop)
    assert code == 0, output
    assert f"stopped ({stop.name}); wrote {out}: {published} samples on 1 keys" in output
    summary = recording_summary(out)  # a finished file: its summary is there
    assert summary is not None, output
    assert summary.samples == published
    assert [s.key for s in read_recording(out)] == [keys.data(SYSTEM, "clock")] * published


@pytest.mark.zenoh
async def test_rap_record_reports_a_write_error_and_keeps_what_it_wrote(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    code, output, _ = await _run_rap_record(tmp_path, out, stop=None, limit=1 << 20)
    assert code == 1, output
    assert "Traceback" not in output
    assert f"rap: error: {out}: writing failed after" in output, output
    assert "File too large" in output
    # what was on disk before the error is read back, up to where writing stopped
    kept = int(output.split("the file keeps ")[1].split()[0])
    assert kept > 0, output
    read: list[Any] = []
    with pytest.raises(RecordingError, match=r"cut short|damaged"):
        read.extend(read_recording(out))
    assert len(read) == kept, output


@pytest.mark.zenoh
async def test_rap_replay_of_a_cut_file_exits_1_naming_the_offset(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    async with Recorder(path, chunk_bytes=8 << 10) as rec:
        for key, data, t in _clock_samples(1000, 1_000_000):
            rec.offer(key, data, t)
    cut = tmp_path / "cut.mcap"
    whole = path.read_bytes()
    cut.write_bytes(whole[: len(whole) // 2])
    ep = f"tcp/127.0.0.1:{free_port()}"
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        with fabric.subscribe(keys.system_pattern(SYSTEM), BIG) as sub:
            res = await anyio.run_process(
                [RAP, "replay", str(cut), "--speed", "0", "--connect", ep],
                check=False,
                cwd=tmp_path,
            )
            err = res.stderr.decode()
            assert res.returncode == 1, err
            assert "Traceback" not in err
            assert "rap: error:" in err
            assert "cut.mcap: byte " in err
            assert "cut short" in err
            n = int(err.split("; replayed ")[1].split()[0])
            assert 0 < n < 1000, err
            # the replay's client sent them through this session: they arrive here
            with anyio.fail_after(10):
                got = 0
                while got < n:
                    await sub.get()
                    got += 1
