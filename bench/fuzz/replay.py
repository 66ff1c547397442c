"""``python -m bench.fuzz.replay KEY HEX --connect EP [--query]``: send one payload (a
sample from a fuzz report, in hex) to a running system, as a put on ``KEY`` or as a query
(``--query``: the replies are printed). For reproducing what a fuzz run found.

    python -m trust_checker SPEC --fabric demo --listen tcp/127.0.0.1:7447 &
    python -m bench.fuzz.replay rap/demo/admin/trust_checker/swap 86a375... \\
        --connect tcp/127.0.0.1:7447 --query
"""

from __future__ import annotations

import argparse
import sys

import anyio
from rap_sdk import FabricError, QueryError, ZenohConfig, ZenohFabric

WAIT = 10.0
"""Seconds to wait for the peer's subscriber or queryable to match."""


async def replay(key: str, payload: bytes, connect: list[str], query: bool) -> int:
    async with ZenohFabric(ZenohConfig(connect=connect)) as fabric:
        try:
            await fabric.wait_matched(key, queryable=query, timeout=WAIT)
        except FabricError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if not query:
            await fabric.publish(key, payload)
            print(f"published {len(payload)} bytes on {key}")
            return 0
        try:
            replies = await fabric.query(key, payload, timeout=WAIT)
        except QueryError as exc:
            print(f"no answer: {exc}")
            return 1
        for r in replies:
            print(f"{'ok' if r.ok else 'error'} reply on {r.key}: {r.payload[:500]!r}")
        if not replies:
            print("no reply (the queryable went away?)")
        return 0 if replies else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.fuzz.replay", description=__doc__)
    ap.add_argument("key", help="the key (or query selector)")
    ap.add_argument("hex", help="the payload, hex")
    ap.add_argument("--connect", action="append", required=True, help="Zenoh endpoint")
    ap.add_argument("--query", action="store_true", help="send it as a query")
    args = ap.parse_args(argv)
    try:
        payload = bytes.fromhex(args.hex)
    except ValueError as exc:
        ap.error(f"not hex: {exc}")
    return anyio.run(replay, args.key, payload, args.connect, args.query)


if __name__ == "__main__":
    sys.exit(main())
