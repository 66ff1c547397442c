"""The fuzz run: start the loop, flood every target, check the loop still closes.

1. This process opens a Zenoh session listening on a free loopback port and starts the
   deployment plan's processes with ``lidar_occlusion.deploy.local_deployment`` (the
   knowledge service, one ``maplek_runner`` per compute node), then one trust checker
   process per MAPLE-K spec (``python -m trust_checker SPEC --fabric SYSTEM``),
   connected to every endpoint before it: a full mesh, as the deployment builds it.
2. Warm-up: occluded scans until a plan of one of them reaches the robot
   (``data/<robot>/spin_config``, matched by cycle) and every checker has published an
   output. The nodes' knowledge access records of these cycles name the knowledge keys
   the loop uses; the write stream gives a valid value of each.
3. RSS of every process (``/proc/<pid>/status``).
4. The flood: every target gets ``samples`` mutated samples (bench/fuzz/mutate.py),
   paced evenly over ``seconds``, published with Zenoh's ``block`` congestion control
   (a full link makes the fuzzer wait rather than drop); queries go a few at a time per
   queryable. Meanwhile: ``rap/<system>/log/**`` is read for ``rap.Rejection`` records,
   ``rap/<system>/alive/**`` for lost liveliness tokens, each process for its exit, and
   every queryable is probed every 2 s (a real knowledge read; a malformed swap request
   each checker must refuse).
5. The loop must close again: occluded scans (a new occlusion each time, every 0.5 s)
   until a plan of one of them reaches the robot, within ``close_timeout``.
6. RSS again; every process is stopped (SIGTERM) and its exit code and log read.

A crash is a process that exited before step 6, a liveliness token withdrawn before
step 6, a queryable that stopped answering (its last probe, after the flood, or three
probes in a row failed), or a node that stopped taking samples: fed garbage, a node
publishes a rejection record every second, so one silent for the last ``STALL_S`` s of
the flood is stuck (a hang or a deadlock; liveliness tokens live on Zenoh's threads and
do not show it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import anyio
import msgspec
from anyio.abc import Process, TaskGroup
from lidar_occlusion.deploy import local_deployment
from lidar_occlusion.scans import occluded_scan
from maplek_runner.loading import load_share
from rap_schemas import (
    KbGet,
    KbRecord,
    KbReply,
    KnowledgeAccess,
    LaserScan,
    Rejection,
    StageTrace,
    TrustSpecStatus,
    TrustSpecUpdate,
    keys,
    load_plan,
)
from rap_schemas.limits import DECODE_ERRORS, decode_failure
from rap_sdk import (
    FabricError,
    InboxPolicy,
    Node,
    Overflow,
    QueryError,
    Sealer,
    ZenohConfig,
    ZenohFabric,
)
from rap_sdk.envelope import typed_decoder
from rap_sdk.fabric import Subscription, free_port
from rap_sdk.knowledge import HybridClock
from rap_sdk.rejections import reason_kind
from trust_checker.specs import MAPLEK_OUTPUTS, maplek_specs

from . import procinfo
from .mutate import Mutator
from .samples import WRITER, kb_request, spec_update, valid_body
from .targets import RECENT, REQUEST, Target, derive, kb_keys_of

__all__ = ["Options", "run"]

log = logging.getLogger("bench.fuzz")

PROBE_EVERY = 2.0
PROBE_TIMEOUT = 5.0
PROBE_FAILS = 3
"""Probes in a row that may fail before a queryable counts as no longer answering."""
QUERY_TIMEOUT = 5.0
QUERY_WORKERS = 32
"""Queries in flight per queryable."""
RSS_EVERY = 1.0
STALL_S = 15.0
"""Seconds a node fed garbage may go without a rejection record before it counts as
having stopped taking samples."""
CTX_NEVER_EVERY = 5.0
"""Seconds between two ``ctx_never`` samples on one target: each makes a reader wait
for its knowledge deadline (2 s), so more would only stall the stage, not test more."""
SCAN_EVERY = 0.5
WARMUP_TIMEOUT = 60.0
CHECKER_STARTUP = 60.0
POOL = 16
"""Valid bodies kept per target (one is remade now and then)."""
OCCLUSIONS = [(-0.4, 0.8), (1.0, 0.6), (-1.8, 0.7), (0.3, 0.5), (2.0, 0.3), (-1.0, 0.9)]
"""(start, width) rad of the scans that close the loop: each differs from the one
before, so the analysis sees a new occlusion every time."""
ROBOT_SOURCE = "fuzz-robot"
EPOCH_S = 1_704_067_200
"""Knowledge versions count ms from 2024-01-01 (rap_schemas.knowledge.EPOCH_MS)."""

_open_trace = typed_decoder(None)
_open_record = typed_decoder(KbRecord)
_open_rejection = typed_decoder(Rejection)
_open_any = typed_decoder(None)
_open_status = typed_decoder(TrustSpecStatus)
_reply = msgspec.msgpack.Decoder(KbReply).decode
_encode = msgspec.msgpack.Encoder().encode
_clock = HybridClock(WRITER)
_BIG_FIFO = InboxPolicy(capacity=1 << 16, overflow=Overflow.FIFO, block=False)


@dataclass
class Options:
    plan: Path
    seconds: float = 300.0
    samples: int = 100_000
    seed: int = 1
    specs: list[str] = field(default_factory=lambda: sorted(MAPLEK_OUTPUTS))
    logs: Path = Path("out/fuzz/logs")
    close_timeout: float = 120.0
    system: str | None = None


@dataclass
class Proc:
    name: str
    process: Process
    log: Path
    kind: str
    """knowledge, runner or checker."""
    exited_at: float | None = None
    before: dict[str, Any] = field(default_factory=dict)
    flood_end: dict[str, Any] = field(default_factory=dict)
    rss_max_kib: int = 0
    rss_max_at_s: float = 0.0
    """The highest VmRSS seen by the sampler (every ``RSS_EVERY`` s) and when."""
    after: dict[str, Any] = field(default_factory=dict)

    @property
    def pid(self) -> int:
        return self.process.pid


@dataclass
class Probe:
    ok: int = 0
    failed: int = 0
    in_a_row: int = 0
    worst_in_a_row: int = 0
    last_error: str = ""
    max_ms: float = 0.0

    def record(self, error: str, ms: float) -> None:
        self.max_ms = max(self.max_ms, ms)
        if error:
            self.failed += 1
            self.in_a_row += 1
            self.worst_in_a_row = max(self.worst_in_a_row, self.in_a_row)
            self.last_error = error
        else:
            self.ok += 1
            self.in_a_row = 0


@dataclass
class Watch:
    """What happens to the processes while the run goes on."""

    stopping: bool = False
    t0: float = field(default_factory=time.time)
    tokens: dict[str, bool] = field(default_factory=dict)
    lost_tokens: list[dict[str, Any]] = field(default_factory=list)
    exits: list[dict[str, Any]] = field(default_factory=list)
    probes: dict[str, Probe] = field(default_factory=dict)
    rejections: Counter[tuple[str, str]] = field(default_factory=Counter)
    """(node, reason kind) -> samples, from the rap.Rejection records."""
    examples: dict[str, str] = field(default_factory=dict)
    """reason kind -> one full reason."""
    records: int = 0
    last_record: dict[str, float] = field(default_factory=dict)
    """Node -> when its last rap.Rejection record arrived (wall time)."""
    stalls: list[dict[str, Any]] = field(default_factory=list)
    puts_ended: float | None = None
    """Wall time the put flood ended (the queries may run on): the nodes' last garbage."""
    recent: Callable[[str], dict[str, Any]] = lambda _who: {}
    """The last samples sent to the targets a process or node reads (set once the
    targets are known)."""

    def at(self) -> float:
        return round(time.time() - self.t0, 2)


def _spec_path(name: str) -> Path:
    return Path(str(resources.files("trust_checker.specs").joinpath("maplek", f"{name}.dsrv")))


def _say(msg: str, t0: float) -> None:
    print(f"[{time.perf_counter() - t0:7.2f} s] {msg}", file=sys.stderr, flush=True)


# -- processes ---------------------------------------------------------------------------


@contextlib.asynccontextmanager
async def _checkers(
    names: list[str], *, system: str, connect: list[str], logs: Path, fabric: ZenohFabric
) -> AsyncIterator[list[Proc]]:
    """One trust checker process per spec, meshed with ``connect``; yields once each one's
    swap queryable is reachable. Stops them (SIGTERM) on exit."""
    procs: list[Proc] = []
    async with contextlib.AsyncExitStack() as stack:
        endpoints = list(connect)
        for name in names:
            node = f"trust_{name}"
            ep = f"tcp/127.0.0.1:{free_port()}"
            path = logs / f"{node}.log"
            out = stack.enter_context(await anyio.to_thread.run_sync(path.open, "wb"))
            args = [sys.executable, "-m", "trust_checker", str(_spec_path(name))]
            args += ["--fabric", system, "--node", node, "--listen", ep, "--log-level", "INFO"]
            args += [a for e in endpoints for a in ("--connect", e)]
            proc = await anyio.open_process(args, stdout=subprocess.DEVNULL, stderr=out)
            p = Proc(node, proc, path, "checker")
            procs.append(p)
            stack.push_async_callback(_stop, p)
            endpoints.append(ep)
        for p in procs:
            try:
                await fabric.wait_matched(
                    keys.admin(system, p.name, "swap"), queryable=True, timeout=CHECKER_STARTUP
                )
            except FabricError as exc:
                raise RuntimeError(f"{p.name} did not come up ({exc}); see {p.log}") from None
        yield procs


async def _stop(p: Proc, grace: float = 15.0) -> None:
    proc = p.process
    if proc.returncode is None:
        proc.terminate()
    with anyio.move_on_after(grace):
        await proc.wait()
    if proc.returncode is None:
        log.warning("%s did not stop within %.0f s of SIGTERM; killing it", p.name, grace)
        proc.kill()
        await proc.wait()


async def _watch_exit(p: Proc, watch: Watch) -> None:
    code = await p.process.wait()
    if not watch.stopping:
        p.exited_at = watch.at()
        watch.exits.append(
            {
                "process": p.name,
                "code": code,
                "at_s": p.exited_at,
                "last_samples": watch.recent(p.name),
            }
        )
        log.error("%s exited with code %s during the run", p.name, code)


async def _watch_tokens(fabric: ZenohFabric, system: str, watch: Watch) -> None:
    with fabric.watch_liveliness(keys.pattern(system, keys.Kind.ALIVE)) as changes:
        async for change in changes:
            name = keys.parse(change.key).name
            was = watch.tokens.get(name)
            watch.tokens[name] = change.alive
            if not change.alive and was and not watch.stopping:
                watch.lost_tokens.append(
                    {"node": name, "at_s": watch.at(), "last_samples": watch.recent(name)}
                )
                log.error("liveliness token of %s withdrawn during the run", name)


async def _read_rejections(sub: Subscription, watch: Watch) -> None:
    async for sample in sub:
        try:
            env = _open_rejection(sample.payload)
        except DECODE_ERRORS:
            continue
        if env.type != Rejection.TYPE:
            continue
        rec: Rejection = env.body
        watch.last_record[rec.node] = time.time()
        kind = reason_kind(rec.reason)
        watch.rejections[(rec.node, kind)] += rec.count
        watch.examples.setdefault(kind, rec.reason[:500])
        watch.records += 1


async def _probe_once(
    fabric: ZenohFabric, key: str, payload: bytes, check: Callable[[Any], str]
) -> tuple[str, float]:
    t = time.perf_counter()
    try:
        replies = await fabric.query(key, payload, timeout=PROBE_TIMEOUT)
    except (QueryError, FabricError) as exc:
        return f"{type(exc).__name__}: {exc}", (time.perf_counter() - t) * 1000
    ms = (time.perf_counter() - t) * 1000
    if not replies:
        return "no reply", ms
    return check(replies[0]), ms


def _kb_check(reply: Any) -> str:
    if not reply.ok:
        return f"error reply: {reply.payload[:200]!r}"
    try:
        kb = _reply(reply.payload)
    except DECODE_ERRORS as exc:
        return f"undecodable reply: {decode_failure(exc)}"
    return "" if kb.ok else f"refused: {kb.code}: {kb.error[:200]}"


def _swap_check(reply: Any) -> str:
    # a malformed request must be refused with an error reply (or a failed status)
    return ""


async def _probe(
    fabric: ZenohFabric, system: str, kb_key: str, checkers: list[Proc], watch: Watch
) -> None:
    targets: list[tuple[str, str, bytes, Callable[[Any], str]]] = [
        ("knowledge", keys.kb(system, kb_key), _encode(KbGet(key=kb_key)), _kb_check)
    ]
    targets += [
        (c.name, keys.admin(system, c.name, "swap"), b"probe: not a spec update", _swap_check)
        for c in checkers
    ]
    for name, *_ in targets:
        watch.probes.setdefault(name, Probe())

    async def one(name: str, key: str, payload: bytes, check: Callable[[Any], str]) -> None:
        error, ms = await _probe_once(fabric, key, payload, check)
        watch.probes[name].record(error, ms)

    while True:
        async with anyio.create_task_group() as tg:
            for t in targets:
                tg.start_soon(one, *t)
        await anyio.sleep(PROBE_EVERY)  # the probe period (pacing, not waiting for an event)


# -- warm-up and closing the loop --------------------------------------------------------


async def _close_loop(
    fabric: ZenohFabric,
    system: str,
    robot: str,
    timeout: float,
    also: anyio.Event | None = None,
    *,
    diagnose: bool = False,
) -> dict[str, Any]:
    """Occluded scans every ``SCAN_EVERY`` s until a plan caused by one of them reaches
    the robot (then, within the same ``timeout``, until ``also`` is set); how many scans
    and seconds it took."""
    scan_key = keys.data(system, f"{robot}/scan")
    plan_key = keys.data(system, f"{robot}/spin_config")
    sealer = Sealer(ROBOT_SOURCE)
    ours: set[bytes] = set()
    got = anyio.Event()
    t = time.perf_counter()
    result: dict[str, Any] = {"closed": False, "scans": 0}
    trail: Counter[str] = Counter()
    ahead_by: dict[str, float] = {}
    errors: Counter[str] = Counter()
    prefix = f"rap/{system}/"
    with (
        fabric.subscribe(plan_key, _BIG_FIFO) as plans,
        fabric.subscribe(keys.system_pattern(system) if diagnose else plan_key, _BIG_FIFO) as all_,
    ):

        async def follow() -> None:
            """What our scans' cycles did: envelopes by key, stage errors."""
            async for sample in all_:
                try:
                    env = _open_any(sample.payload)
                    if env.cycle not in ours and env.uid not in ours:
                        continue
                    trail[sample.key.removeprefix(prefix)] += 1
                    if env.type == StageTrace.TYPE:
                        rec = msgspec.msgpack.decode(env.body, type=StageTrace)
                        if rec.ended and not rec.ok:
                            errors[f"{rec.node}: {reason_kind(rec.error)}"] += 1
                    for acc in _accesses(env):
                        # how far ahead of now the version read was (a version from the
                        # future shadows every genuine write until the clock gets there)
                        ahead = (acc.version >> 20) / 1000 + EPOCH_S - time.time()
                        k = f"{acc.op} {acc.key}"
                        ahead_by[k] = max(ahead_by.get(k, -1e9), round(ahead, 1))
                except DECODE_ERRORS:
                    continue

        async def wait_plans() -> None:
            async for sample in plans:
                try:
                    env = _open_any(sample.payload)
                except DECODE_ERRORS:
                    continue
                if env.cycle in ours:
                    result["plan_after_s"] = round(time.perf_counter() - t, 3)
                    got.set()
                    return

        async with anyio.create_task_group() as tg:
            tg.start_soon(wait_plans)
            if diagnose:
                tg.start_soon(follow)
            with anyio.move_on_after(timeout):
                i = 0
                while not got.is_set():
                    start, width = OCCLUSIONS[i % len(OCCLUSIONS)]
                    scan: LaserScan = occluded_scan(start, width, robot=robot)
                    payload, env = sealer.seal_message(scan_key, scan)
                    ours.add(env.uid)
                    await fabric.publish(scan_key, payload)
                    i += 1
                    result["scans"] = i
                    with anyio.move_on_after(SCAN_EVERY):  # the scan period
                        await got.wait()
                if also is not None:
                    await also.wait()
            tg.cancel_scope.cancel()
    result["closed"] = got.is_set() and (also is None or also.is_set())
    result["seconds"] = round(time.perf_counter() - t, 3)
    if diagnose:
        result["cycles_reached"] = dict(sorted(trail.items()))
        result["stage_errors"] = dict(errors.most_common(20))
        result["versions_ahead_s"] = dict(sorted(ahead_by.items()))
    return result


def _accesses(env: Any) -> list[KnowledgeAccess]:
    """The knowledge accesses a trace record tells of: those a ``StageTrace`` lists, or
    a ``KnowledgeAccess`` record itself."""
    if env.type == KnowledgeAccess.TYPE:
        return [msgspec.msgpack.decode(env.body, type=KnowledgeAccess)]
    if env.type != StageTrace.TYPE:
        return []
    rec = msgspec.msgpack.decode(env.body, type=StageTrace)
    return [
        KnowledgeAccess(
            node=rec.node, op=a.op, key=a.key, version=a.version, ts=a.ts, cycle=rec.cycle
        )
        for a in rec.access
    ]


async def _warm_up(
    fabric: ZenohFabric, system: str, robot: str, checkers: list[Proc]
) -> tuple[dict[str, Any], list[KnowledgeAccess], dict[str, bytes]]:
    """Close the loop once with every checker hearing it; the knowledge accesses of those
    cycles and the last value written to each key."""
    access: list[KnowledgeAccess] = []
    values: dict[str, bytes] = {}
    spoken: set[str] = set()
    want = {c.name for c in checkers}
    heard = anyio.Event()
    if not want:
        heard.set()
    with (
        fabric.subscribe(keys.pattern(system, keys.Kind.TRACE), _BIG_FIFO) as traces,
        fabric.subscribe(keys.pattern(system, keys.Kind.KB), _BIG_FIFO) as kb,
        fabric.subscribe(keys.pattern(system, keys.Kind.TRUST), _BIG_FIFO) as trust,
    ):

        async def read_traces() -> None:
            async for s in traces:
                try:
                    access.extend(_accesses(_open_trace(s.payload)))
                except DECODE_ERRORS:
                    continue

        async def read_kb() -> None:
            async for s in kb:
                try:
                    rec: KbRecord = _open_record(s.payload).body
                except DECODE_ERRORS:
                    continue
                if not rec.deleted:
                    values[rec.key] = bytes(rec.value)

        async def read_trust() -> None:
            async for s in trust:
                try:
                    spoken.add(_open_any(s.payload).source)
                except DECODE_ERRORS:
                    continue
                if want <= spoken:
                    heard.set()

        async with anyio.create_task_group() as tg:
            for fn in (read_traces, read_kb, read_trust):
                tg.start_soon(fn)
            result = await _close_loop(fabric, system, robot, WARMUP_TIMEOUT, also=heard)
            tg.cancel_scope.cancel()
    result["checkers_heard"] = sorted(spoken & want)
    return result, access, values


# -- the flood ---------------------------------------------------------------------------


class Feeder:
    """Makes the samples of every target."""

    def __init__(
        self,
        targets: list[Target],
        *,
        seed: int,
        nodes: list[Node],
        kb_keys: list[str],
        values: dict[str, bytes],
        specs: dict[str, str],
    ) -> None:
        self.nodes = [n.name for n in nodes]
        self.kb_keys = kb_keys
        self.values = values
        self.specs = specs
        sources = ["fuzzer", *self.nodes]
        self.mutators = {
            t.name: Mutator(t.name, seed, sealed=t.sealed, sources=sources, ctx_keys=kb_keys)
            for t in targets
        }
        self.pools: dict[str, list[tuple[str, Any]]] = {}
        self.last_ctx_never: dict[str, float] = {}
        self.unknown_types: set[str] = set()

    def _value(self, key: str) -> bytes:
        return self.values.get(key) or _encode({"fuzz": 1})

    def _body(self, t: Target, key: str, m: Mutator) -> tuple[str, Any]:
        kb_key = key.split("/kb/", 1)[1] if "/kb/" in key else ""
        wire = m.rng.choice([t.wire_type, *t.alt_types])
        body = valid_body(
            wire,
            m.rng,
            nodes=self.nodes,
            kb_keys=self.kb_keys,
            kb_key=kb_key,
            kb_value=self._value(kb_key),
        )
        if body is None:
            self.unknown_types.add(wire)
            body = {}
        return wire, body

    def sample(self, t: Target, key: str) -> tuple[str, bytes]:
        m = self.mutators[t.name]
        rng = m.rng
        locked = False
        if t.wire_type == REQUEST:
            kb_key = key.split("/kb/", 1)[1]
            valid = kb_request(rng, kb_key, self._value(kb_key))
        elif t.wire_type == TrustSpecUpdate.TYPE:
            checker = keys.parse(key).name.removeprefix("trust_")
            body, locked = spec_update(rng, self.specs.get(checker, ""))
            valid = m.envelope(key, t.wire_type, body)
        else:
            pool = self.pools.get(t.name)
            if pool is None:
                pool = self.pools[t.name] = [self._body(t, key, m) for _ in range(POOL)]
            i = rng.randrange(POOL)
            if rng.random() < 1 / 32:
                pool[i] = self._body(t, key, m)  # fresh times, versions, uids
            wire, body = pool[i]
            if wire == KbRecord.TYPE:  # a fresh version: the latest, as a writer's would be
                body = {**body, "version": _clock.next(), "ts": time.time_ns()}
            valid = m.envelope(key, wire, body)
        now = time.monotonic()
        allowed = now - self.last_ctx_never.get(t.name, -1e9) >= CTX_NEVER_EVERY
        name = m.choose(locked=locked, ctx_never=allowed and t.sealed)
        if name == "ctx_never":
            self.last_ctx_never[t.name] = now
        return name, m.mutate(name, valid)


def _send(t: Target, key: str, name: str, payload: bytes) -> None:
    t.sent += 1
    t.bytes += len(payload)
    t.by_mutation[name] += 1
    t.remember(time.time(), name, key, payload)


async def _puts_then_mark(
    watch: Watch, fabric: ZenohFabric, puts: list[Target], feeder: Feeder, opts: Options
) -> None:
    await _flood_puts(fabric, puts, feeder, opts.samples, opts.seconds)
    watch.puts_ended = time.time()


async def _flood_puts(
    fabric: ZenohFabric, targets: list[Target], feeder: Feeder, n: int, budget: float
) -> None:
    """Round-robin over the targets, one sample each per round, paced evenly so that
    ``n`` samples per target take ``budget`` s."""
    if not targets:
        return
    rate = n * len(targets) / budget
    start = anyio.current_time()
    deadline = start + budget * 1.5
    done = 0
    while min(t.sent for t in targets) < n:
        for t in targets:
            if t.sent >= n:
                continue
            key = t.keys[t.sent % len(t.keys)]
            name, payload = feeder.sample(t, key)
            try:
                await fabric.publish(key, payload)
            except FabricError as exc:
                t.replies[f"publish failed: {reason_kind(str(exc))}"] += 1
            _send(t, key, name, payload)
            done += 1
        now = anyio.current_time()
        if now > deadline:
            return
        due = start + done / rate
        await anyio.sleep(max(due - now, 0))  # pacing; 0 yields to the other tasks


async def _flood_queries(
    fabric: ZenohFabric, t: Target, feeder: Feeder, n: int, budget: float
) -> None:
    """``n`` queries to ``t``, ``QUERY_WORKERS`` in flight, paced evenly over ``budget``."""
    rate = n / budget
    start = anyio.current_time()
    deadline = start + budget * 1.5
    claimed = 0

    async def worker() -> None:
        nonlocal claimed
        while claimed < n:
            i = claimed
            claimed += 1
            due = start + i / rate
            now = anyio.current_time()
            if now > deadline:
                return
            if due > now:
                await anyio.sleep(due - now)  # pacing
            key = t.keys[i % len(t.keys)]
            name, payload = feeder.sample(t, key)
            _send(t, key, name, payload)
            try:
                replies = await fabric.query(key, payload, timeout=QUERY_TIMEOUT)
            except QueryError:
                t.replies["timeout"] += 1
                continue
            except FabricError as exc:
                t.replies[f"query failed: {reason_kind(str(exc))}"] += 1
                continue
            kind = _classify(t, replies)
            t.replies[kind] += 1
            if kind.startswith("undecodable reply"):
                t.oddity(kind, key, payload, replies[0].payload)

    async with anyio.create_task_group() as tg:
        for _ in range(QUERY_WORKERS):
            tg.start_soon(worker)


def _classify(t: Target, replies: list[Any]) -> str:
    if not replies:
        return "no reply"
    r = replies[0]
    if not r.ok:
        text = bytes(r.payload[:300]).decode(errors="replace")
        t.reply_details[reason_kind(text)[:120]] += 1
        return "error reply: " + text.split(":", 1)[0][:60]
    try:
        if t.wire_type == REQUEST:
            kb = _reply(r.payload)
            if not kb.ok:
                t.reply_details[reason_kind(kb.error)[:120]] += 1
            return "ok" if kb.ok else f"refused: {kb.code}"
        status: TrustSpecStatus = _open_status(r.payload).body
        return "swapped" if status.ok else "swap refused"
    except DECODE_ERRORS as exc:
        return f"undecodable reply: {reason_kind(decode_failure(exc))[:60]}"


# -- the run -----------------------------------------------------------------------------


async def run(opts: Options) -> dict[str, Any]:
    t0 = time.perf_counter()
    doc = await anyio.to_thread.run_sync(load_plan, opts.plan)
    system = opts.system or doc.plan.system
    shares = {
        cn: await anyio.to_thread.run_sync(load_share, doc, cn) for cn in doc.plan.compute_nodes
    }
    hosts = {n.name: f"runner-{cn}" for cn, sh in shares.items() for n in sh.nodes}
    nodes = [n for sh in shares.values() for n in sh.nodes]
    robot = next(
        r.name.split("/", 1)[0] for n in nodes for r in n.routes if r.name.endswith("/scan")
    )
    specs = await anyio.to_thread.run_sync(maplek_specs)
    unknown = sorted(set(opts.specs) - set(specs))
    if unknown:
        raise ValueError(f"unknown MAPLE-K spec(s) {unknown}; known: {sorted(specs)}")
    await anyio.Path(opts.logs).mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    watch = Watch()
    procs: list[Proc] = []
    report: dict[str, Any] = {
        "system": system,
        "plan": str(opts.plan),
        "seed": opts.seed,
        "samples_per_target": opts.samples,
        "seconds_budget": opts.seconds,
    }
    zconf = ZenohConfig(listen=[endpoint], congestion_control="block")
    async with ZenohFabric(zconf) as fabric:
        _say(f"starting the knowledge service and {len(shares)} runner(s)", t0)
        async with local_deployment(
            opts.plan, fabric=fabric, endpoint=endpoint, logs=opts.logs, system=system
        ) as dep:
            for name, proc in dep.processes.items():
                kind = "knowledge" if name == "knowledge" else "runner"
                procs.append(Proc(name, proc, opts.logs / f"{name}.log", kind))
            connect = [endpoint]
            for p in procs:
                connect += await procinfo.listen_endpoints(p.pid)
            _say(f"starting {len(opts.specs)} trust checker(s): {', '.join(opts.specs)}", t0)
            async with _checkers(
                [*opts.specs], system=system, connect=connect, logs=opts.logs, fabric=fabric
            ) as checkers:
                procs += checkers
                async with anyio.create_task_group() as tg:
                    for p in procs:
                        tg.start_soon(_watch_exit, p, watch)
                    tg.start_soon(_watch_tokens, fabric, system, watch)
                    report.update(
                        await _main(
                            fabric, tg, opts, system, robot, nodes, hosts, procs, checkers,
                            specs, watch, t0,
                        )
                    )  # fmt: skip
                    watch.stopping = True
                    tg.cancel_scope.cancel()
                _say("stopping the processes", t0)
        # every process has been stopped (SIGTERM, SIGKILL after a grace period)
    report["exit_codes"] = {p.name: p.process.returncode for p in procs}
    report["processes"], findings = await process_reports(
        procs, {p.name: p.process.returncode for p in procs}
    )
    report.update(_verdicts(report, watch, findings))
    report["wall_seconds"] = round(time.perf_counter() - t0, 1)
    return report


async def process_reports(
    procs: list[Proc], exit_codes: dict[str, int | None]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Per process: what the run saw of it (RSS, CPU, exit code) and what its log says;
    and the log findings by process name (for :func:`_verdicts`)."""
    out: dict[str, Any] = {}
    findings = {}
    for p in procs:
        f = await procinfo.read_log(str(p.log))
        findings[p.name] = f
        out[p.name] = {
            "kind": p.kind,
            "pid": p.pid,
            "log": str(p.log),
            "rss_before_kib": p.before.get("rss_kib"),
            "rss_after_kib": p.after.get("rss_kib"),
            "peak_rss_kib": p.after.get("hwm_kib"),
            "sampled_max_rss_kib": p.rss_max_kib,
            "sampled_max_rss_at_s": p.rss_max_at_s,
            "cpu_s": p.after.get("cpu_s"),
            "cpu_s_while_closing": (
                round(p.after["cpu_s"] - p.flood_end["cpu_s"], 2)
                if "cpu_s" in p.after and "cpu_s" in p.flood_end
                else None
            ),
            "exit_code": exit_codes.get(p.name),
            "log_findings": f.as_dict(),
        }
    return out, findings


async def _main(
    fabric: ZenohFabric,
    tg: TaskGroup,
    opts: Options,
    system: str,
    robot: str,
    nodes: list[Node],
    hosts: dict[str, str],
    procs: list[Proc],
    checkers: list[Proc],
    specs: dict[str, str],
    watch: Watch,
    t0: float,
) -> dict[str, Any]:
    out: dict[str, Any] = {}
    _say("warm-up: closing the loop once", t0)
    warm, access, values = await _warm_up(fabric, system, robot, checkers)
    out["warm_up"] = warm
    if not warm["closed"]:
        raise RuntimeError(
            f"the loop did not close before the flood ({warm}); see the logs in {opts.logs}"
        )
    targets = derive(
        system=system,
        nodes=nodes,
        hosts=hosts,
        kb_access=access,
        checkers=[c.name for c in checkers],
    )
    kb_keys = kb_keys_of(targets)
    feeder = Feeder(
        targets,
        seed=opts.seed,
        nodes=nodes,
        kb_keys=kb_keys,
        values=values,
        specs={
            c.name.removeprefix("trust_"): specs[c.name.removeprefix("trust_")] for c in checkers
        },
    )
    watch.recent = lambda who: {
        **_recent([t for t in targets if any(who in s for s in t.subscribers)], watch.t0, 1, 256),
        **_recent([t for t in targets if who in t.name], watch.t0, RECENT // 2, 1024),
    }
    probe_key = kb_keys[0] if kb_keys else "fuzz"
    tg.start_soon(_probe, fabric, system, probe_key, checkers, watch)
    log_sub = fabric.subscribe(keys.pattern(system, keys.Kind.LOG), _BIG_FIFO)
    tg.start_soon(_read_rejections, log_sub, watch)
    for p in procs:
        p.before = await procinfo.snapshot(p.pid)
    puts = [t for t in targets if t.kind == "put"]
    for t in puts:  # a publisher puts only once a remote subscriber matches: wait for it
        for key in t.keys:
            try:
                await fabric.wait_matched(key, timeout=10.0)
            except FabricError as exc:
                t.replies[f"no subscriber matched: {reason_kind(str(exc))}"] += 1
    queries = [t for t in targets if t.kind == "query"]
    _say(
        f"flood: {len(targets)} targets x {opts.samples} samples over {opts.seconds:g} s "
        f"({len(puts)} keys, {len(queries)} queryables)",
        t0,
    )
    flood_t = time.perf_counter()
    async with anyio.create_task_group() as outer:
        outer.start_soon(_progress, targets, opts.samples, t0)
        outer.start_soon(_sample_rss, procs, watch)
        async with anyio.create_task_group() as flood:
            flood.start_soon(_puts_then_mark, watch, fabric, puts, feeder, opts)
            for t in queries:
                flood.start_soon(_flood_queries, fabric, t, feeder, opts.samples, opts.seconds)
        outer.cancel_scope.cancel()
    out["flood_seconds"] = round(time.perf_counter() - flood_t, 1)
    _stalls(watch, nodes, hosts, time.time() - out["flood_seconds"])
    for p in procs:
        p.flood_end = await procinfo.snapshot(p.pid)
    _say(f"flood over in {out['flood_seconds']} s; closing the loop again", t0)
    out["after"] = await _close_loop(fabric, system, robot, opts.close_timeout, diagnose=True)
    _say(
        f"loop closed after {out['after']['seconds']} s ({out['after']['scans']} scans)"
        if out["after"]["closed"]
        else f"the loop did NOT close within {opts.close_timeout:g} s",
        t0,
    )
    # one last probe of every queryable, now that the flood is over
    final = {}
    for name, probe in watch.probes.items():
        kb = name == "knowledge"
        key = keys.kb(system, probe_key) if kb else keys.admin(system, name, "swap")
        payload = _encode(KbGet(key=probe_key)) if kb else b"probe"
        error, ms = await _probe_once(fabric, key, payload, _kb_check if kb else _swap_check)
        probe.record(error, ms)
        final[name] = error or "ok"
    out["final_probes"] = final
    for p in procs:
        p.after = await procinfo.snapshot(p.pid)
    out["fuzzer"] = await procinfo.snapshot(os.getpid())
    log_sub.close()
    out["targets"] = {t.name: t.summary() for t in targets}
    out["recent"] = _recent(targets, watch.t0, 4, 1024)
    out["unknown_wire_types"] = sorted(feeder.unknown_types)
    return out


def _stalls(watch: Watch, nodes: list[Node], hosts: dict[str, str], flood_start: float) -> None:
    """A node fed garbage publishes a rap.Rejection record every second (one per key per
    second): one silent for ``STALL_S`` at the end of the flood had stopped taking its
    samples (a hang, a deadlock)."""
    end = watch.puts_ended or time.time()  # the put flood may end before the queries'
    if end - flood_start < 2 * STALL_S:
        return  # too short a flood to tell
    for n in nodes:
        last = watch.last_record.get(n.name, flood_start)
        if end - last > STALL_S:
            watch.stalls.append(
                {
                    "node": n.name,
                    "process": hosts.get(n.name, "?"),
                    "silent_for_s": round(end - last, 1),
                    "last_record_at_s": round(last - watch.t0, 1)
                    if n.name in watch.last_record
                    else None,
                }
            )
            log.error(
                "%s published no rejection record in the last %.0f s of the flood",
                n.name,
                end - last,
            )


def _recent(targets: list[Target], t0: float, n: int = 8, head: int = 2048) -> dict[str, Any]:
    """The last ``n`` samples of each target: when (s into the run), which mutation, on
    which key, the payload's length and its first ``head`` bytes in hex."""
    return {
        t.name: [
            {
                "at_s": round(at - t0, 3),
                "mutation": m,
                "key": k,
                "len": len(pl),
                "hex": pl[:head].hex(),
            }
            for at, m, k, pl in list(t.recent)[-n:]
        ]
        for t in targets
    }


async def _sample_rss(procs: list[Proc], watch: Watch) -> None:
    while True:
        for p in procs:
            if p.process.returncode is None:
                snap = await procinfo.snapshot(p.pid)
                if snap.get("rss_kib", 0) > p.rss_max_kib:
                    p.rss_max_kib, p.rss_max_at_s = snap["rss_kib"], watch.at()
        await anyio.sleep(RSS_EVERY)  # the sampling period


async def _progress(targets: list[Target], n: int, t0: float) -> None:
    total = n * len(targets)
    while True:
        await anyio.sleep(10)  # a progress line every 10 s
        sent = sum(min(t.sent, n) for t in targets)
        _say(f"  {sent:,} / {total:,} samples ({100 * sent / total:.0f} %)", t0)


def _verdicts(report: dict[str, Any], watch: Watch, findings: dict[str, Any]) -> dict[str, Any]:
    crashes: list[dict[str, Any]] = [{"what": "process exited", **e} for e in watch.exits]
    crashes += [{"what": "liveliness token withdrawn", **lt} for lt in watch.lost_tokens]
    crashes += [
        {"what": "stopped answering (no rejection records while fed garbage)", **st}
        for st in watch.stalls
    ]
    exited = {e["process"] for e in watch.exits}
    for name, probe in watch.probes.items():
        final = report.get("final_probes", {}).get(name, "ok")
        if name in exited:
            continue  # reported as exited
        if final != "ok" or probe.worst_in_a_row >= PROBE_FAILS:
            crashes.append(
                {
                    "what": "stopped answering",
                    "process": name,
                    "final_probe": final,
                    "probes_failed": probe.failed,
                    "worst_in_a_row": probe.worst_in_a_row,
                    "last_error": probe.last_error,
                }
            )
    for c in crashes:
        # the tracebacks of a process that exited or whose queryable stopped answering
        # (a hung node's process logs its handlers' failures, which are not the cause)
        f = findings.get(c.get("process", "")) if "node" not in c else None
        if f is not None and f.tracebacks:
            c["tracebacks"] = f.tracebacks
    by_reason: Counter[str] = Counter()
    by_reader: Counter[str] = Counter()
    for (node, kind), n in watch.rejections.items():
        by_reason[kind] += n
        by_reader[node] += n
    from_logs: Counter[tuple[str, str]] = Counter()
    publishers = {node for node, _ in watch.rejections}
    for f in findings.values():
        for (who, kind), n in f.rejected.items():
            if who not in publishers:
                from_logs[(who, kind)] += n
    targets = report.get("targets", {})
    sent = {k: v["sent"] for k, v in targets.items()}
    n = report["samples_per_target"]
    return {
        "crashes": crashes,
        "loop_closed_after": bool(report.get("after", {}).get("closed")),
        "target_reached": bool(sent) and min(sent.values()) >= n,
        "samples_total": sum(sent.values()),
        "rejections": {
            "records": watch.records,
            "by_reason": dict(by_reason.most_common()),
            "by_reader": dict(by_reader.most_common()),
            "examples": watch.examples,
            "by_reader_and_reason": [
                {"reader": r, "reason": k, "count": c}
                for (r, k), c in watch.rejections.most_common()
            ],
            "from_logs": [
                {"who": w, "reason": k, "count": c} for (w, k), c in from_logs.most_common()
            ],
        },
        "probes": {k: vars(v) for k, v in watch.probes.items()},
        "tokens_at_end": watch.tokens,
    }
