"""Recordings of a system's fabric: MCAP files of whole envelopes (``rap record``,
``rap replay``), and the API other code reads them with.

A recording is an MCAP file (the format ROS 2 bags and Foxglove read) with profile
``rap``:

- one channel per key (its topic is the full key, ``rap/<system>/data/tb1/scan``), with
  message encoding ``msgpack-envelope``: each message's data is the sample's bytes as
  they crossed the fabric, the *whole* envelope, so a replay sends the same bytes;
- the channel's schema is named by the envelope's ``type`` (``rap.LaserScan/2``), with
  the JSON Schema of that message's body when RAP knows the type (``{}`` otherwise);
  a key whose samples change type gets one channel per type;
- a message's log time is when the sample was received, its publish time the
  envelope's ``ts``, its sequence the envelope's ``seq`` (modulo 2**32);
- samples on a recorded key that are not envelopes are kept too, on a channel of their
  key with message encoding ``rap-raw`` and no schema (a replay sends them as they were).

Reading::

    for key, log_time, data in read_recording("run.mcap"):   # envelopes, in file order
        env = msgspec.msgpack.decode(data, type=Envelope)

A file cut short (a recorder killed with SIGKILL, a full disk) or damaged raises
:class:`RecordingError` naming the byte offset, after everything before it was read.

Writing: :class:`Recorder` writes from a thread of its own through a bounded queue, so
the event loop never waits for the disk; what it cannot queue is dropped and counted.
:func:`replay` publishes a recording's samples again with the recorded timing.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final, NamedTuple

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import Envelope, catalog, keys
from rap_schemas.limits import DECODE_ERRORS

__all__ = [
    "ENVELOPE_ENCODING",
    "PROFILE",
    "RAW_ENCODING",
    "RecordedSample",
    "Recorder",
    "RecorderStats",
    "Recording",
    "RecordingError",
    "RecordingSummary",
    "ReplayStats",
    "read_recording",
    "recording_summary",
    "replay",
    "selected",
    "system_of",
]

PROFILE: Final = "rap"
"""The MCAP header's profile of a RAP recording."""
ENVELOPE_ENCODING: Final = "msgpack-envelope"
"""Message encoding of the channels whose data are whole RAP envelopes (msgpack)."""
RAW_ENCODING: Final = "rap-raw"
"""Message encoding of samples that were not envelopes (kept as received)."""
SCHEMA_ENCODING: Final = "jsonschema"
LIBRARY: Final = "rap-cli record"

MAX_QUEUE: Final = 65_536
"""Samples the writer may have waiting before new ones are dropped."""
MAX_QUEUED_BYTES: Final = 256 << 20
"""Bytes the writer may have waiting before new samples are dropped."""
CHUNK_BYTES: Final = 1 << 20
FLUSH_EVERY: Final = 1.0
"""Seconds between forced chunk flushes: what a recorder killed without warning loses."""
RECORD_LIMIT: Final = 1 << 30
"""The largest MCAP record a reader accepts (a corrupt length fails instead of reading
gigabytes)."""

_decode_envelope = msgspec.msgpack.Decoder(Envelope).decode
_STOP: Final = object()


class RecordingError(Exception):
    """A recording that cannot be written or read (further). ``offset``: the byte where
    reading stopped (None for a write error); ``samples``: samples read (or written)
    before it."""

    def __init__(self, message: str, *, offset: int | None = None, samples: int = 0) -> None:
        super().__init__(message)
        self.message = message
        self.offset = offset
        self.samples = samples


class RecordedSample(NamedTuple):
    """One recorded sample: ``for key, log_time, data in read_recording(path)``."""

    key: str
    """The full key it was received on."""
    log_time: int
    """When the recorder received it (UTC, ns)."""
    data: bytes
    """The sample's bytes as they crossed the fabric (a whole envelope)."""


# -- writing ------------------------------------------------------------------------------


@dataclass(slots=True)
class RecorderStats:
    """What a :class:`Recorder` did so far (a snapshot)."""

    samples: int = 0
    """Samples handed to the file's writer."""
    bytes: int = 0
    """Their payload bytes."""
    keys: int = 0
    """Distinct keys among them."""
    not_envelopes: int = 0
    """Samples among them that were not envelopes (kept as ``rap-raw``)."""
    on_disk: int = 0
    """Samples flushed to the file (at most ``flush_every`` s behind ``samples``)."""
    dropped: int = 0
    """Samples received but not recorded because the writer could not keep up (its
    queue, or the subscription's inbox, was full)."""
    lost: int = 0
    """Samples not written because writing failed (those of the chunk being written
    then, and every one after it)."""
    queued: int = 0
    """Samples waiting for the writer now."""


def _schema_data(type_name: str) -> bytes:
    """The JSON Schema of a message type's body (``{}`` for a type RAP does not know)."""
    try:
        cls = catalog.by_type(type_name)
    except KeyError:
        return b"{}"
    try:
        schema = msgspec.json.schema(cls)
    except (TypeError, ValueError):  # a message msgspec cannot describe: any value
        return b"{}"
    schema["title"] = type_name
    return json.dumps(schema, sort_keys=True).encode()


class Recorder:
    """Writes samples into an MCAP file from a thread of its own.

    ``offer()`` (on the event loop) never blocks: it queues the sample, or drops and
    counts it when ``max_queue`` samples or ``max_queued_bytes`` bytes already wait. Use
    it as ``async with Recorder(path) as rec:`` (the file is opened and finished in worker
    threads), and :meth:`follow` to record what a fabric carries::

        async with Recorder("run.mcap") as rec, anyio.create_task_group() as tg:
            await tg.start(rec.follow, fabric, [keys.system_pattern("demo")])
            ...
            tg.cancel_scope.cancel()

    The writer flushes a chunk to the file every ``flush_every`` seconds, so a recorder
    killed without warning loses at most that much. A write error (a full disk) stops
    the writer: :attr:`error` says what happened, and what came later is counted as
    lost. :meth:`close` finishes the file (its summary and index).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        max_queue: int = MAX_QUEUE,
        max_queued_bytes: int = MAX_QUEUED_BYTES,
        compression: bool = True,
        chunk_bytes: int = CHUNK_BYTES,
        flush_every: float = FLUSH_EVERY,
        overwrite: bool = True,
    ) -> None:
        self.path = Path(path)
        self.max_queue = max_queue
        self.max_queued_bytes = max_queued_bytes
        self.compression = compression
        self.chunk_bytes = chunk_bytes
        self.flush_every = flush_every
        self.overwrite = overwrite
        self.error: str | None = None
        """Why writing stopped (None: it has not)."""
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        # Each counter has one writer, so neither side ever waits for a lock: the loop
        # counts what it queued and refused, the writer thread what it took and wrote.
        self._in = 0
        self._in_bytes = 0
        self._refused = 0
        self._out = 0
        self._out_bytes = 0
        self._accepted = 0
        self._accepted_bytes = 0
        self._flushed = 0
        self._flushed_bytes = 0
        self._lost = 0
        self._late = 0
        """Samples offered after the writer stopped or the recorder closed."""
        self._not_envelopes = 0
        self._keys: set[str] = set()
        self._left = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        self._subs: list[Any] = []
        self._stream: IO[bytes] | None = None
        self._writer: Any = None

    # -- life cycle (blocking: call from a worker thread, or use ``async with``) ---------

    def open(self) -> None:
        """Create the file and start the writer; :class:`RecordingError` says why not."""
        from mcap.writer import CompressionType, Writer

        mode = "wb" if self.overwrite else "xb"
        try:
            stream = open(self.path, mode)  # closed by the writer thread
        except FileExistsError:
            raise RecordingError(
                f"{self.path}: the file exists - choose another path (or overwrite it)"
            ) from None
        except OSError as exc:
            raise RecordingError(
                f"{self.path}: cannot create it ({exc.strerror or exc}) - choose a path in a "
                "folder you can write to"
            ) from None
        try:
            writer = Writer(
                stream,
                chunk_size=self.chunk_bytes,
                compression=CompressionType.ZSTD if self.compression else CompressionType.NONE,
            )
            writer.start(profile=PROFILE, library=LIBRARY)
            stream.flush()
        except OSError as exc:
            stream.close()
            raise RecordingError(
                f"{self.path}: cannot write it ({exc.strerror or exc}) - free some space or "
                "choose another path"
            ) from None
        self._stream, self._writer = stream, writer
        self._thread = threading.Thread(target=self._run, name=f"recorder {self.path}", daemon=True)
        self._thread.start()

    def close(self) -> RecorderStats:
        """Write what is queued, finish the file and close it (idempotent)."""
        if self._thread is not None and not self._closed:
            self._closed = True
            self._queue.put(_STOP)
            self._thread.join()
            self._left = self._in - self._out  # offered as it closed: never written
        return self.stats

    async def __aenter__(self) -> Recorder:
        await anyio.to_thread.run_sync(self.open)
        return self

    async def __aexit__(self, *exc: object) -> None:
        with anyio.CancelScope(shield=True):
            await anyio.to_thread.run_sync(self.close)

    # -- feeding (on the event loop) -----------------------------------------------------

    def offer(self, key: str, data: bytes, log_time: int | None = None) -> bool:
        """Queue one sample (``log_time``: when it was received, UTC ns; default now).
        False when it was not queued (queue full, writer stopped or closed)."""
        n = len(data)
        if self._closed or self.error is not None:
            self._late += 1
            return False
        if (
            self._in - self._out >= self.max_queue
            or self._in_bytes - self._out_bytes + n > self.max_queued_bytes
        ):
            self._refused += 1
            return False
        self._in += 1
        self._in_bytes += n
        self._queue.put((key, data, time.time_ns() if log_time is None else log_time))
        return True

    async def follow(
        self,
        fabric: Any,
        key_exprs: Sequence[str],
        *,
        task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Record every sample on ``key_exprs`` (full key expressions) until cancelled;
        ``task_status.started()`` once subscribed. Overlapping expressions record a
        sample once."""
        from rap_sdk import InboxPolicy, Overflow
        from rap_sdk.keyexpr import intersects

        policy = InboxPolicy(
            capacity=self.max_queue, overflow=Overflow.FIFO, block=False, max_bytes=64 << 20
        )
        subs = [fabric.subscribe(expr, policy) for expr in dict.fromkeys(key_exprs)]
        self._subs.extend(subs)
        exprs = [s.key_expr for s in subs]

        async def pump(sub: Any, earlier: list[str]) -> None:
            offer, now, mono = self.offer, time.time_ns, time.monotonic
            async for sample in sub:
                key = sample.key
                if earlier and any(intersects(e, key) for e in earlier):
                    continue  # an earlier expression's subscription records it
                arrived = sample.arrived
                t = now()
                offer(key, sample.payload, t - int((mono() - arrived) * 1e9) if arrived else t)

        try:
            async with anyio.create_task_group() as tg:
                for i, sub in enumerate(subs):
                    tg.start_soon(pump, sub, exprs[:i])
                task_status.started()
        finally:
            for sub in subs:
                sub.close()

    @property
    def stats(self) -> RecorderStats:
        inbox_drops = sum(s.stats.dropped for s in self._subs)
        return RecorderStats(
            samples=self._accepted,
            bytes=self._accepted_bytes,
            keys=len(self._keys),
            not_envelopes=self._not_envelopes,
            on_disk=self._flushed,
            dropped=self._refused + inbox_drops,
            lost=self._lost + self._late + self._left,
            queued=max(0, self._in - self._out - self._left),
        )

    # -- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        writer, stream = self._writer, self._stream
        assert stream is not None
        schemas: dict[str, int] = {}
        channels: dict[tuple[str, str, str], int] = {}
        pending = False
        last_flush = time.monotonic()
        get = self._queue.get
        while True:
            try:
                item = get(timeout=self.flush_every) if pending else get()
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None:
                key, data, log_time = item
                self._out += 1
                self._out_bytes += len(data)
                if self.error is not None:
                    self._lost += 1
                    continue
                try:
                    self._write(writer, schemas, channels, key, data, log_time)
                except OSError as exc:
                    self._failed(exc, in_hand=1)
                    continue
                pending = True
            if pending and time.monotonic() - last_flush >= self.flush_every:
                self._flush(writer)
                pending, last_flush = False, time.monotonic()
        try:
            if self.error is None:
                writer.finish()
                stream.flush()
                self._flushed, self._flushed_bytes = self._accepted, self._accepted_bytes
                os.fsync(stream.fileno())
        except OSError as exc:
            self._failed(exc)
        except ValueError:  # a stream without a file descriptor (fsync): nothing to sync
            pass
        finally:
            with contextlib.suppress(OSError):  # the error, if any, is reported already
                stream.close()

    def _flush(self, writer: Any) -> None:
        if self.error is not None:
            return
        try:
            writer.flush()
        except OSError as exc:
            self._failed(exc)
        else:
            self._flushed, self._flushed_bytes = self._accepted, self._accepted_bytes

    def _failed(self, exc: OSError, in_hand: int = 0) -> None:
        if self.error is None:
            # what was handed to the writer since the last flush went down with it
            self._lost += self._accepted - self._flushed + in_hand
            self._accepted, self._accepted_bytes = self._flushed, self._flushed_bytes
            self.error = (
                f"{self.path}: writing failed after {self._flushed} samples were on disk "
                f"({exc.strerror or exc}) - free some space or record to another path"
            )
        else:
            self._lost += in_hand

    def _write(
        self,
        writer: Any,
        schemas: dict[str, int],
        channels: dict[tuple[str, str, str], int],
        key: str,
        data: bytes,
        log_time: int,
    ) -> None:
        try:
            env = _decode_envelope(data)
        except DECODE_ERRORS:
            type_name, encoding, publish_time, seq = "", RAW_ENCODING, log_time, 0
        else:
            type_name, encoding = env.type, ENVELOPE_ENCODING
            publish_time, seq = max(env.ts, 0), env.seq & 0xFFFF_FFFF
        ch = channels.get((key, type_name, encoding))
        if ch is None:
            schema_id = 0
            if encoding == ENVELOPE_ENCODING:
                schema_id = schemas.get(type_name, 0)
                if not schema_id:
                    schema_id = schemas[type_name] = writer.register_schema(
                        name=type_name, encoding=SCHEMA_ENCODING, data=_schema_data(type_name)
                    )
            ch = channels[(key, type_name, encoding)] = writer.register_channel(
                topic=key, message_encoding=encoding, schema_id=schema_id
            )
        writer.add_message(
            channel_id=ch,
            log_time=max(log_time, 0),
            data=data,
            publish_time=publish_time,
            sequence=seq,
        )
        self._accepted += 1
        self._accepted_bytes += len(data)
        self._keys.add(key)
        if encoding == RAW_ENCODING:
            self._not_envelopes += 1


# -- reading ------------------------------------------------------------------------------


def _read_errors() -> tuple[type[BaseException], ...]:
    """What the MCAP reader raises on a damaged or truncated file."""
    from mcap.exceptions import McapError

    errors: list[type[BaseException]] = [McapError, struct.error, ValueError, EOFError, KeyError]
    with contextlib.suppress(ImportError):
        import zstandard

        errors.append(zstandard.ZstdError)
    errors.append(RuntimeError)  # lz4's frame errors
    return tuple(errors)


def _reason(exc: BaseException) -> str:
    from mcap.exceptions import EndOfFile, InvalidMagic

    if isinstance(exc, EndOfFile):
        return "the file ends inside a record (cut short: the recorder did not finish it)"
    if isinstance(exc, InvalidMagic):
        return "not an MCAP file (its first or last bytes are not MCAP's magic)"
    if isinstance(exc, struct.error):
        return "the file ends inside a record (cut short)"
    return f"damaged record ({type(exc).__name__}: {exc})"


class Recording:
    """A recording on disk, read in file order (blocking I/O: iterate it in a worker
    thread when on an event loop).

    ``samples()`` yields :class:`RecordedSample`; at a damaged or truncated record it
    raises :class:`RecordingError` with the offset, after yielding everything before it.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.read = 0
        """Samples yielded so far."""
        self.skipped: dict[str, int] = {}
        """Messages not yielded, per channel topic: other encodings (an MCAP file not of
        RAP), or not envelopes when ``raw`` is False."""
        self.size = 0

    def samples(self, *, raw: bool = False) -> Iterator[RecordedSample]:
        """Every sample in file order; ``raw``: also those that were not envelopes."""
        from mcap.records import Channel, Message
        from mcap.stream_reader import StreamReader

        errors = _read_errors()
        try:
            f = open(self.path, "rb")  # closed below
        except OSError as exc:
            raise RecordingError(
                f"{self.path}: cannot read it ({exc.strerror or exc}) - check the path"
            ) from None
        with f:
            self.size = os.fstat(f.fileno()).st_size
            reader = StreamReader(f, validate_crcs=True, record_size_limit=RECORD_LIMIT)
            channels: dict[int, tuple[str, str]] = {}
            wanted = (ENVELOPE_ENCODING, RAW_ENCODING) if raw else (ENVELOPE_ENCODING,)
            good = 0  # where the record after the last one read begins
            records = reader.records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except errors as exc:
                    raise RecordingError(
                        f"{self.path}: byte {good} of {self.size}: {_reason(exc)}; "
                        f"{self.read} sample(s) before it were read",
                        offset=good,
                        samples=self.read,
                    ) from None
                good = f.tell()
                if isinstance(record, Channel):
                    channels[record.id] = (record.topic, record.message_encoding)
                elif isinstance(record, Message):
                    topic, encoding = channels.get(record.channel_id, ("", ""))
                    if not topic:
                        raise RecordingError(
                            f"{self.path}: byte {good}: a message of channel "
                            f"{record.channel_id}, which the file never declared (damaged)",
                            offset=good,
                            samples=self.read,
                        )
                    if encoding not in wanted:
                        self.skipped[topic] = self.skipped.get(topic, 0) + 1
                        continue
                    self.read += 1
                    yield RecordedSample(topic, record.log_time, record.data)


def read_recording(path: str | os.PathLike[str], *, raw: bool = False) -> Iterator[RecordedSample]:
    """Iterate a recording's samples ``(key, log_time, data)`` in file order (blocking
    I/O). ``raw``: also the samples that were not envelopes. Raises
    :class:`RecordingError` (with ``offset``) at a damaged or truncated record, after
    yielding everything before it."""
    return Recording(path).samples(raw=raw)


@dataclass(frozen=True, slots=True)
class RecordingSummary:
    """What a finished recording's summary section says (none for an unfinished one)."""

    samples: int
    start: int
    """Log time of the first sample (UTC ns)."""
    end: int
    topics: dict[str, int]
    """Samples per key."""

    @property
    def seconds(self) -> float:
        return max(0, self.end - self.start) / 1e9


def recording_summary(path: str | os.PathLike[str]) -> RecordingSummary | None:
    """The summary of a finished recording, read from its end without reading the
    samples; None when the file has none (cut short) or cannot be read so."""
    from mcap.reader import SeekingReader

    errors: tuple[type[BaseException], ...] = (OSError, *_read_errors())
    try:
        with open(path, "rb") as f:
            summary = SeekingReader(f, record_size_limit=RECORD_LIMIT).get_summary()
    except errors:
        return None
    if summary is None or summary.statistics is None:
        return None
    st = summary.statistics
    topics: dict[str, int] = {}
    for cid, n in st.channel_message_counts.items():
        ch = summary.channels.get(cid)
        if ch is not None:
            topics[ch.topic] = topics.get(ch.topic, 0) + n
    return RecordingSummary(st.message_count, st.message_start_time, st.message_end_time, topics)


# -- replaying ----------------------------------------------------------------------------


def _publishable(key: str) -> bool:
    """Whether ``key`` is a concrete key expression (no wildcard, canonical)."""
    from rap_sdk.keyexpr import KeyExprError, validate

    if "*" in key:
        return False
    try:
        validate(key)
    except KeyExprError:
        return False
    return True


def selected(key: str, only: Sequence[str] = (), exclude: Sequence[str] = ()) -> bool:
    """Whether ``key`` passes the filters: it matches one of ``only`` (when any are
    given) and none of ``exclude`` (full key expressions)."""
    from rap_sdk.keyexpr import intersects

    if only and not any(intersects(e, key) for e in only):
        return False
    return not any(intersects(e, key) for e in exclude)


@dataclass(slots=True)
class ReplayStats:
    """What :func:`replay` did so far."""

    sent: int = 0
    bytes: int = 0
    filtered: int = 0
    """Samples of the recording the filters left out."""
    keys: set[str] = field(default_factory=set)
    position: float = 0.0
    """Recorded seconds replayed (log time of the last sample sent, from the first)."""
    behind: float = 0.0
    """The most the replay fell behind the scaled recorded timing (s)."""
    bad_keys: dict[str, int] = field(default_factory=dict)
    """Samples not sent because their recorded key is not a key one can publish on (a
    damaged or hand-made file), per key."""


async def replay(
    path: str | os.PathLike[str],
    fabric: Any,
    *,
    speed: float = 1.0,
    only: Sequence[str] = (),
    exclude: Sequence[str] = (),
    stats: ReplayStats | None = None,
    on_sample: Callable[[RecordedSample], None] | None = None,
) -> ReplayStats:
    """Publish a recording's samples on ``fabric``, each on its key with its recorded
    bytes, spaced as recorded divided by ``speed`` (0: as fast as possible). ``only`` /
    ``exclude``: full key expressions that select the samples (see :func:`selected`).
    Raises :class:`RecordingError` at a damaged or truncated record after replaying
    everything before it (``stats``, when given, shows how far it got)."""
    if not (speed >= 0 and speed != float("inf")):
        raise ValueError(f"speed {speed!r}: give a number >= 0 (0: as fast as possible)")
    st = stats if stats is not None else ReplayStats()
    send, recv = anyio.create_memory_object_stream[RecordedSample | RecordingError](256)

    def read() -> None:
        rec = Recording(path)
        try:
            for s in rec.samples(raw=True):
                if not _publishable(s.key):
                    st.bad_keys[s.key] = st.bad_keys.get(s.key, 0) + 1
                elif selected(s.key, only, exclude):
                    anyio.from_thread.run(send.send, s)
                else:
                    st.filtered += 1
        except RecordingError as exc:
            anyio.from_thread.run(send.send, exc)
        except (anyio.BrokenResourceError, anyio.ClosedResourceError):
            return  # the replay stopped: no one reads any more
        finally:
            with contextlib.suppress(RuntimeError):  # the loop is gone: nothing to tell
                anyio.from_thread.run_sync(send.close)

    failure: RecordingError | None = None
    async with anyio.create_task_group() as tg:
        tg.start_soon(anyio.to_thread.run_sync, read)
        with recv:
            t0: int | None = None
            start = anyio.current_time()
            async for item in recv:
                if isinstance(item, RecordingError):
                    failure = item
                    break
                if t0 is None:
                    t0 = item.log_time
                offset = (item.log_time - t0) / 1e9
                if speed > 0:
                    late = anyio.current_time() - (start + offset / speed)
                    if late < 0:
                        await anyio.sleep(-late)  # the recorded spacing
                    else:
                        st.behind = max(st.behind, late)
                        await anyio.lowlevel.checkpoint()
                else:
                    await anyio.lowlevel.checkpoint()
                await fabric.publish(item.key, item.data)
                st.sent += 1
                st.bytes += len(item.data)
                st.keys.add(item.key)
                st.position = max(st.position, offset)
                if on_sample is not None:
                    on_sample(item)
    if failure is not None:
        raise failure
    return st


def system_of(key: str) -> str | None:
    """The system of a recorded key (None: not a RAP key)."""
    try:
        return keys.parse(key).system
    except keys.KeyError_:
        return None
