"""Scenario 6: what a compute node's router keeps of peers that sent ~1 MiB samples and
were killed mid-stream.

A router runs as ``rap up`` runs it (``python -m rap_cli.router`` with the config
``rap_cli.deploy.router_config`` makes for a one-node model with ``fabric:
{max_sample_bytes: 4194304}``, the 4 MiB RAP's subscribers take). A receiver process
subscribes to it (``python -m bench.faults.memory receive CONFIG N``, a client built from
the node's client config, as ``rap up``'s processes are). Then, one after the other,
``peers`` publisher processes (``python -m bench.faults.memory publish CONFIG INDEX
SIZE``, clients of the same config) each publish 1 MiB samples as fast as the link takes
them until the receiver has had ``SAMPLES`` of theirs, and get SIGKILL while still
publishing. After each kill, once the router logged the link lost, its RSS is read from
/proc (``VmRSS``, and its anonymous and shared-memory parts, ``RssAnon`` and
``RssShmem``); once more ``settle`` s after the last.

Four router (and client) configs, each with a router of its own, in the same run:

- ``zenoh``: the config without the two settings below, i.e. Zenoh's own defaults (a
  link takes messages up to 1 GiB; shared memory between processes of one machine), as
  RAP wrote it before the model had a limit;
- ``limit``: the model's limit (``transport.link.rx.max_message_size``), shared memory on;
- ``no-shm``: shared memory off, Zenoh's 1 GiB limit;
- ``rap``: what ``rap up`` and ``rap generate`` write now: the limit, shared memory off.

Retained per disconnected peer: the router's RSS after the last kill minus after the
first, over ``peers - 1`` (the first peer's share includes what a router allocates once:
thread stacks, buffers). Target: with ``rap``'s config, at most ``TARGET_MIB`` per peer.
"""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import anyio
import anyio.lowlevel
from rap_cli.deploy import client_config, render_zenoh, router_config
from rap_schemas import parse_plan
from rap_schemas.limits import MESSAGE_HEADROOM
from rap_sdk import InboxPolicy, Overflow, ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port, node_overlay
from rap_sdk.testing import stop_process

from ..report import ROOT
from .common import Lines, ScenarioError, say

__all__ = ["TARGET_MIB", "VARIANTS", "run_memory"]

LIMIT = 4 << 20
MODEL = f"""\
system: memory
compute_nodes:
  edge: {{}}
fabric:
  max_sample_bytes: {LIMIT}
"""
KEY = "rap/memory/data/big"
SAMPLE_BYTES = 1 << 20
SAMPLES = 20
"""Samples of each peer this process receives before the peer is killed."""
TARGET_MIB = 2.0
VARIANTS: dict[str, tuple[bool, bool, str]] = {
    # name: (the model's limit, shared memory, what it is)
    "zenoh": (False, True, "Zenoh's defaults (before)"),
    "limit": (True, True, "the model's limit alone"),
    "no-shm": (False, False, "shared memory off alone"),
    "rap": (True, False, "rap up / rap generate now"),
}


# -- the publishers and the receiver (processes of their own) ------------------------------


def _session(config: Path) -> ZenohFabric:
    """A session as ``rap up``'s processes open theirs (``RAP_ZENOH_CONFIG``)."""
    text = config.read_text(encoding="utf-8")
    return ZenohFabric(node_overlay(ZenohConfig(), text, source=str(config)))


def _say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


async def publish(config: Path, index: int, size: int) -> None:
    """Publish ``size``-byte samples (the first byte: ``index``) until killed."""
    payload = bytes([index % 256]) * size
    async with _session(config) as fabric:
        await fabric.wait_matched(KEY, timeout=30)
        _say("ready")
        while True:
            await fabric.publish(KEY, payload)
            await anyio.lowlevel.checkpoint()


async def receive(config: Path, samples: int) -> None:
    """Say ``got INDEX`` once ``samples`` samples of publisher INDEX arrived."""
    counts: dict[int, int] = {}
    async with _session(config) as fabric:
        sub = fabric.subscribe(KEY, InboxPolicy(capacity=16, overflow=Overflow.FIFO))
        _say("ready")
        async for sample in sub:
            i = sample.payload[0]
            counts[i] = n = counts.get(i, 0) + 1
            if n == samples:
                _say(f"got {i}")


# -- the measurement (this process) ---------------------------------------------------------


async def _rss(pid: int) -> dict[str, float]:
    """The router's resident memory, in MiB: all of it, anonymous, shared memory."""
    text = await anyio.Path(f"/proc/{pid}/status").read_text()
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)

    def mib(key: str) -> float:
        return round(int(fields[key].split()[0]) / 1024, 1)

    return {"rss": mib("VmRSS"), "anon": mib("RssAnon"), "shmem": mib("RssShmem")}


def _configs(limit: bool, shm: bool) -> tuple[dict[str, Any], dict[str, Any]]:
    """The router's and the clients' configs of one variant."""
    plan = parse_plan(MODEL, "<memory model>").plan
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = router_config(plan, "edge", local=[endpoint])
    client = client_config(endpoint, max_sample_bytes=plan.fabric.max_sample_bytes)
    out = []
    for conf in (router, client):
        conf = copy.deepcopy(conf)
        if not limit:
            del conf["transport"]["link"]["rx"]
        if shm:
            del conf["transport"]["shared_memory"]  # Zenoh's default: on
        out.append(conf)
    return out[0], out[1]


def _env() -> dict[str, str]:
    """The children's environment as ``rap up`` gives it, which opens no session first:
    without the Zenoh runtime this process's sessions set (each child picks its own)."""
    return {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}


async def _variant(
    folder: Path, name: str, *, peers: int, settle: float, size: int = SAMPLE_BYTES
) -> dict[str, Any]:
    limit, shm, what = VARIANTS[name]
    router, client = _configs(limit, shm)
    await anyio.Path(folder).mkdir(parents=True, exist_ok=True)
    router_path, client_path = folder / "zenoh-router.json5", folder / "zenoh-client.json5"
    await anyio.Path(router_path).write_text(render_zenoh(router, title=f"memory: {name}"))
    await anyio.Path(client_path).write_text(render_zenoh(client, title=f"memory: {name}"))
    me = [sys.executable, "-m", "bench.faults.memory"]
    argv = [sys.executable, "-m", "rap_cli.router", "--config", str(router_path)]
    samples: list[dict[str, float]] = []
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT, cwd=ROOT, env=_env()) as proc,
        anyio.create_task_group() as tg,
    ):
        lines = Lines(proc, f"the {name} router")
        tg.start_soon(lines.pump)
        try:
            await lines.first(lambda _t, s: "listening on" in s, timeout=60)
            receiver = await anyio.open_process(
                [*me, "receive", str(client_path), str(SAMPLES)],
                stderr=subprocess.DEVNULL,
                cwd=ROOT,
                env=_env(),
            )
            async with receiver:
                got = Lines(receiver, "the receiver")
                tg.start_soon(got.pump)
                try:
                    await got.first(lambda _t, s: s == "ready", timeout=60)
                    samples.append(await _rss(proc.pid))
                    for i in range(peers):
                        await _peer(me, client_path, i, size, got)
                        await lines.first(_lost(lines, i + 1), timeout=30)  # link gone
                        samples.append(await _rss(proc.pid))
                    await anyio.sleep(settle)  # what the router gives back, given time
                    end = await _rss(proc.pid)
                finally:
                    await stop_process(receiver, grace=10)
        finally:
            await stop_process(proc, grace=10)
            tg.cancel_scope.cancel()
    return _figures(name, what, limit, shm, samples, end, peers, settle)


def _lost(lines: Lines, n: int) -> Callable[[float, str], bool]:
    """Whether the router has logged ``n`` links lost."""

    def pred(_t: float, _s: str) -> bool:
        return sum(1 for _, s in lines.items if " lost " in s) >= n

    return pred


async def _peer(me: list[str], config: Path, index: int, size: int, got: Lines) -> None:
    """A publisher, killed (SIGKILL) while it publishes, once ``SAMPLES`` of its samples
    reached the receiver."""
    argv = [*me, "publish", str(config), str(index), str(size)]
    async with await anyio.open_process(
        argv, stderr=subprocess.DEVNULL, cwd=ROOT, env=_env()
    ) as peer:
        try:
            await got.first(lambda _t, s: s == f"got {index}", timeout=60)
        finally:
            peer.send_signal(signal.SIGKILL)
            with anyio.CancelScope(shield=True):
                await peer.wait()


def _figures(
    name: str,
    what: str,
    limit: bool,
    shm: bool,
    samples: list[dict[str, float]],
    end: dict[str, float],
    peers: int,
    settle: float,
) -> dict[str, Any]:
    first, last = samples[1], samples[-1]
    per = {k: round((last[k] - first[k]) / max(peers - 1, 1), 2) for k in first}
    return {
        "what": what,
        "message_limit_bytes": LIMIT + MESSAGE_HEADROOM if limit else 1 << 30,
        "shared_memory": shm,
        "rss_mib": [s["rss"] for s in samples],
        "anon_mib": [s["anon"] for s in samples],
        "shmem_mib": [s["shmem"] for s in samples],
        "end_mib": end,
        "settle_s": settle,
        "per_peer_mib": per["rss"],
        "per_peer_anon_mib": per["anon"],
        "per_peer_shmem_mib": per["shmem"],
        "given_back_mib": round(last["rss"] - end["rss"], 1),
    }


async def run_memory(
    folder: Path, *, peers: int, settle: float, variants: tuple[str, ...] = tuple(VARIANTS)
) -> dict[str, Any]:
    if peers < 2:
        raise ScenarioError("the memory scenario needs at least 2 peers (a slope)")
    say(
        f"memory: {peers} peers a router, each sending {SAMPLES} x 1 MiB and killed -9 "
        f"mid-stream; configs {', '.join(variants)}"
    )
    out: dict[str, Any] = {}
    for name in variants:
        out[name] = await _variant(folder / name, name, peers=peers, settle=settle)
        v = out[name]
        say(
            f"  {name}: {v['rss_mib'][0]} -> {v['rss_mib'][-1]} MiB after {peers} peers, "
            f"{v['per_peer_mib']} MiB per peer ({v['per_peer_shmem_mib']} shared memory)"
        )
    rap = out.get("rap")
    return {
        "peers": peers,
        "sample_bytes": SAMPLE_BYTES,
        "samples_per_peer": SAMPLES,
        "max_sample_bytes": LIMIT,
        "target_mib_per_peer": TARGET_MIB,
        "variants": out,
        "ok": rap is not None and rap["per_peer_mib"] <= TARGET_MIB,
    }


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) == 4 and args[0] == "publish" and args[2].isdigit() and args[3].isdigit():
        anyio.run(publish, Path(args[1]), int(args[2]), int(args[3]))
        return 0
    if len(args) == 3 and args[0] == "receive" and args[2].isdigit():
        anyio.run(receive, Path(args[1]), int(args[2]))
        return 0
    print(
        "usage: python -m bench.faults.memory publish CLIENT_CONFIG INDEX SIZE\n"
        "       python -m bench.faults.memory receive CLIENT_CONFIG SAMPLES",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    sys.exit(main())
