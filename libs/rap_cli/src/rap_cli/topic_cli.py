"""``rap topic list|echo|hz``, ``rap record`` and ``rap replay``: read a running system's
fabric, record it to MCAP and play a recording back.

    rap topic list -m model.yaml                 # keys seen in 2 s: kind, type, rate
    rap topic echo event/anomaly -m model.yaml   # each sample decoded, with its envelope
    rap topic hz data/tb1/scan -m model.yaml     # rate per key, refreshed every second
    rap record -o run.mcap -m model.yaml         # everything of the system, until Ctrl-C
    rap replay run.mcap --only 'data/**' -m model.yaml

Key expressions are relative to the system (``data/tb1/scan``, ``event/**``, ``**``) or
full (``rap/demo/data/tb1/scan``). The fabric is reached as every operate verb reaches it
(:mod:`rap_cli.reach`).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import anyio
import msgspec
import typer
from rap_schemas import Envelope, catalog, keys
from rap_schemas.limits import MAX_DEPTH, MAX_SAMPLE_BYTES, DecodeRejected, SafeDecoder

from .cli import FAILED, OK, usage
from .reach import (
    SYSTEM_ENV,
    Reach,
    Where,
    open_fabric,
    reach_options,
)
from .recording import (
    Recorder,
    RecordingError,
    RecordingSummary,
    ReplayStats,
    read_recording,
    recording_summary,
    replay,
    selected,
    system_of,
)

__all__ = [
    "Decoded",
    "KeyStats",
    "RateWindow",
    "decode_sample",
    "key_expr",
    "register",
]

topic_app = typer.Typer(
    help="Look at a running system's fabric: the keys on it, their samples, their rates.",
    no_args_is_help=True,
)

# -- key expressions ----------------------------------------------------------------------


def key_expr(system: str, expr: str) -> str:
    """The full key expression for ``expr``: relative to ``system`` (``data/tb1/scan``,
    ``event/**``, ``**``) or already full (``rap/<system>/...``). ``ValueError`` saying
    what to write otherwise."""
    from rap_sdk.keyexpr import KeyExprError, validate

    expr = expr.strip().strip("/")
    if not expr:
        raise ValueError("an empty key expression; give e.g. 'data/tb1/scan' or 'event/**'")
    first, _, rest = expr.partition("/")
    try:
        if first == keys.ROOT:
            return validate(expr)
        if expr == "**":
            return keys.system_pattern(system)
        try:
            kind = keys.Kind(first)
        except ValueError:
            raise ValueError(
                f"{expr!r}: begin with a kind ({', '.join(k.value for k in keys.Kind)}), "
                f"give '**' for everything, or a full key expression '{keys.ROOT}/...'"
            ) from None
        return keys.pattern(system, kind, rest or "**")
    except (keys.KeyError_, KeyExprError) as exc:
        raise ValueError(f"{expr!r}: {exc}") from None


def _exprs(system: str, exprs: list[str] | None, option: str) -> list[str]:
    out = []
    for e in exprs or []:
        try:
            out.append(key_expr(system, e))
        except ValueError as exc:
            usage(f"{option} {exc}")
    return out


def _kind(key: str) -> str:
    try:
        return keys.parse(key).kind.value
    except keys.KeyError_:
        return "-"


def _hex(value: bytes | None) -> str | None:
    return None if value is None else value.hex()


# -- decoding (rap topic echo) ------------------------------------------------------------

_envelope: SafeDecoder[Envelope] = SafeDecoder(Envelope, what="not an envelope")
_untyped: SafeDecoder[Any] = SafeDecoder(max_depth=MAX_DEPTH, what="body")
_typed: dict[str, SafeDecoder[Any]] = {}


@dataclass(frozen=True, slots=True)
class Decoded:
    """One sample as ``rap topic echo`` shows it."""

    key: str
    size: int
    envelope: Envelope | None = None
    body: Any = None
    """The body as plain data (typed messages via their class, unknown types untyped)."""
    known: bool = False
    """Whether the type is in :mod:`rap_schemas.catalog`."""
    rejected: str | None = None
    """Why the sample could not be shown (not an envelope, a body that does not decode)."""

    def to_json(self) -> dict[str, Any]:
        if self.envelope is None or self.rejected is not None:
            out: dict[str, Any] = {"key": self.key, "rejected": self.rejected, "size": self.size}
            if self.envelope is not None:
                out["type"] = self.envelope.type
                out["source"] = self.envelope.source
            return out
        env = self.envelope
        return {
            "key": self.key,
            "type": env.type,
            "source": env.source,
            "seq": env.seq,
            "ts": env.ts,
            "uid": env.uid.hex(),
            "cycle": _hex(env.cycle),
            "cause": _hex(env.cause),
            "ctx": dict(env.ctx),
            "known_type": self.known,
            "size": self.size,
            "body": _jsonable(self.body),
        }


def _decoder(type_name: str) -> SafeDecoder[Any] | None:
    dec = _typed.get(type_name)
    if dec is None:
        try:
            cls = catalog.by_type(type_name)
        except KeyError:
            return None
        dec = _typed[type_name] = SafeDecoder(cls, what=f"body ({type_name})")
    return dec


def decode_sample(key: str, payload: bytes, *, max_bytes: int = MAX_SAMPLE_BYTES) -> Decoded:
    """Decode a sample for display: the envelope, then its body by the envelope's
    ``type`` (a class of :mod:`rap_schemas.catalog`; plain msgpack for a type it does not
    know). Never raises for bad input: the result says why it was rejected."""
    n = len(payload)
    if n > max_bytes:
        return Decoded(key, n, rejected=f"{n} bytes, over the limit of {max_bytes}")
    try:
        env = _envelope.decode(payload)
    except DecodeRejected as exc:
        return Decoded(key, n, rejected=exc.reason)
    dec = _decoder(env.type)
    try:
        if dec is None:
            return Decoded(key, n, env, _untyped.decode(env.body))
        obj = dec.decode(env.body)
    except DecodeRejected as exc:
        return Decoded(key, n, env, rejected=exc.reason)
    return Decoded(key, n, env, msgspec.to_builtins(obj, builtin_types=(bytes,)), known=True)


def _jsonable(value: Any) -> Any:
    """Plain data fit for JSON: map keys as strings, msgpack extensions as
    ``{"ext": code, "data": base64}`` (bytes stay bytes: msgspec writes them as base64).
    Depth is bounded by the decoder (``MAX_DEPTH``)."""
    if isinstance(value, dict):
        return {
            (k if isinstance(k, str) else _scalar_text(k)): _jsonable(v) for k, v in value.items()
        }
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, msgspec.msgpack.Ext):
        return {"ext": value.code, "data": bytes(value.data)}
    return value


def _scalar_text(value: Any) -> str:
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    return str(value)


_SHORT_BYTES = 32


def _show(value: Any) -> str:
    """A scalar for the pretty view: bytes as hex when short, else their length."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        b = bytes(value)
        if len(b) <= _SHORT_BYTES:
            return b.hex() or "''"
        return f"<{len(b)} bytes: {b[:8].hex()}...>"
    if isinstance(value, msgspec.msgpack.Ext):
        return f"<ext {value.code}: {len(bytes(value.data))} bytes>"
    if isinstance(value, str):
        return repr(value) if value == "" or value != value.strip() or "\n" in value else value
    if value is None:
        return "null"
    return str(value)


def _lines(value: Any, indent: str) -> list[str]:
    out: list[str] = []
    if isinstance(value, dict):
        if not value:
            return [f"{indent}{{}}"]
        for k, v in value.items():
            name = k if isinstance(k, str) else _scalar_text(k)
            if isinstance(v, (dict, list, tuple)) and v and not _flat(v):
                out.append(f"{indent}{name}:")
                out += _lines(v, indent + "  ")
            else:
                out.append(f"{indent}{name}: {_inline(v)}")
        return out
    if isinstance(value, (list, tuple)):
        if _flat(value):
            return [f"{indent}{_inline(value)}"]
        for v in value:
            sub = _lines(v, indent + "  ")
            out.append(f"{indent}- {sub[0].lstrip()}")
            out += sub[1:]
        return out
    return [f"{indent}{_show(value)}"]


def _flat(value: Any) -> bool:
    """A short list of scalars (or an empty container): shown on one line."""
    if isinstance(value, dict):
        return not value
    return len(value) <= 16 and not any(isinstance(v, (dict, list, tuple)) for v in value)


def _inline(value: Any) -> str:
    if isinstance(value, dict):
        return "{}" if not value else "{...}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return _show(value)


def _stamp(ts: int) -> str:
    try:
        t = datetime.datetime.fromtimestamp(ts / 1e9, tz=datetime.UTC)
    except (OverflowError, OSError, ValueError):
        return str(ts)
    return t.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def render(d: Decoded) -> str:
    """The pretty view of one decoded sample."""
    if d.rejected is not None:
        head = f"{d.key}: REJECTED ({d.size} bytes): {d.rejected}"
        if d.envelope is not None:
            head += f" [type {d.envelope.type} from {d.envelope.source}]"
        return head
    env = d.envelope
    assert env is not None
    typ = env.type if d.known else f"{env.type} (unknown type: plain msgpack)"
    lines = [
        f"{d.key}  {typ}",
        f"  source: {env.source}  seq: {env.seq}  ts: {_stamp(env.ts)}",
        f"  uid: {env.uid.hex()}",
        f"  cycle: {_hex(env.cycle) or '-'}  cause: {_hex(env.cause) or '-'}",
    ]
    if env.ctx:
        lines.append("  ctx: " + ", ".join(f"{k}={v}" for k, v in env.ctx.items()))
    body = d.body
    if isinstance(body, dict) and body:
        lines.append("  body:")
        lines += _lines(body, "    ")
    else:
        lines.append(f"  body: {_inline(body)}")
    return "\n".join(lines)


# -- rates (rap topic hz, rap topic list) -------------------------------------------------


class RateWindow:
    """The arrival times of the last ``window + 1`` samples of one key: the rate and the
    intervals' mean, min, max and standard deviation (s)."""

    __slots__ = ("count", "times")

    def __init__(self, window: int = 100) -> None:
        self.times: deque[float] = deque(maxlen=window + 1)
        self.count = 0

    def add(self, t: float) -> None:
        self.times.append(t)
        self.count += 1

    def stats(self) -> dict[str, float | int | None]:
        ts = self.times
        gaps = [b - a for a, b in zip(ts, list(ts)[1:], strict=False)]
        if not gaps:
            return {"n": 0, "rate_hz": None, "mean": None, "min": None, "max": None, "std": None}
        mean = sum(gaps) / len(gaps)
        std = math.sqrt(sum((g - mean) ** 2 for g in gaps) / len(gaps))
        return {
            "n": len(gaps),
            "rate_hz": 1.0 / mean if mean > 0 else None,
            "mean": mean,
            "min": min(gaps),
            "max": max(gaps),
            "std": std,
        }


@dataclass(slots=True)
class KeyStats:
    """What ``rap topic list`` saw on one key."""

    key: str
    kind: str
    type: str | None = None
    count: int = 0
    bytes: int = 0
    first: float = 0.0
    last: float = 0.0
    not_envelopes: int = 0
    types: set[str] = field(default_factory=set)

    @property
    def rate(self) -> float | None:
        if self.count < 2 or self.last <= self.first:
            return None
        return (self.count - 1) / (self.last - self.first)

    def to_json(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "kind": self.kind,
            "type": self.type,
            "types": sorted(self.types),
            "count": self.count,
            "bytes": self.bytes,
            "rate_hz": self.rate,
            "not_envelopes": self.not_envelopes,
        }


_TYPE_ONLY = msgspec.msgpack.Decoder(Envelope).decode


def _arrival(sample: Any) -> float:
    arrived: float = sample.arrived
    return arrived if arrived else time.monotonic()


# -- running on the fabric ------------------------------------------------------------------


def _policy(capacity: int = 4096) -> Any:
    from rap_sdk import InboxPolicy, Overflow

    return InboxPolicy(capacity=capacity, overflow=Overflow.FIFO, block=False, max_bytes=64 << 20)


async def _until_signal(scope: anyio.CancelScope, said: list[str]) -> None:
    """Cancel ``scope`` on SIGINT or SIGTERM (recording what came)."""
    with anyio.open_signal_receiver(signal.SIGINT, signal.SIGTERM) as signals:
        async for signum in signals:
            said.append(signal.Signals(signum).name)
            scope.cancel()
            return


def _out(text: str) -> bool:
    """Print a line on standard output; False when the reader has gone (a closed pipe,
    as after ``| head``): standard output then goes nowhere, so that nothing more fails."""
    try:
        typer.echo(text)
        sys.stdout.flush()
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return False
    return True


def _run(fn: Callable[..., Any], *args: Any) -> int:
    code: int = anyio.run(fn, *args)
    return code


def _positive(option: str, value: float | None, *, zero: bool = False) -> None:
    if value is None:
        return
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero):
        usage(f"{option} {value:g}: give a number of seconds > 0")


SecondsOpt = Annotated[
    float,
    typer.Option("--for", help="Seconds to watch the fabric.", show_default=True),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="JSON output (see the description).")]


@topic_app.command("list")
@reach_options
def list_cmd(
    seconds: SecondsOpt = 2.0,
    as_json: JsonOpt = False,
    *,
    where: Where,
) -> None:
    """The keys on the system's fabric: kind, message type, rate and count.

    The keys seen within `--for` seconds, each with its kind (data, event, kb, trace,
    trust, log, alive), the message type its envelopes name, its rate and count; the
    alive keys are the liveliness tokens up now. `--json`: one JSON array of
    `{key, kind, type, types, count, bytes, rate_hz, not_envelopes}`.

    Example: `rap topic list -m examples/lidar_occlusion/model.yaml --for 5`"""
    _positive("--for", seconds)
    reach = where.resolve()
    raise typer.Exit(_run(_list, reach, seconds, as_json))


async def _list(reach: Reach, seconds: float, as_json: bool) -> int:
    seen: dict[str, KeyStats] = {}
    alive: list[str] = []
    async with open_fabric(reach) as fabric:
        with fabric.subscribe(keys.system_pattern(reach.system), _policy()) as sub:
            with anyio.move_on_after(seconds):
                async for sample in sub:
                    key = sample.key
                    st = seen.get(key)
                    if st is None:
                        st = seen[key] = KeyStats(key, _kind(key))
                    t = _arrival(sample)
                    if not st.count:
                        st.first = t
                    st.last = t
                    st.count += 1
                    payload = sample.payload
                    st.bytes += len(payload)
                    try:
                        st.type = _TYPE_ONLY(payload).type
                        st.types.add(st.type)
                    except (msgspec.MsgspecError, RecursionError, ValueError):
                        st.not_envelopes += 1
        from rap_sdk import FabricError

        try:
            alive = await fabric.alive(keys.pattern(reach.system, keys.Kind.ALIVE))
        except FabricError as exc:
            typer.echo(f"rap: warning: liveliness not read: {exc}", err=True)
    for key in alive:
        seen.setdefault(key, KeyStats(key, keys.Kind.ALIVE.value))
    rows = [seen[k] for k in sorted(seen)]
    if as_json:
        _out(msgspec.json.encode([r.to_json() for r in rows]).decode())
        return OK
    if not rows:
        typer.echo(
            f"no keys of system {reach.system} seen in {seconds:g} s ({reach.where}); is it "
            "running, and is it the right system (--system)?",
            err=True,
        )
        return OK
    table = [("KEY", "KIND", "TYPE", "RATE", "COUNT")]
    for r in rows:
        if r.kind == keys.Kind.ALIVE.value and not r.count:
            table.append((r.key, r.kind, "-", "-", "-"))
            continue
        typ = r.type or "-"
        if len(r.types) > 1:
            typ = ",".join(sorted(r.types))
        if r.not_envelopes:
            typ += f" (+{r.not_envelopes} not envelopes)"
        rate = "-" if r.rate is None else f"{r.rate:.1f} Hz"
        table.append((r.key, r.kind, typ, rate, str(r.count)))
    widths = [max(len(row[i]) for row in table) for i in range(5)]
    _out(
        "\n".join(
            "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in table
        )
    )
    return OK


@topic_app.command("echo")
@reach_options
def echo_cmd(
    expr: Annotated[
        str,
        typer.Argument(
            help="What to show: a key expression relative to the system (data/tb1/scan, "
            "event/**, **) or a full one (rap/demo/...).",
            metavar="KEYEXPR",
        ),
    ],
    count: Annotated[
        int | None,
        typer.Option("-n", "--count", help="Stop after this many samples.", show_default=False),
    ] = None,
    as_json: JsonOpt = False,
    *,
    where: Where,
) -> None:
    """Print each sample on KEYEXPR, decoded, with its envelope.

    Each sample is decoded by its envelope's type (the classes of
    `rap_schemas.catalog`; a type it does not know as plain msgpack data), with the
    envelope's source, seq, ts, uid, cycle and cause (hex). A sample that is not an
    envelope, or whose body does not decode, is shown as REJECTED with the reason.
    `--json`: one JSON object per line (`key, type, source, seq, ts, uid, cycle, cause,
    ctx, known_type, size, body`, or `key, rejected, size`; bytes in the body as base64).
    Until Ctrl-C, or `-n COUNT` samples.

    Example: `rap topic echo event/anomaly -n 1 -m examples/lidar_occlusion/model.yaml`"""
    if count is not None and count < 1:
        usage(f"-n {count}: give a number of samples >= 1")
    reach = where.resolve()
    [full] = _exprs(reach.system, [expr], "KEYEXPR")
    raise typer.Exit(_run(_echo, reach, full, count, as_json))


async def _echo(reach: Reach, expr: str, count: int | None, as_json: bool) -> int:
    shown = rejected = 0
    async with open_fabric(reach) as fabric:
        with fabric.subscribe(expr, _policy()) as sub:
            async with anyio.create_task_group() as tg:
                said: list[str] = []
                tg.start_soon(_until_signal, tg.cancel_scope, said)
                async for sample in sub:
                    d = decode_sample(sample.key, sample.payload)
                    rejected += d.rejected is not None
                    text = msgspec.json.encode(d.to_json()).decode() if as_json else render(d)
                    if not _out(text if as_json else text + "\n---"):
                        break  # the reader went away (| head): done
                    shown += 1
                    if count is not None and shown >= count:
                        break
                tg.cancel_scope.cancel()
            dropped = sub.stats.dropped
    if dropped:
        typer.echo(f"rap: warning: {dropped} sample(s) not shown: arrived too fast", err=True)
    if rejected and not as_json:
        typer.echo(f"{rejected} of {shown} sample(s) rejected", err=True)
    return OK


@topic_app.command("hz")
@reach_options
def hz_cmd(
    expr: Annotated[
        str,
        typer.Argument(
            help="A key expression relative to the system (data/tb1/scan, data/**) or a full one.",
            metavar="KEYEXPR",
        ),
    ],
    window: Annotated[
        int, typer.Option("--window", "-w", help="Intervals per key the numbers cover.")
    ] = 100,
    seconds: Annotated[
        float | None,
        typer.Option(
            "--for", help="Stop after this many seconds (default: Ctrl-C).", show_default=False
        ),
    ] = None,
    as_json: JsonOpt = False,
    *,
    where: Where,
) -> None:
    """The rate of each key matching KEYEXPR, refreshed every second.

    Over each key's last `--window` intervals: rate
    (Hz), mean, min and max interval and their standard deviation (ms), refreshed every
    second. `--json`: each second, one JSON object per key (`key, count, n, rate_hz,
    mean, min, max, std`, intervals in seconds).

    Example: `rap topic hz data/tb1/scan -m examples/lidar_occlusion/model.yaml`"""
    if window < 1:
        usage(f"--window {window}: give a number of intervals >= 1")
    _positive("--for", seconds)
    reach = where.resolve()
    [full] = _exprs(reach.system, [expr], "KEYEXPR")
    raise typer.Exit(_run(_hz, reach, full, window, seconds, as_json))


def _ms(v: float | int | None) -> str:
    return "-" if v is None else f"{v * 1e3:.1f}"


def hz_report(rates: dict[str, RateWindow], as_json: bool) -> list[str]:
    """The lines one refresh of ``rap topic hz`` prints."""
    out = []
    for key in sorted(rates):
        st = rates[key].stats()
        if as_json:
            out.append(msgspec.json.encode({"key": key, "count": rates[key].count, **st}).decode())
            continue
        rate = st["rate_hz"]
        out.append(
            f"{key}: "
            + ("- Hz" if rate is None else f"{rate:.2f} Hz")
            + f"  mean {_ms(st['mean'])} ms  min {_ms(st['min'])} ms  max {_ms(st['max'])} ms"
            + f"  std {_ms(st['std'])} ms  window {st['n']}"
        )
    return out


async def _hz(reach: Reach, expr: str, window: int, seconds: float | None, as_json: bool) -> int:
    rates: dict[str, RateWindow] = {}

    async def report(stop: anyio.CancelScope) -> None:
        while True:
            await anyio.sleep(1.0)
            lines = hz_report(rates, as_json)
            if not lines and not as_json:
                lines = [f"no samples on {expr} yet"]
            if lines and not _out("\n".join(lines) + ("" if as_json else "\n")):
                stop.cancel()  # the reader went away (| head): done
                return

    async with open_fabric(reach) as fabric:
        with fabric.subscribe(expr, _policy()) as sub:
            with anyio.move_on_after(math.inf if seconds is None else seconds):
                async with anyio.create_task_group() as tg:
                    said: list[str] = []
                    tg.start_soon(_until_signal, tg.cancel_scope, said)
                    tg.start_soon(report, tg.cancel_scope)
                    async for sample in sub:
                        r = rates.get(sample.key)
                        if r is None:
                            r = rates[sample.key] = RateWindow(window)
                        r.add(_arrival(sample))
    return OK


# -- rap record ------------------------------------------------------------------------------


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


class _Progress:
    """One status line on standard error, rewritten in place on a terminal."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.shown = False

    def show(self, text: str) -> None:
        if self.tty:
            typer.echo("\r" + text + "\x1b[K", err=True, nl=False)
        else:
            typer.echo(text, err=True)
        self.shown = True

    def done(self) -> None:
        if self.tty and self.shown:
            typer.echo("", err=True)


@reach_options
def record_cmd(
    exprs: Annotated[
        list[str] | None,
        typer.Argument(
            help="What to record: key expressions relative to the system (data/**, "
            "event/anomaly) or full ones (default: everything of the system, rap/<system>/**).",
            metavar="[KEYEXPR]...",
            show_default=False,
        ),
    ] = None,
    output: Annotated[
        Path,
        typer.Option("--output", "-o", help="The MCAP file to write.", show_default=False),
    ] = Path(),
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            "-d",
            help="Stop after this many seconds (default: Ctrl-C or SIGTERM).",
            show_default=False,
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite FILE if it exists.")] = False,
    *,
    where: Where,
) -> None:
    """Record the system's fabric (or the keys given) into an MCAP file.

    One channel per key (its topic the
    full key), the schema named by the envelope's type, message encoding
    `msgpack-envelope`, each message the whole envelope as received (log time: when it
    arrived; publish time: the envelope's ts). Samples that are not envelopes are kept
    too (encoding `rap-raw`). Progress (samples, bytes, keys, dropped) on standard error
    every second. Ctrl-C, SIGTERM or `--duration` stops it and finishes the file.
    Exit 0 when stopped so, 1 when writing failed (what was written is kept), 2 for bad
    usage. Read it back with `rap replay`, or `rap_cli.recording.read_recording`.

    Example: `rap record -o run.mcap -m examples/lidar_occlusion/model.yaml --duration 30`"""
    if output == Path():
        usage("where to? give --output FILE.mcap (-o)")
    _positive("--duration", duration)
    if output.is_dir():
        usage(f"--output {output}: is a folder - give a file path, e.g. {output / 'run.mcap'}")
    if not output.parent.is_dir():
        usage(f"--output {output}: the folder {output.parent} does not exist - create it first")
    if output.exists() and not force:
        usage(f"--output {output}: the file exists - choose another path, or give --force")
    reach = where.resolve()
    chosen = _exprs(reach.system, exprs, "KEYEXPR") or [keys.system_pattern(reach.system)]
    raise typer.Exit(_run(_record, reach, chosen, output, duration))


async def _record(reach: Reach, exprs: list[str], output: Path, duration: float | None) -> int:
    rec = Recorder(output)
    progress = _Progress()
    said: list[str] = []
    started = time.monotonic()
    async with open_fabric(reach) as fabric:
        try:
            await anyio.to_thread.run_sync(rec.open)
        except RecordingError as exc:
            usage(exc.message)
        try:
            with anyio.move_on_after(math.inf if duration is None else duration):
                async with anyio.create_task_group() as tg:
                    await tg.start(rec.follow, fabric, exprs)
                    tg.start_soon(_until_signal, tg.cancel_scope, said)
                    typer.echo(
                        f"recording {' '.join(exprs)} to {output} ({reach.where}); "
                        + ("Ctrl-C to stop" if duration is None else f"for {duration:g} s"),
                        err=True,
                    )
                    while rec.error is None:
                        await anyio.sleep(1.0)
                        st = rec.stats
                        progress.show(
                            f"{time.monotonic() - started:6.0f} s  {st.samples} samples, "
                            f"{_size(st.bytes)}, {st.keys} keys, {st.dropped} dropped"
                        )
                    tg.cancel_scope.cancel()
        finally:
            with anyio.CancelScope(shield=True):
                st = await anyio.to_thread.run_sync(rec.close)
            progress.done()
    why = f" ({said[0]})" if said else ""
    on_disk = (await anyio.Path(output).stat()).st_size
    summary = (
        f"{output}: {st.samples} samples on {st.keys} keys, {_size(st.bytes)} of "
        f"envelopes ({_size(on_disk)} on disk, compressed)"
        + (f", {st.not_envelopes} not envelopes" if st.not_envelopes else "")
        + (f", {st.dropped} dropped (the writer could not keep up)" if st.dropped else "")
    )
    if rec.error is not None:
        typer.echo(
            f"rap: error: {rec.error}; {st.lost} sample(s) not written; the file keeps "
            f"{st.on_disk} (rap replay reads them up to where writing stopped)",
            err=True,
        )
        return FAILED
    typer.echo(f"stopped{why}; wrote {summary}", err=True)
    return OK


# -- rap replay ------------------------------------------------------------------------------


def _first_key(path: Path) -> str | None:
    try:
        for s in read_recording(path, raw=True):
            return s.key
    except RecordingError:
        return None
    return None


@reach_options
def replay_cmd(
    file: Annotated[
        Path,
        typer.Argument(
            help="A recording (rap record's MCAP file).", metavar="FILE", show_default=False
        ),
    ],
    speed: Annotated[
        float,
        typer.Option(
            "--speed", help="Time scale: 2 twice as fast, 0.5 half, 0 as fast as possible."
        ),
    ] = 1.0,
    only: Annotated[
        list[str] | None,
        typer.Option(
            "--only",
            help="Replay only keys matching this expression (relative "
            "to the system, or full); repeatable.",
            show_default=False,
        ),
    ] = None,
    exclude: Annotated[
        list[str] | None,
        typer.Option(
            "--exclude",
            help="Leave out keys matching this expression; repeatable.",
            show_default=False,
        ),
    ] = None,
    *,
    where: Where,
) -> None:
    """Publish a recording's samples again, with the recorded timing.

    Each sample goes on its recorded key with the very bytes
    recorded (uid, seq, ts, cycle and cause as they were), spaced as recorded divided by
    `--speed`. Everything is replayed unless `--only`/`--exclude` choose: to feed a
    fresh loop the inputs of a recorded run, replay only its inputs, e.g. `--only
    'data/**' --exclude data/tb1/spin_config` (the managed system's data, not the plans
    the loop sent), so that the loop makes its own decisions again. Replay into a loop
    that has not seen the samples: receivers drop what they have seen as duplicates. A
    damaged or cut-short file is replayed up to the damage, then reported with its byte
    offset (exit 1). The system defaults to the recording's.

    Example: `rap replay run.mcap --only 'data/**' -m examples/lidar_occlusion/model.yaml`"""
    if not (math.isfinite(speed) and speed >= 0):
        usage(f"--speed {speed:g}: give a number >= 0 (0: as fast as possible)")
    if not file.is_file():
        usage(f"{file}: no such file - give a recording made by rap record")
    if (
        where.system is None
        and where.model is None
        and not Path("model.yaml").is_file()
        and not os.environ.get(SYSTEM_ENV)
    ):
        first = _first_key(file)
        where = dataclasses.replace(where, system=system_of(first) if first else None)
    reach = where.resolve()
    only_exprs = _exprs(reach.system, only, "--only")
    exclude_exprs = _exprs(reach.system, exclude, "--exclude")
    summary = recording_summary(file)
    raise typer.Exit(_run(_replay, reach, file, speed, only_exprs, exclude_exprs, summary))


async def _replay(
    reach: Reach,
    file: Path,
    speed: float,
    only: list[str],
    exclude: list[str],
    summary: RecordingSummary | None,
) -> int:
    from rap_sdk import FabricError

    st = ReplayStats()
    progress = _Progress()
    said: list[str] = []
    error: str | None = None
    total = (
        f"/{sum(n for k, n in summary.topics.items() if selected(k, only, exclude))}"
        if summary is not None
        else ""
    )
    length = f"/{summary.seconds:.1f}" if summary is not None else ""
    started = time.monotonic()
    async with open_fabric(reach) as fabric:
        typer.echo(
            f"replaying {file} ({'as fast as possible' if speed == 0 else f'x{speed:g}'}) "
            f"through {reach.where}",
            err=True,
        )
        try:
            async with anyio.create_task_group() as tg:
                tg.start_soon(_until_signal, tg.cancel_scope, said)

                async def show() -> None:
                    while True:
                        await anyio.sleep(1.0)
                        progress.show(
                            f"{st.sent}{total} samples sent, "
                            f"{st.position:.1f}{length} s of the recording, {len(st.keys)} keys"
                        )

                tg.start_soon(show)
                try:
                    await replay(file, fabric, speed=speed, only=only, exclude=exclude, stats=st)
                except RecordingError as exc:
                    error = exc.message
                except FabricError as exc:
                    error = f"publishing failed: {exc} - is the fabric still up ({reach.where})?"
                tg.cancel_scope.cancel()
        finally:
            progress.done()
    took = time.monotonic() - started
    done = (
        f"{st.sent} samples on {len(st.keys)} keys, {st.position:.1f} s of the recording "
        f"in {took:.1f} s"
        + (f", {st.filtered} left out by --only/--exclude" if st.filtered else "")
    )
    for key, n in sorted(st.bad_keys.items()):
        typer.echo(
            f"rap: warning: {file}: {n} sample(s) on {key!r} not sent: not a key one can "
            "publish on (a damaged or hand-made recording)",
            err=True,
        )
    if error is not None:
        typer.echo(f"rap: error: {error}; replayed {done}", err=True)
        return FAILED
    if said:
        typer.echo(f"stopped ({said[0]}); replayed {done}", err=True)
        return OK
    typer.echo(f"replayed {done}", err=True)
    if st.sent == 0:
        typer.echo(
            "rap: warning: nothing was replayed - check --only/--exclude against the "
            "recording's keys",
            err=True,
        )
    return OK


def register(app: typer.Typer) -> None:
    """Add ``rap topic list|echo|hz``, ``rap record`` and ``rap replay`` to ``app``."""
    app.add_typer(topic_app, name="topic")
    app.command("record")(record_cmd)
    app.command("replay")(replay_cmd)
