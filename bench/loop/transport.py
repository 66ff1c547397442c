"""The transport floor of the race: what two cross-process hops cost on this machine.

- ``zenoh-echo``: raw Zenoh, no RAP and no event loop. This process puts a 4.5 KB
  payload, a child process puts it straight back from inside Zenoh's subscriber callback
  (on Zenoh's own thread), and this process timestamps the echo in its callback. It is
  the least a scan -> plan round trip over Zenoh can cost here.
- ``rap-echo`` (see ``chain.echo`` and ``plans/echo.yaml``) is the same round trip through
  RAP: the robot's scan reaches one RAP node in a runner process, which publishes the plan
  back: envelopes, typed decode, inboxes and two asyncio event loops woken by Zenoh.

Every RAP variant pays at least the ``rap-echo`` round trip; every stage it adds in
another process pays one more hop.

    python -m bench.loop.transport echo --connect ENDPOINT    (the child, used internally)
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from typing import Any

import zenoh
from rap_sdk.fabric import free_port

PING, PONG = "race/floor/ping", "race/floor/pong"
PAYLOAD = b"\x00" * 4500
"""About the size of the race's 360-beam scan as msgpack."""


def _config(*, listen: str = "", connect: str = "") -> zenoh.Config:
    conf: dict[str, Any] = {"mode": "peer", "scouting": {"multicast": {"enabled": False}}}
    if listen:
        conf["listen"] = {"endpoints": [listen]}
    if connect:
        conf["connect"] = {"endpoints": [connect]}
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
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(_config(listen=endpoint))
    child = subprocess.Popen(
        [sys.executable, "-m", "bench.loop.transport", "echo", "--connect", endpoint],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None
        if child.stdout.readline().strip() != "ready":
            raise RuntimeError("the zenoh echo process did not start")
        back = threading.Event()
        arrived = [0]

        def on_pong(_: zenoh.Sample) -> None:
            arrived[0] = time.perf_counter_ns()
            back.set()

        session.declare_subscriber(PONG, zenoh.handlers.Callback(on_pong, indirect=False))
        pub = session.declare_publisher(PING)
        deadline = time.monotonic() + 10.0
        while not pub.matching_status.matching:  # the child's subscriber reached us
            if time.monotonic() > deadline:
                raise RuntimeError("the zenoh echo process never subscribed")
            time.sleep(0.01)
        lat: list[int] = []
        lost = 0
        period = 1.0 / rate
        start = time.perf_counter()
        for i in range(warmup + cycles):
            delay = start + i * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            back.clear()
            t = time.perf_counter_ns()
            pub.put(PAYLOAD)
            if not back.wait(1.0):
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
    finally:
        if child.stdin is not None:
            child.stdin.close()
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        session.close()


if __name__ == "__main__":
    if sys.argv[1:2] == ["echo"] and len(sys.argv) == 4 and sys.argv[2] == "--connect":
        _echo(sys.argv[3])
    else:
        sys.exit("usage: python -m bench.loop.transport echo --connect ENDPOINT")
