"""``python -m rap_cli.router --config FILE``: a compute node's Zenoh router.

Every process of a compute node is a Zenoh client of its node's router; the routers link
the nodes (``rap_cli.deploy``). The router opens one Zenoh session in router mode from
the JSON5 file (``rap up`` and the generated compose files write it), logs where it
listens and every link to another session that comes up, is lost or is restored, and
runs until SIGTERM or SIGINT.

Exit codes: 0 stopped by a signal, 1 the session could not open (an endpoint taken, say),
2 an unusable config file.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import select
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import anyio
import typer
import zenoh
from rap_sdk.entry import fail, run_cli, setup_logging

__all__ = ["READY", "DenialLog", "cli", "main", "watch_denials"]

READY = "listening on"
"""What the router logs once its listeners are bound (``rap up`` waits for it)."""

cli = typer.Typer(add_completion=False, help=__doc__, rich_markup_mode=None)
log = logging.getLogger("rap.router")


@cli.command()
def main(
    config: Annotated[
        Path,
        typer.Option(
            "--config",
            help="The router's Zenoh config (JSON5), as rap up or rap generate wrote it.",
        ),
    ],
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
) -> None:
    """Run a compute node's Zenoh router until SIGTERM or SIGINT."""
    _own_runtime()
    setup_logging(log_level)
    conf = load_config(config)
    if _json(conf, "access_control/enabled") is True and RUST_LOG not in os.environ:
        watch_denials()
        zenoh.init_log_from_env_or(ACL_TRACE)
    else:
        zenoh.try_init_log_from_env()
    anyio.run(_serve, conf, str(config))


_RUNTIME_ENV = "ZENOH_RUNTIME"


def _own_runtime() -> None:
    """Give the router Zenoh's own thread pools, not the one-thread runtime of RAP's other
    processes (``rap_sdk.ZenohConfig.runtime``), which a router started by one of them
    inherits (``ZENOH_RUNTIME``). A router forwards on the thread that reads a link; with
    that one thread also sending, nothing drains a link's send queue while it forwards a
    message bigger than the queue (256 KiB is): the message is dropped, or, with
    congestion control ``block``, the link stalls. Another runtime set there is kept."""
    from rap_sdk.fabric import ZenohConfig

    if os.environ.get(_RUNTIME_ENV) == ZenohConfig().runtime:
        del os.environ[_RUNTIME_ENV]


# -- what access control refuses -----------------------------------------------------------

RUST_LOG = "RUST_LOG"
ACL_TRACE = "warn,zenoh::net::routing::interceptor::access_control=trace"
"""Zenoh's own log filter with access control on: its checks are traced (only there does
Zenoh say what it refuses, and from whom); :class:`DenialLog` keeps the refusals."""
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_CHECK = re.compile(
    r"(?P<cached>Using cached result: )?(?P<zid>[0-9a-f]+)(?: on (?P<link>\S+))?\s+is "
    r"(?P<verdict>authorized|unauthorized) to (?P<action>.+?) \((?P<flow>ingress|egress)\) "
    r"on (?P<key>\S+)"
)
_CN = re.compile(r"CertCommonName\((?P<cn>[^)]*)\)")
_CACHED, _PASSED = b"Using cached result: ", b" is authorized to "
"""What the trace of a message let through has (skipped before any decoding: a router
relaying thousands of messages a second writes a line for each)."""


@dataclass
class DenialLog:
    """Turns Zenoh's access-control trace into one log line per refusal, naming the
    identity (the certificate's common name) that sent it; repeats of the same refusal
    are counted and told at most every ``every`` seconds.

    Zenoh checks every kind of message at once for a key a peer declares (a burst of
    checks on one key, most of them never used): such a burst is not a refusal. A
    refusal is a check of one message: a cached result, or a lone check."""

    every: float = 10.0
    burst: float = 0.1
    """Checks of one peer and key within this many seconds are one burst."""
    names: dict[str, str] = field(default_factory=dict)
    """Zenoh id -> identity."""
    pending: dict[tuple[str, str], tuple[float, set[str], list[tuple[str, str]]]] = field(
        default_factory=dict
    )
    told: dict[tuple[str, str, str], tuple[float, int]] = field(default_factory=dict)
    refused: int = 0

    def feed(self, line: str, now: float) -> bool:
        """Take one line of Zenoh's log; False when it is not an access-control check."""
        m = _CHECK.search(_ANSI.sub("", line))
        if m is None:
            return False
        zid, key, action = m["zid"], m["key"], m["action"]
        if m["link"]:
            cn = _CN.search(m["link"])
            self.names[zid] = cn["cn"] if cn else "unauthenticated"
        if m["cached"]:
            if m["verdict"] == "unauthorized":
                self._refused(zid, action, m["flow"], key, now)
            return True
        _at, actions, denied = self.pending.setdefault((zid, key), (now, set(), []))
        actions.add(action)
        if m["verdict"] == "unauthorized":
            denied.append((action, m["flow"]))
        return True

    def flush(self, now: float) -> None:
        """Tell the refusals of checks older than a burst."""
        for (zid, key), (at, actions, denied) in list(self.pending.items()):
            if now - at < self.burst:
                continue
            del self.pending[(zid, key)]
            if len(actions) < 3:  # not a declaration's burst
                for action, flow in denied:
                    self._refused(zid, action, flow, key, now)

    def _refused(self, zid: str, action: str, flow: str, key: str, now: float) -> None:
        self.refused += 1
        who = self.names.get(zid, f"zenoh id {zid}")
        what = (who, action, key)
        last, count = self.told.get(what, (-self.every, 0))
        if now - last < self.every:
            self.told[what] = (last, count + 1)
            return
        more = f" ({count} more since the last line)" if count else ""
        log.warning("refused: %s may not %s (%s) on %s%s", who, action.lower(), flow, key, more)
        self.told[what] = (now, 0)


def watch_denials() -> DenialLog:
    """Read Zenoh's log (its standard output) in a thread: access-control checks go to
    a :class:`DenialLog`, anything else on to the real standard output."""
    denials = DenialLog()
    read, write = os.pipe()
    out = os.dup(1)
    os.dup2(write, 1)
    os.close(write)

    def pump() -> None:
        with os.fdopen(read, "rb", buffering=0) as pipe, os.fdopen(out, "wb") as real:
            buf = b""
            while True:
                ready, _, _ = select.select([pipe], [], [], denials.burst)
                now = time.monotonic()
                if ready:
                    chunk = pipe.read(65536)
                    if not chunk:
                        return
                    buf += chunk
                    *lines, buf = buf.split(b"\n")
                    for raw in lines:
                        if _PASSED in raw and _CACHED in raw:
                            continue  # a message let through: one such line per message
                        if not denials.feed(raw.decode("utf-8", "replace"), now):
                            real.write(raw + b"\n")
                            real.flush()
                denials.flush(now)

    threading.Thread(target=pump, name="acl-log", daemon=True).start()
    return denials


def load_config(path: Path) -> zenoh.Config:
    """The router's Zenoh config from ``path``, in router mode; raises ``EntryError``."""
    if not path.is_file():
        raise fail(
            f"{path}: no such file - give the router config that rap up wrote "
            "(<run-dir>/<node>/zenoh-router.json5)"
        )
    try:
        conf = zenoh.Config.from_file(str(path))
        mode = _json(conf, "mode")
        if mode not in (None, "router"):
            raise fail(f"{path}: mode is {mode!r} - a router config says mode: 'router'")
        conf.insert_json5("mode", '"router"')
    except zenoh.ZError as exc:
        raise fail(
            f"{path}: not a usable Zenoh config ({_one_line(exc)}) - fix it, or run rap up "
            "again to rewrite it"
        ) from None
    return conf


def _json(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except (zenoh.ZError, ValueError, TypeError):
        return None


def _endpoints(conf: zenoh.Config, key: str) -> list[str]:
    value = _json(conf, key)
    if isinstance(value, list):
        return [str(v) for v in value]
    if isinstance(value, dict):  # per-mode lists: { router: [...], peer: [...] }
        router = value.get("router", [])
        return [str(v) for v in router] if isinstance(router, list) else []
    return []


def _one_line(exc: BaseException) -> str:
    """Zenoh's error message on one line, without the Rust source locations."""
    return " ".join(_SOURCE.sub("", str(exc)).split())


_SOURCE = re.compile(r"\s+at\s+/\S+\.rs:\d+\.?")


@dataclass
class LinkLog:
    """Logs links to other sessions: the first one to a Zenoh id is ``up``, a later one
    ``restored``; a closed one ``lost``."""

    linked: dict[str, str] = field(default_factory=dict)
    """Zenoh id -> what it is (router, peer, client), for the links up now."""
    seen: set[str] = field(default_factory=set)

    def change(self, zid: str, what: str, up: bool) -> None:
        if up:
            if zid in self.linked:
                return
            self.linked[zid] = what
            again = zid in self.seen
            self.seen.add(zid)
            log.info(
                "link to %s %s (%s; %d link(s) up)",
                zid,
                "restored" if again else "up",
                what,
                len(self.linked),
            )
            return
        what = self.linked.pop(zid, what)
        (log.warning if what == "router" else log.info)(
            "link to %s lost (%s; %d link(s) left)", zid, what, len(self.linked)
        )


async def _serve(conf: zenoh.Config, source: str) -> None:
    listen = _endpoints(conf, "listen/endpoints")
    connect = _endpoints(conf, "connect/endpoints")
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        try:
            session = await anyio.to_thread.run_sync(zenoh.open, conf)
        except zenoh.ZError as exc:
            raise fail(
                f"{source}: the router cannot open its Zenoh session: {_one_line(exc)} - "
                "check its listen endpoints: each must be an address of this machine that "
                "no other process listens on",
                1,
            ) from None
        links = LinkLog()
        loop = asyncio.get_running_loop()
        put = zenoh.SampleKind.PUT

        def on_event(event: zenoh.TransportEvent) -> None:  # a Zenoh thread: hand over
            change = (str(event.transport.zid), str(event.transport.whatami), event.kind == put)
            _hand_over(loop, links.change, change)

        listener = session.info.declare_transport_events_listener(on_event, history=True)
        try:
            log.info(
                "router %s %s %s; connecting to %s",
                session.info.zid(),
                READY,
                ", ".join(listen) or "(nothing)",
                ", ".join(connect) or "(nothing)",
            )
            async for signum in signals:
                log.info("received %s; stopping", signal.Signals(signum).name)
                break
        finally:
            listener.undeclare()
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(session.close)
    log.info("router stopped")


def _hand_over(
    loop: asyncio.AbstractEventLoop,
    fn: Callable[[str, str, bool], None],
    args: tuple[str, str, bool],
) -> None:
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:  # the loop has closed: the router is stopping
        pass


if __name__ == "__main__":
    run_cli(cli)
