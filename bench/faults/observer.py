"""``python -m bench.faults.observer ENDPOINT SYSTEM``: a Zenoh client of one router that
prints a JSON line per anomaly, verdict and plan sent to the robot, with
``time.monotonic()`` (one clock for every process and network namespace of the machine).

Each line: ``t``, ``kind`` (``anomaly``, ``verdict``, ``plan``, ``alive`` or ``ready``),
``uid``, ``cause`` and ``cycle`` (hex), ``source``, and for a verdict ``plan_uid`` (hex)
and ``approved``; an ``alive`` line names the node whose liveliness token came
(``up: true``) or went. A sample that does not decode is printed as ``kind: "undecodable"`` with
the reason: the observer carries on.

The fault runs use it to time the loop (the next executed plan after a restart or a
cut) and to count plans executed twice (by the plan id the verdict names: a plan's
``cause`` is the verdict the executor acted on)."""

from __future__ import annotations

import json
import sys
import time
from functools import partial
from typing import Any

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import Envelope, Verdict, keys
from rap_schemas.limits import DECODE_ERRORS, decode_failure
from rap_sdk import InboxPolicy, Overflow, ZenohConfig, ZenohFabric

PLAN_TOPIC = "tb1/spin_config"
_envelope = msgspec.msgpack.Decoder(Envelope)
_verdict = msgspec.msgpack.Decoder(Verdict[Any])
_FIFO = InboxPolicy(capacity=1 << 14, overflow=Overflow.FIFO, block=False)


def _say(**line: Any) -> None:
    sys.stdout.write(json.dumps({"t": time.monotonic(), **line}) + "\n")
    sys.stdout.flush()


def _line(kind: str, payload: bytes) -> dict[str, Any]:
    env = _envelope.decode(payload)
    out: dict[str, Any] = {
        "kind": kind,
        "uid": env.uid.hex(),
        "cause": env.cause.hex() if env.cause else "",
        "cycle": env.cycle.hex() if env.cycle else "",
        "source": env.source,
    }
    if kind == "verdict":
        v = _verdict.decode(env.body)
        out["plan_uid"] = bytes(v.plan_uid).hex()
        out["approved"] = bool(v.approved)
    return out


async def observe(endpoint: str, system: str) -> None:
    config = ZenohConfig(mode="client", listen=[], connect=[endpoint])
    wanted = {
        "anomaly": keys.event(system, "anomaly"),
        "verdict": keys.event(system, "verdict"),
        "plan": keys.data(system, PLAN_TOPIC),
    }
    async with ZenohFabric(config) as fabric:

        async def follow(kind: str, key: str, *, task_status: TaskStatus[None]) -> None:
            with fabric.subscribe(key, _FIFO) as sub:
                task_status.started()
                async for sample in sub:
                    try:
                        _say(**_line(kind, sample.payload))
                    except DECODE_ERRORS as exc:
                        _say(kind="undecodable", key=sample.key, reason=decode_failure(exc))

        async def alive(*, task_status: TaskStatus[None]) -> None:
            with fabric.watch_liveliness(keys.pattern(system, keys.Kind.ALIVE)) as changes:
                task_status.started()
                async for change in changes:
                    _say(kind="alive", name=keys.parse(change.key).name, up=change.alive)

        async with anyio.create_task_group() as tg:
            for kind, key in wanted.items():
                await tg.start(partial(follow, kind, key))
            await tg.start(alive)
            _say(kind="ready", endpoint=endpoint)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m bench.faults.observer ENDPOINT SYSTEM", file=sys.stderr)
        return 2
    try:
        anyio.run(observe, args[0], args[1])
    except KeyboardInterrupt:
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
