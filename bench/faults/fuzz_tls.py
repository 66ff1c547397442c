"""Scenario 5: bench/fuzz's mutated samples at every subscriber of the lidar loop, over
mutual TLS, as an operator.

The model copy says ``fabric: {tls: true, operators: [fuzzer]}`` and leaves the
simulator out (the fuzzer plays the robot, as in ``make fuzz``); ``rap certs`` makes the
CA and every identity's certificate, and ``rap up --all`` runs both compute nodes, their
routers linked over TLS. The fuzzer is a Zenoh client of the edge's router on its
``tls/`` endpoint, presenting the operator certificate ``fuzzer`` (as ``rap status --as
fuzzer`` would): everything it sends crosses a TLS link, and what goes to the robot's
processes crosses the routers' link too.

The run is bench/fuzz's (its targets, mutations, warm-up, probes, rejection counting
and verdicts are reused), with the processes of ``rap up`` in place of the fuzz run's
own: a process that exits (``rap up`` restarts it: its ``restarts`` in ``up.json``), a
liveliness token withdrawn, a knowledge queryable that stops answering, or a node that
stops taking samples is a crash. The targets add what the adaptation manager reads
besides the loop's keys: trust outputs (``trust/fuzz``) and log records
(``log/fuzz``: ``rap.Rejection`` and ``rap.LogRecord``)."""

from __future__ import annotations

import json
import os
import random
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, cast

import anyio
from anyio.abc import Process, TaskGroup
from maplek_runner.loading import load_share
from rap_cli.deploy import TlsFiles, client_config
from rap_schemas import KbGet, LogRecord, Rejection, TrustOutput, keys, load_plan
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.fabric import Subscription

from ..fuzz import procinfo
from ..fuzz.mutate import Mutator
from ..fuzz.run import (
    _BIG_FIFO,
    Feeder,
    Options,
    Proc,
    Watch,
    _close_loop,
    _encode,
    _flood_puts,
    _flood_queries,
    _kb_check,
    _probe,
    _probe_once,
    _progress,
    _read_rejections,
    _recent,
    _stalls,
    _verdicts,
    _warm_up,
    _watch_tokens,
    process_reports,
)
from ..fuzz.samples import plain, valid_body
from ..fuzz.targets import Target, derive, kb_keys_of
from .common import SYSTEM, RapUp, ScenarioError, rap_command, rap_up, say, write_model

__all__ = ["run_fuzz_tls"]

OPERATOR = "fuzzer"
CLOSE_TIMEOUT = 120.0
ROBOT = "tb1"
LOG_KEY = keys.log(SYSTEM, "fuzz")
"""Where the fuzzed log records go: a key of its own, left out when the nodes' real
rejection records are counted (they name nodes, whose silence tells a stall)."""


class _Child:
    """A process of ``rap up`` seen as the fuzz run's ``Process``: its pid, and no exit
    code while that pid lives (``rap up`` restarts a child that exits: a new pid)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def refresh(self) -> None:
        if self.returncode is None and not os.path.exists(f"/proc/{self.pid}"):
            self.returncode = -1


def _router_conf(run: Path, node: str) -> dict[str, Any]:
    text = (run / node / "zenoh-router.json5").read_text()
    conf = json.loads("\n".join(x for x in text.splitlines() if not x.lstrip().startswith("//")))
    return cast(dict[str, Any], conf)


def _acl_on(run: Path) -> dict[str, bool]:
    """Per router: whether its config enforces access control (deny by default) and
    listens on tls/ endpoints only - what the run claims, read from what rap up wrote."""
    out = {}
    for node in ("robot", "edge"):
        conf = _router_conf(run, node)
        acl = conf.get("access_control", {})
        tls_only = all(str(e).startswith("tls/") for e in conf["listen"]["endpoints"])
        out[node] = bool(acl.get("enabled")) and acl.get("default_permission") == "deny"
        out[node] = out[node] and tls_only
    return out


def _tls_endpoint(run: Path) -> str:
    conf = _router_conf(run, "edge")
    for ep in conf["listen"]["endpoints"]:
        if str(ep).startswith("tls/"):
            return str(ep)
    raise ScenarioError(f"{run}/edge: the edge's router listens on no tls/ endpoint")


class TlsFeeder(Feeder):
    """bench/fuzz's feeder, with valid log records besides its own types."""

    def _body(self, t: Target, key: str, m: Mutator) -> tuple[str, Any]:
        if t.wire_type in (Rejection.TYPE, LogRecord.TYPE):
            wire = m.rng.choice([t.wire_type, *t.alt_types])
            return wire, plain(_log_body(wire, m.rng, self.nodes))
        return super()._body(t, key, m)


def _log_body(wire: str, rng: random.Random, nodes: list[str]) -> Rejection | LogRecord:
    node = rng.choice(nodes)
    if wire == Rejection.TYPE:
        return Rejection(
            node=node,
            key=keys.event(SYSTEM, "new-data"),
            reason="invalid envelope: fuzz",
            ts=time.time_ns(),
            count=rng.randrange(1, 100),
        )
    return LogRecord(
        ts=time.time_ns(),
        level=rng.choice(["INFO", "WARNING", "ERROR"]),
        logger="rap_sdk.runtime",
        message=f"{node}: a fuzzed log line",
        system=SYSTEM,
        compute_node="edge",
        process="runner",
        component=node,
    )


def _more_targets(nodes: list[str]) -> list[Target]:
    """What the adaptation manager reads besides the loop's keys."""
    assert valid_body(TrustOutput.TYPE, random.Random(0), nodes=nodes, kb_keys=[]) is not None
    return [
        Target("trust/fuzz", "put", [keys.trust(SYSTEM, "fuzz")], TrustOutput.TYPE, ["manager"]),
        Target(
            "log/fuzz",
            "put",
            [LOG_KEY],
            Rejection.TYPE,
            ["manager"],
            alt_types=[LogRecord.TYPE],
        ),
    ]


class _Without:
    """A subscription's samples, less those on one key (the fuzzer's own)."""

    def __init__(self, sub: Any, key: str) -> None:
        self.sub = sub
        self.key = key

    def __aiter__(self) -> AsyncIterator[Any]:
        return self._items()

    async def _items(self) -> AsyncIterator[Any]:
        async for sample in self.sub:
            if sample.key != self.key:
                yield sample


async def _watch_children(up: RapUp, watch: Watch) -> None:
    """A child of rap up that exited (rap up restarted it) is a crash."""
    seen: dict[str, tuple[int, Any]] = {}
    while True:
        for node in up.nodes:
            for c in up.state(node)["children"]:
                name = f"{node}/{c['name']}"
                now = (int(c["restarts"]), c["pid"])
                was = seen.get(name)
                if was is not None and now[0] > was[0] and not watch.stopping:
                    watch.exits.append(
                        {
                            "process": name,
                            "code": c["last_exit"],
                            "at_s": watch.at(),
                            "restarts": now[0],
                            "last_samples": watch.recent(name),
                        }
                    )
                    say(f"  CRASH: {name} exited with {c['last_exit']} (rap up restarted it)")
                seen[name] = now
        await anyio.sleep(1.0)  # up.json is rewritten on every change


async def _sample_rss(procs: list[Proc], watch: Watch) -> None:
    while True:
        for p in procs:
            child = cast(_Child, p.process)
            child.refresh()
            if child.returncode is None:
                snap = await procinfo.snapshot(p.pid)
                if snap.get("rss_kib", 0) > p.rss_max_kib:
                    p.rss_max_kib, p.rss_max_at_s = snap["rss_kib"], watch.at()
        await anyio.sleep(1.0)  # the sampling period


async def _flood(
    fabric: ZenohFabric,
    tg: TaskGroup,
    opts: Options,
    nodes: list[Any],
    hosts: dict[str, str],
    procs: list[Proc],
    watch: Watch,
) -> dict[str, Any]:
    """bench/fuzz's main phase (run.py's ``_main``), with the extra targets."""
    out: dict[str, Any] = {}
    say("  warm-up: closing the loop once (the fuzzer's own scans)")
    warm, access, values = await _warm_up(fabric, SYSTEM, ROBOT, [])
    out["warm_up"] = warm
    if not warm["closed"]:
        raise ScenarioError(f"the loop did not close before the flood over TLS: {warm}")
    targets = derive(system=SYSTEM, nodes=nodes, hosts=hosts, kb_access=access, checkers=[])
    targets += _more_targets([n.name for n in nodes])
    kb_keys = kb_keys_of(targets)
    feeder = TlsFeeder(
        targets, seed=opts.seed, nodes=nodes, kb_keys=kb_keys, values=values, specs={}
    )
    watch.recent = lambda who: _recent(
        [t for t in targets if any(who.split("/")[-1] in s for s in t.subscribers)],
        watch.t0,
        1,
        256,
    )
    probe_key = kb_keys[0] if kb_keys else "fuzz"
    tg.start_soon(_probe, fabric, SYSTEM, probe_key, [], watch)
    log_sub = fabric.subscribe(keys.pattern(SYSTEM, keys.Kind.LOG), _BIG_FIFO)
    tg.start_soon(_read_rejections, cast(Subscription, _Without(log_sub, LOG_KEY)), watch)
    for p in procs:
        p.before = await procinfo.snapshot(p.pid)
    puts = [t for t in targets if t.kind == "put"]
    for t in puts:  # a publisher puts only once a remote subscriber matches
        for key in t.keys:
            try:
                await fabric.wait_matched(key, timeout=10.0)
            except Exception as exc:  # reported with the target; the run goes on
                t.replies[f"no subscriber matched: {type(exc).__name__}"] += 1
    queries = [t for t in targets if t.kind == "query"]
    say(
        f"  flood over TLS: {len(targets)} targets x {opts.samples:,} samples within "
        f"{opts.seconds:g} s"
    )
    flood_t = time.perf_counter()
    async with anyio.create_task_group() as outer:
        outer.start_soon(_progress, targets, opts.samples, flood_t)
        outer.start_soon(_sample_rss, procs, watch)
        async with anyio.create_task_group() as flood:

            async def puts_then_mark() -> None:
                await _flood_puts(fabric, puts, feeder, opts.samples, opts.seconds)
                watch.puts_ended = time.time()

            flood.start_soon(puts_then_mark)
            for t in queries:
                flood.start_soon(_flood_queries, fabric, t, feeder, opts.samples, opts.seconds)
        outer.cancel_scope.cancel()
    out["flood_seconds"] = round(time.perf_counter() - flood_t, 1)
    _stalls(watch, nodes, hosts, time.time() - out["flood_seconds"])
    for p in procs:
        p.flood_end = await procinfo.snapshot(p.pid)
    say(f"  flood over in {out['flood_seconds']} s; closing the loop again")
    out["after"] = await _close_loop(fabric, SYSTEM, ROBOT, opts.close_timeout, diagnose=True)
    say(
        f"  loop closed again after {out['after']['seconds']} s"
        if out["after"]["closed"]
        else f"  the loop did NOT close within {opts.close_timeout:g} s"
    )
    final = {}
    for name, probe in watch.probes.items():
        error, ms = await _probe_once(
            fabric, keys.kb(SYSTEM, probe_key), _encode(KbGet(key=probe_key)), _kb_check
        )
        probe.record(error, ms)
        final[name] = error or "ok"
    out["final_probes"] = final
    for p in procs:
        p.after = await procinfo.snapshot(p.pid)
    log_sub.close()
    out["targets"] = {t.name: t.summary() for t in targets}
    out["recent"] = _recent(targets, watch.t0, 4, 1024)
    out["unknown_wire_types"] = sorted(feeder.unknown_types)
    return out


async def run_fuzz_tls(
    folder: Path, *, samples: int, seconds: float, seed: int = 1
) -> dict[str, Any]:
    say(f"fuzz over TLS: {samples:,} samples per target within {seconds:g} s")
    t0 = time.perf_counter()
    model = write_model(folder, simulator=False, tls_operators=[OPERATOR])
    made = await anyio.run_process(
        [rap_command(), "certs", str(model)], check=False, stderr=subprocess.STDOUT
    )
    if made.returncode != 0:
        raise ScenarioError(f"rap certs {model} failed: {made.stdout.decode()}")
    certs = folder / "certs"
    files = TlsFiles.of(certs, OPERATOR)
    if files.missing():
        raise ScenarioError(f"rap certs made no certificate for {OPERATOR}: {files.missing()}")
    doc = await anyio.to_thread.run_sync(load_plan, model)
    shares = {cn: await anyio.to_thread.run_sync(load_share, doc, cn) for cn in ("robot", "edge")}
    hosts = {n.name: f"{cn}/runner" for cn, sh in shares.items() for n in sh.nodes}
    nodes = [n for sh in shares.values() for n in sh.nodes]
    opts = Options(
        plan=model,
        seconds=seconds,
        samples=samples,
        seed=seed,
        specs=[],
        logs=folder / "run",
        close_timeout=CLOSE_TIMEOUT,
    )
    watch = Watch()
    report: dict[str, Any] = {
        "system": SYSTEM,
        "tls": True,
        "operator": OPERATOR,
        "seed": seed,
        "samples_per_target": samples,
        "seconds_budget": seconds,
    }
    procs: list[Proc] = []
    async with rap_up(model, folder / "run") as up:
        endpoint = _tls_endpoint(folder / "run")
        report["endpoint"] = endpoint
        report["acl_and_tls_only"] = _acl_on(folder / "run")
        if not all(report["acl_and_tls_only"].values()):
            raise ScenarioError(
                f"the routers do not all enforce access control over TLS only: "
                f"{report['acl_and_tls_only']}"
            )
        for node in up.nodes:
            for c in up.state(node)["children"]:
                if c["pid"] is None:
                    raise ScenarioError(f"{node}/{c['name']} is not running: {c}")
                kind = "runner" if c["name"] == "runner" else str(c["role"])
                procs.append(
                    Proc(
                        f"{node}/{c['name']}",
                        cast(Process, _Child(int(c["pid"]))),
                        Path(c["log"]),
                        kind,
                    )
                )
        transport = client_config("", files)["transport"]
        conf = ZenohConfig(
            mode="client",
            listen=[],
            connect=[endpoint],
            congestion_control="block",
            extra={"transport": transport},
        )
        say(f"  the fuzzer connects to {endpoint} as operator {OPERATOR!r} (mutual TLS)")
        async with ZenohFabric(conf) as fabric, anyio.create_task_group() as tg:
            tg.start_soon(_watch_tokens, fabric, SYSTEM, watch)
            tg.start_soon(_watch_children, up, watch)
            report.update(await _flood(fabric, tg, opts, nodes, hosts, procs, watch))
            watch.stopping = True
            tg.cancel_scope.cancel()
        say("  stopping rap up")
    # rap down has stopped every process: their logs hold the stop summaries
    exits = {
        f"{node}/{c['name']}": c["last_exit"]
        for node in up.nodes
        for c in up.state(node)["children"]
    }
    report["processes"], findings = await process_reports(procs, exits)
    report.update(_verdicts(report, watch, findings))
    report["wall_seconds"] = round(time.perf_counter() - t0, 1)
    report["ok"] = (
        not report["crashes"] and report["loop_closed_after"] and report["target_reached"]
    )
    say(
        f"  fuzz over TLS: {report['samples_total']:,} samples, "
        f"{len(report['crashes'])} crash(es), loop closed after: {report['loop_closed_after']}"
    )
    return report
