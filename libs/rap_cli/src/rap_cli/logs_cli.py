"""``rap logs``: the structured logs of a system's processes, live or from history.

    rap logs -m model.yaml                      # the history in rap up's JSON lines files
    rap logs analysis --level warning --since 10m -m model.yaml
    rap logs --redis redis://127.0.0.1:6379/0 -s demo     # the history in a Redis stream
    rap logs -f -m model.yaml                   # live from the fabric, until Ctrl-C
    rap logs --audit -m model.yaml              # the admin actions: who did what, and how

Live, every record on ``rap/<system>/log/**`` is shown, decoded by its envelope's type:
log lines (``rap.LogRecord/1``) and rejections (``rap.Rejection/1``: samples a node
refused). The history comes from the files ``rap up`` writes
(``<run-dir>/<node>/logs/<process>.jsonl`` and their rotated ``.jsonl.N``), or from the
Redis stream ``rap:<system>:log`` that services given ``--log-redis`` write.

``--audit`` keeps only the audit records (logger ``rap.audit``, each line's message an
``rap_schemas.admin.AuditRecord``): every admin verb and hot swap a component was asked
for, who asked (or ``unauthenticated``), and whether it was done, refused or failed.
"""

from __future__ import annotations

import datetime
import os
import re
import signal
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import anyio
import msgspec
import typer
from rap_schemas import Envelope, LogRecord, Rejection, keys
from rap_schemas.admin import AUDIT_LOGGER, AuditRecord
from rap_schemas.limits import DecodeRejected, SafeDecoder

from .cli import OK, failed, usage
from .reach import (
    SYSTEM_ENV,
    Reach,
    Where,
    open_fabric,
    reach_options,
)

__all__ = [
    "LEVELS",
    "Entry",
    "Filter",
    "decode_log_sample",
    "parse_since",
    "read_files",
    "register",
    "render",
    "render_audit",
]

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
_UNITS = {"ms": 1e-3, "s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
_SINCE = re.compile(r"(\d+(?:\.\d+)?)(ms|s|m|h|d)")
_PAGE = 1000
"""Entries read from Redis per round trip."""

_envelope: SafeDecoder[Envelope] = SafeDecoder(Envelope, what="envelope")
_log_body: SafeDecoder[LogRecord] = SafeDecoder(LogRecord, what="log record")
_rejection_body: SafeDecoder[Rejection] = SafeDecoder(Rejection, what="rejection")
_line = msgspec.json.Decoder(LogRecord)
_audit = msgspec.json.Decoder(AuditRecord)
_encode = msgspec.json.Encoder().encode


@dataclass(frozen=True, slots=True)
class Entry:
    """One record to show: a log line, or a rejection (``key``: where it came)."""

    ts: int
    log: LogRecord | None = None
    rejection: Rejection | None = None

    @property
    def level(self) -> str:
        return self.log.level if self.log is not None else "WARNING"

    @property
    def audit(self) -> AuditRecord | None:
        """The audit record this line carries (None: not one)."""
        if self.log is None or self.log.logger != AUDIT_LOGGER:
            return None
        try:
            return _audit.decode(self.log.message)
        except msgspec.DecodeError:  # ValidationError is one
            return None


def parse_since(text: str) -> float:
    """Seconds in ``10m``, ``30s``, ``1.5h``, ``2d``, ``500ms``; ``ValueError`` otherwise."""
    m = _SINCE.fullmatch(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not a duration - write e.g. 30s, 10m, 2h or 1d")
    return float(m[1]) * _UNITS[m[2]]


@dataclass(frozen=True, slots=True)
class Filter:
    component: str | None = None
    level: int = 0
    """Index in :data:`LEVELS` of the lowest level shown."""
    since_ns: int = 0
    audit: bool = False
    """Only audit records."""

    def __call__(self, e: Entry) -> bool:
        if e.ts < self.since_ns:
            return False
        if self.audit and e.audit is None:
            return False
        level = e.level
        if level in LEVELS and LEVELS.index(level) < self.level:
            return False
        c = self.component
        if c is None:
            return True
        if e.log is not None:
            return c in (e.log.component, e.log.process)
        return e.rejection is not None and e.rejection.node == c


def _time(ts: int) -> str:
    t = datetime.datetime.fromtimestamp(ts / 1e9, tz=datetime.UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def render_audit(r: LogRecord, a: AuditRecord) -> str:
    """An audit record as a readable line: when, the result, who (role), the verb and
    the component, what was asked, and the reason."""
    who = a.who + (f" ({a.role})" if a.role else "")
    where = r.process + (f"@{r.compute_node}" if r.compute_node else "") if r.process else ""
    text = f"{_time(a.ts)} AUDIT    {a.result.upper():<7} {who}: {a.verb} {a.component}"
    if a.via != "fabric":
        text += f" (via {a.via} {a.key})"
    if a.request:
        text += f" {a.request}"
    if a.reason:
        text += f" - {a.reason}"
    if not a.checked:
        text += " [identities not checked]"
    if where:
        text += f" [{where}]"
    return text


def render(e: Entry) -> str:
    """One record as a readable line (an exception's text on the lines after it)."""
    audit = e.audit
    if audit is not None and e.log is not None:
        return render_audit(e.log, audit)
    if e.log is not None:
        r = e.log
        who = r.component or r.process or "-"
        if r.process and r.component and r.process != r.component:
            who += f"/{r.process}"
        if r.compute_node:
            who += f"@{r.compute_node}"
        text = f"{_time(r.ts)} {r.level:<8} {who} {r.logger}: {r.message}"
        if r.exc:
            text += "\n" + "\n".join("    " + line for line in r.exc.splitlines())
        return text
    assert e.rejection is not None
    j = e.rejection
    source = f" (from {j.source!r})" if j.source else ""
    return f"{_time(j.ts)} REJECTED {j.node} {j.count} sample(s) on {j.key}: {j.reason}{source}"


def as_json(e: Entry, *, audit: bool = False) -> str:
    """One record as JSON: a log line as in the files, a rejection with its ``type``;
    with ``audit``, an audit record as its own object (with the line's ``system``,
    ``compute_node`` and ``process``)."""
    record = e.audit if audit else None
    if record is not None and e.log is not None:
        where = {"system": e.log.system, "compute_node": e.log.compute_node}
        where["process"] = e.log.process
        return _encode({**msgspec.to_builtins(record), **where}).decode()
    if e.log is not None:
        return _encode(e.log).decode()
    assert e.rejection is not None
    return _encode({"type": Rejection.TYPE, **msgspec.to_builtins(e.rejection)}).decode()


def decode_log_sample(payload: bytes) -> Entry | None:
    """A sample of ``log/**`` decoded by its envelope's type (None: not a log line nor a
    rejection, or not decodable)."""
    try:
        env = _envelope.decode(payload)
        if env.type == LogRecord.TYPE:
            rec = _log_body.decode(env.body)
            return Entry(rec.ts, log=rec)
        if env.type == Rejection.TYPE:
            rej = _rejection_body.decode(env.body)
            return Entry(rej.ts, rejection=rej)
    except DecodeRejected:
        return None
    return None


# -- history: files ----------------------------------------------------------------------


def _rotation(path: Path) -> int:
    """``x.jsonl`` -> 0, ``x.jsonl.3`` -> 3 (older files have larger numbers)."""
    suffix = path.name.rpartition(".jsonl")[2].lstrip(".")
    return int(suffix) if suffix.isdigit() else 0


def log_files(run_dir: Path) -> list[Path]:
    """The JSON lines files under a ``rap up`` run dir, oldest first per process."""
    found = [p for p in run_dir.glob("*/logs/*.jsonl*") if p.is_file()]
    return sorted(found, key=lambda p: (str(p.parent), p.name.split(".jsonl")[0], -_rotation(p)))


def read_files(files: Iterable[Path]) -> tuple[list[Entry], int]:
    """Every record of ``files`` in time order, and how many lines could not be read."""
    out: list[Entry] = []
    bad = 0
    for path in files:
        try:
            data = path.read_bytes()
        except OSError:
            bad += 1
            continue
        for line in data.splitlines():
            if not line.strip():
                continue
            try:
                rec = _line.decode(line)
            except msgspec.DecodeError:
                bad += 1
                continue
            out.append(Entry(rec.ts, log=rec))
    out.sort(key=lambda e: e.ts)
    return out, bad


def _run_dir(model: Path | None, run_dir: Path | None) -> Path:
    from .up import _default_run_dir, _load

    if model is None and run_dir is not None:
        return run_dir
    file = model if model is not None else Path("model.yaml")
    if model is None and not file.is_file():
        usage(
            "whose logs? give --model MODEL (the history of its rap up), --run-dir DIR, "
            "--redis URL, or -f to follow the fabric"
        )
    file, doc = _load(file)
    return (run_dir or _default_run_dir(file, doc.plan)).resolve()


# -- history: Redis ----------------------------------------------------------------------


def _system(model: Path | None, system: str | None) -> str:
    if system is None and model is not None:
        from .up import _load

        system = _load(model)[1].plan.system
    system = system or os.environ.get(SYSTEM_ENV)
    if not system:
        usage(f"which system? give --system NAME or --model MODEL, or set {SYSTEM_ENV}")
    try:
        keys.system_pattern(system)
    except keys.KeyError_ as exc:
        usage(f"--system {system!r}: {exc}")
    return system


async def read_redis(url: str, stream: str, since_ns: int = 0) -> tuple[list[Entry], int]:
    """The records of a Redis log stream from ``since_ns`` on, and how many entries could
    not be read. Raises ``redis.RedisError`` or ``OSError`` when Redis cannot be reached."""
    import redis.asyncio

    client = redis.asyncio.from_url(url, socket_timeout=5, socket_connect_timeout=5)
    out: list[Entry] = []
    bad = 0
    start = f"{since_ns // 1_000_000}-0" if since_ns else "-"
    try:
        while True:
            rows = await client.xrange(stream, min=start, max="+", count=_PAGE)
            for _, fields in rows or []:
                try:
                    rec = _line.decode((fields or {})[b"record"])
                except (KeyError, msgspec.DecodeError):
                    bad += 1
                    continue
                out.append(Entry(rec.ts, log=rec))
            if not rows or len(rows) < _PAGE:
                break
            last = rows[-1][0]
            start = "(" + (last.decode() if isinstance(last, bytes) else str(last))
    finally:
        await client.aclose()
    return out, bad


# -- live ------------------------------------------------------------------------------------


async def _follow(reach: Reach, keep: Filter, count: int | None, raw: bool) -> int:
    from rap_sdk import InboxPolicy, Overflow

    shown = 0
    policy = InboxPolicy(capacity=4096, overflow=Overflow.FIFO, block=False, max_bytes=64 << 20)
    async with open_fabric(reach) as fabric:
        with fabric.subscribe(keys.pattern(reach.system, keys.Kind.LOG), policy) as sub:
            async with anyio.create_task_group() as tg:
                tg.start_soon(_until_signal, tg.cancel_scope)
                async for sample in sub:
                    entry = decode_log_sample(sample.payload)
                    if entry is None or not keep(entry):
                        continue
                    typer.echo(as_json(entry, audit=keep.audit) if raw else render(entry))
                    shown += 1
                    if count is not None and shown >= count:
                        break
                tg.cancel_scope.cancel()
            dropped = sub.stats.dropped
    if dropped:
        typer.echo(f"rap: warning: {dropped} record(s) not shown: they came too fast", err=True)
    return OK


async def _until_signal(scope: anyio.CancelScope) -> None:
    with anyio.open_signal_receiver(signal.SIGINT, signal.SIGTERM) as signals:
        async for _ in signals:
            scope.cancel()
            return


# -- the command ---------------------------------------------------------------------------


@reach_options
def logs_cmd(
    component: Annotated[
        str | None,
        typer.Argument(
            help="Only this component's (or process's) records.",
            metavar="COMPONENT",
            show_default=False,
        ),
    ] = None,
    follow: Annotated[
        bool, typer.Option("-f", "--follow", help="Live from the fabric, until Ctrl-C.")
    ] = False,
    level: Annotated[
        str,
        typer.Option("--level", "-l", help="The lowest level shown: debug, info, warning, error."),
    ] = "DEBUG",
    since: Annotated[
        str | None,
        typer.Option(
            "--since", help="History from this long ago: 30s, 10m, 2h, 1d.", show_default=False
        ),
    ] = None,
    raw: Annotated[bool, typer.Option("--json", help="One JSON object per record.")] = False,
    count: Annotated[
        int | None,
        typer.Option(
            "-n", "--count", help="With -f: stop after this many records.", show_default=False
        ),
    ] = None,
    redis_url: Annotated[
        str | None,
        typer.Option(
            "--redis",
            metavar="URL",
            help="The history in the Redis stream `rap:<system>:log` at URL (what services "
            "given --log-redis write).",
            show_default=False,
        ),
    ] = None,
    audit: Annotated[
        bool,
        typer.Option(
            "--audit",
            help="Only the audit records: each admin verb and hot swap, who asked, and "
            "whether it was done, refused or failed.",
        ),
    ] = False,
    *,
    where: Where,
) -> None:
    """Show the structured logs of a system's processes (knowledge, runners, trust
    checkers): one line per record (time UTC, level, component or process@compute node,
    logger, message; an exception's traceback indented below), or `--json`.

    Without `-f`: the history, from the JSON lines files of the model's `rap up` run dir
    (`<run-dir>/<node>/logs/*.jsonl`, rotated files included), or from a Redis stream
    (`--redis`). With `-f`: live from the fabric (`rap/<system>/log/**`), log lines and
    rejections (samples a node refused, shown as REJECTED). Audit records (admin verbs
    and hot swaps, who asked, the result) show as AUDIT; `--audit` shows only them.

    Example: `rap logs analysis --level warning --since 10m -m model.yaml`;
    `rap logs --audit --since 1h`"""
    name = level.upper()
    if name not in LEVELS:
        usage(f"--level {level!r} is not a level - use one of {', '.join(LEVELS).lower()}")
    since_ns = 0
    if since is not None:
        if follow:
            usage("--since picks the history; with -f records are shown as they come - drop one")
        try:
            seconds = parse_since(since)
        except ValueError as exc:
            usage(f"--since {exc}")
        since_ns = time.time_ns() - int(seconds * 1e9)
    if count is not None and (count < 1 or not follow):
        usage("-n COUNT goes with -f and is a number >= 1")
    keep = Filter(component, LEVELS.index(name), since_ns, audit)
    if follow:
        if redis_url is not None:
            usage("--redis reads the history; -f follows the fabric - drop one")
        reach = where.resolve()
        code: int = anyio.run(_follow, reach, keep, count, raw)
        raise typer.Exit(code)
    if redis_url is not None:
        import redis
        from rap_sdk.logs import redis_stream

        stream = redis_stream(_system(where.model, where.system))
        try:
            entries, bad = anyio.run(read_redis, redis_url, stream, since_ns)
        except (redis.RedisError, OSError, ValueError) as exc:  # ValueError: a bad URL
            failed(
                f"cannot read the log stream {stream} at {redis_url}: {exc} - is Redis running "
                "there (check --redis)?"
            )
        source = f"{redis_url} {stream}"
    else:
        base = _run_dir(where.model, where.run_dir)
        files = log_files(base)
        if not files:
            failed(
                f"no JSON lines logs under {base} (<node>/logs/*.jsonl) - has rap up run the "
                "model there (check --run-dir)?"
            )
        entries, bad = anyio.run(anyio.to_thread.run_sync, read_files, files)
        source = str(base)
    shown = 0
    for e in entries:
        if keep(e):
            typer.echo(as_json(e, audit=audit) if raw else render(e))
            shown += 1
    if not shown and entries:
        typer.echo(
            f"rap: no record of {len(entries)} in {source} matches"
            + (" --audit" if audit else "")
            + (f" component {component!r}" if component else "")
            + (f", level {name} or above" if name != LEVELS[0] else "")
            + (" since then" if since_ns else ""),
            err=True,
        )
    if bad:
        typer.echo(f"rap: warning: {bad} line(s) of {source} could not be read", err=True)
    raise typer.Exit(OK)


def register(app: typer.Typer) -> None:
    """Add ``rap logs`` to ``app``."""
    app.command("logs")(logs_cmd)
