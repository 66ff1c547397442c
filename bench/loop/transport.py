"""The transport floor of the race: what two cross-process hops cost on this machine.

- ``zenoh-echo``: raw Zenoh, no RAP and no event loop. This process puts a 4.5 KB
  payload, a child process puts it straight back from inside Zenoh's subscriber callback
  (on Zenoh's own thread), and this process timestamps the echo in its callback. It is
  the least a scan -> plan round trip over Zenoh can cost here.
- ``zenoh-echo-loop``: the same two hops with each end woken in its asyncio loop
  (uvloop): the child is a one-stage relay (below), and this process takes the echo from
  Zenoh's thread into its loop before it timestamps it. Every RAP process is an asyncio
  process, so this is the least a round trip between two of them can cost.
- ``rap-echo`` (see ``chain.echo`` and ``plans/echo.yaml``) is the same round trip through
  RAP: the robot's scan reaches one RAP node in a runner process, which publishes the plan
  back: envelopes, typed decode, inboxes and two asyncio event loops woken by Zenoh.

Every RAP variant pays at least the ``rap-echo`` round trip; every stage it adds in
another process pays one more hop.

    python -m bench.loop.transport echo --connect ENDPOINT    (the child, used internally)
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import uvloop
import zenoh
from rap_sdk import ZenohConfig
from rap_sdk.fabric import free_port

PING, PONG = "race/floor/ping", "race/floor/pong"
ECHO_CMD = (sys.executable, "-m", "bench.loop.transport", "echo")
PAYLOAD = b"\x00" * 4500
"""About the size of the race's 360-beam scan as msgpack."""


def _config(*, listen: str = "", connect: str | list[str] = "") -> zenoh.Config:
    conf: dict[str, Any] = {"mode": "peer", "scouting": {"multicast": {"enabled": False}}}
    if listen:
        conf["listen"] = {"endpoints": [listen]}
    if connect:
        conf["connect"] = {"endpoints": [connect] if isinstance(connect, str) else connect}
    return zenoh.Config.from_json5(json.dumps(conf))


def _echo(connect: str) -> None:
    session = zenoh.open(_config(connect=connect))
    pub = session.declare_publisher(PONG)
    session.declare_subscriber(
        PING, zenoh.handlers.Callback(lambda s: pub.put(s.payload.to_bytes()), indirect=False)
    )
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    sys.stdin.read()  # until the parent closes the pipe
    session.close()


def zenoh_echo(rate: float, cycles: int, warmup: int = 20) -> dict[str, Any]:
    """Round trips at ``rate`` Hz on absolute deadlines; a round trip not back within
    1 s is counted as lost."""
    ZenohConfig().use_runtime()  # Zenoh's threads as in RAP's processes, children too
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(_config(listen=endpoint))
    children: list[subprocess.Popen[str]] = []
    try:
        _start(children, [[*ECHO_CMD, "--connect", endpoint]])
        return _round_trips(session, PING, PONG, rate, cycles, warmup)
    finally:
        _stop(children)
        session.close()


RELAY = "race/floor/relay"
RELAY_CMD = (sys.executable, "-m", "bench.loop.transport", "relay")
STAGES = 5


def _relay(index: int, listen: str, connect: list[str], stages: int = STAGES) -> None:
    """Stage ``index`` of the relay floor: a sample on ``relay/<index>`` wakes this
    process's asyncio loop (uvloop, as RAP's processes run), which puts it on the next
    key from the loop: what one RAP stage in its own process pays at least, with no
    envelope, no decoding and no knowledge."""

    async def run() -> None:
        loop = asyncio.get_running_loop()
        session = zenoh.open(_config(listen=listen, connect=connect))
        nxt = f"{RELAY}/{index + 1}" if index + 1 < stages else f"{RELAY}/back"
        pub = session.declare_publisher(nxt)

        def on_sample(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()  # on Zenoh's thread: hand it to the loop
            loop.call_soon_threadsafe(pub.put, data)

        session.declare_subscriber(
            f"{RELAY}/{index}", zenoh.handlers.Callback(on_sample, indirect=False)
        )
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        await loop.run_in_executor(None, sys.stdin.read)  # until the parent closes it
        session.close()

    uvloop.run(run())


def zenoh_relay(
    rate: float, cycles: int, warmup: int = 20, stages: int = STAGES, woken: bool = False
) -> dict[str, Any]:
    """The transport floor of the five-process loop: six cross-process hops (robot ->
    five relay processes, each woken in its event loop -> robot) on raw Zenoh, all
    sessions meshed with each other; lost after 1 s, as ``zenoh_echo``. ``stages``: how
    many relays; ``woken``: this process, too, takes each sample that comes back from
    Zenoh's thread into an asyncio loop (uvloop) before it timestamps it."""
    ZenohConfig().use_runtime()  # Zenoh's threads as in RAP's processes, children too
    ports = [free_port() for _ in range(stages + 1)]
    ends = [f"tcp/127.0.0.1:{p}" for p in ports]
    session = zenoh.open(_config(listen=ends[0]))
    children: list[subprocess.Popen[str]] = []
    try:
        _start(
            children,
            [
                [*RELAY_CMD, str(i), ends[i + 1], *ends[: i + 1], "--stages", str(stages)]
                for i in range(stages)
            ],
        )
        with _loop_thread() if woken else contextlib.nullcontext() as loop:
            return _round_trips(session, f"{RELAY}/0", f"{RELAY}/back", rate, cycles, warmup, loop)
    finally:
        _stop(children)
        session.close()


def zenoh_echo_loop(rate: float, cycles: int, warmup: int = 20) -> dict[str, Any]:
    """``zenoh-echo`` with both ends woken in their asyncio loops (uvloop), as every RAP
    process is: the child is a one-stage relay, and this process takes the echo from
    Zenoh's thread into a loop before it timestamps it. Two hops and two loop wake-ups,
    no RAP code: the least a round trip between two RAP processes can cost."""
    return zenoh_relay(rate, cycles, warmup, stages=1, woken=True)


@contextlib.contextmanager
def _loop_thread() -> Iterator[asyncio.AbstractEventLoop]:
    """An idle uvloop running on a thread of its own, for the duration of the block."""
    loop = uvloop.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="floor-loop", daemon=True)
    thread.start()
    try:
        yield loop
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=5)
        loop.close()


def _start(children: list[subprocess.Popen[str]], cmds: list[list[str]]) -> None:
    """Start ``cmds`` (appended to ``children`` as they start, for ``_stop``) and wait
    until each says it is ready."""
    children.extend(  # appended one by one: a failed start leaves the others to stop
        subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for cmd in cmds
    )
    for child in children:
        assert child.stdout is not None
        if child.stdout.readline().strip() != "ready":
            raise RuntimeError(f"a floor process did not start: {child.args}")


def _stop(children: list[subprocess.Popen[str]]) -> None:
    """Close the children's stdin (they end), wait for them, close their pipes."""
    for child in children:
        if child.stdin is not None:
            child.stdin.close()
    for child in children:
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        if child.stdout is not None:
            child.stdout.close()


def _round_trips(
    session: zenoh.Session,
    out: str,
    back: str,
    rate: float,
    cycles: int,
    warmup: int,
    loop: asyncio.AbstractEventLoop | None = None,
) -> dict[str, Any]:
    """Put on ``out`` at ``rate`` Hz, time until the sample is back on ``back``: in
    Zenoh's callback, or, with ``loop``, once ``loop`` has been woken to take it."""
    got = threading.Event()
    arrived = [0]

    def stamp() -> None:
        arrived[0] = time.perf_counter_ns()
        got.set()

    def on_back(_: zenoh.Sample) -> None:
        if loop is None:
            stamp()
        else:
            loop.call_soon_threadsafe(stamp)

    session.declare_subscriber(back, zenoh.handlers.Callback(on_back, indirect=False))
    pub = session.declare_publisher(out)
    deadline = time.monotonic() + 10.0
    while True:  # the whole chain is connected: a probe comes back
        got.clear()
        pub.put(PAYLOAD)
        if got.wait(0.2):
            break
        if time.monotonic() > deadline:
            raise RuntimeError(f"nothing came back on {back} from {out} within 10 s")
    lat: list[int] = []
    lost = 0
    period = 1.0 / rate
    start = time.perf_counter()
    for i in range(warmup + cycles):
        delay = start + i * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        got.clear()
        t = time.perf_counter_ns()
        pub.put(PAYLOAD)
        if not got.wait(1.0):
            lost += i >= warmup
            continue
        if i >= warmup:
            lat.append(arrived[0] - t)
    return {
        "rate_hz": rate,
        "sent": cycles,
        "received": len(lat),
        "lost": lost,
        "latencies_ns": lat,
    }


if __name__ == "__main__":
    if sys.argv[1:2] == ["echo"] and len(sys.argv) == 4 and sys.argv[2] == "--connect":
        _echo(sys.argv[3])
    elif sys.argv[1:2] == ["relay"] and len(sys.argv) >= 5:
        args = sys.argv[4:]
        stages = STAGES
        if args[-2:-1] == ["--stages"]:
            stages, args = int(args[-1]), args[:-2]
        _relay(int(sys.argv[2]), sys.argv[3], args, stages)
    else:
        sys.exit(
            "usage: python -m bench.loop.transport echo --connect ENDPOINT\n"
            "       python -m bench.loop.transport relay INDEX LISTEN CONNECT... [--stages N]"
        )
