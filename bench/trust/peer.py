"""The processes bench/trust's end-to-end rows start (each connects to the bench's Zenoh
endpoint and prints READY once it is subscribed):

    python -m bench.trust.peer echo SYSTEM ENDPOINT
        the raw baseline: a plain RAP fabric process that takes every record on
        rap/SYSTEM/** the way the checker's transport does (envelope opened, duplicates
        dropped, the StageTrace body decoded) and answers each with a sealed
        rap.TrustOutput on rap/SYSTEM/trust/echo: the same hops and envelopes as the
        checker, without its session and spec runner
    python -m bench.trust.peer session SYSTEM ENDPOINT SPEC
        the checker's fabric transport and session (trust_checker.service.open_service)
        on SPEC with no other sink: ``python -m trust_checker --fabric`` without its
        console output (and without verdicts)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import anyio
import msgspec
from rap_schemas import StageTrace, TrustOutput, keys
from rap_sdk import InboxPolicy, Opener, Overflow, Sealer, ZenohConfig, ZenohFabric
from rap_sdk.errors import RejectedSample

_INBOX = InboxPolicy(capacity=1 << 16, overflow=Overflow.FIFO, block=False)


async def echo(system: str, endpoint: str) -> None:
    decode = msgspec.msgpack.Decoder(StageTrace).decode
    opener = Opener()
    sealer = Sealer("echo")
    out_key = keys.trust(system, "echo")
    tick = 0
    async with ZenohFabric(ZenohConfig(connect=[endpoint])) as fabric:
        with fabric.subscribe(keys.system_pattern(system), _INBOX) as sub:
            print("READY", flush=True)
            async for sample in sub:
                if not sample.key.startswith(f"{keys.ROOT}/{system}/trace/"):
                    continue  # our own answers
                try:
                    env = opener.open(sample.key, sample.payload)
                except RejectedSample:
                    continue
                if env is None or env.type != StageTrace.TYPE:
                    continue
                rec = decode(env.body)
                msg = TrustOutput(
                    stream="echo", tick=tick, ts=time.time_ns(), value=bool(rec.cycle)
                )
                tick += 1
                payload, _ = sealer.seal_message(out_key, msg)
                await fabric.publish(out_key, payload, timeout=2.0)


async def session(system: str, endpoint: str, spec_path: str) -> None:
    from trust_checker.config import FabricConfig, ServiceConfig
    from trust_checker.lang import load_spec
    from trust_checker.service import open_service

    spec = load_spec(Path(spec_path))
    config = ServiceConfig(verdicts=False, fabric=FabricConfig(system=system))
    async with (
        ZenohFabric(ZenohConfig(connect=[endpoint])) as fabric,
        open_service(config, spec, fabric=fabric),
    ):
        print("READY", flush=True)
        await anyio.sleep_forever()


def main(argv: list[str]) -> None:
    if len(argv) == 3 and argv[0] == "echo":
        anyio.run(echo, argv[1], argv[2], backend_options={"use_uvloop": True})
    elif len(argv) == 4 and argv[0] == "session":
        anyio.run(session, argv[1], argv[2], argv[3], backend_options={"use_uvloop": True})
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
