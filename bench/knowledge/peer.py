"""A raw zenoh-python queryable that hands each query to asyncio and replies from the
loop (the baseline round trip): ``python -m bench.knowledge.peer ENDPOINT``."""

from __future__ import annotations

import asyncio
import json
import sys

import zenoh

KEY = "bench/raw/query"


async def main(endpoint: str) -> None:
    loop = asyncio.get_running_loop()
    conf = {
        "mode": "peer",
        "listen": {"endpoints": []},
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
    }
    session = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))

    def reply(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(KEY, payload)
        query.drop()

    session.declare_queryable(
        KEY, zenoh.handlers.Callback(lambda q: loop.call_soon_threadsafe(reply, q), indirect=False)
    )
    print("READY", flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1]))
