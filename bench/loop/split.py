"""What the deployed loops cost without their knowledge, against the peer.

    python -m bench.loop.split [--rates 20 100] [--rounds 2] [--seconds 8] [--no-peer]

Runs, interleaved in each round and at each rate: the peer over Redis (``rpio-redis``),
the raw Zenoh floors (``zenoh-echo``, ``zenoh-relay``), RAP's one- and five-process
loops as the race deploys them (``rap-1proc``, ``rap-5proc``) and the same loops with
every knowledge read and write taken out of the stages (``-bare``: bench/loop/chain_bare.py,
same nodes, messages and gate). Prints each row's p50 and its ratio to the peer and to
the raw echo, round by round, and writes bench/results/split.json.

``-bare`` is not a floor of the race (the race's stages use knowledge, as the peer's
do); it splits a loop's time in two: what the stages' knowledge adds (the row less its
``-bare`` row) and what is left without it (the ``-bare`` row less the transport floor).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import anyio

from .rap import run_rap
from .transport import zenoh_echo, zenoh_relay

RESULTS = Path(__file__).resolve().parents[1] / "results" / "split.json"
RAP_ROWS = ("rap-1proc", "rap-1proc-bare", "rap-5proc", "rap-5proc-bare")


def _p50(lat: list[int]) -> float | None:
    lat = sorted(lat)
    return round(lat[len(lat) // 2] / 1e6, 3) if lat else None


def one_round(rate: float, cycles: int, peer: bool) -> dict[str, float | None]:
    """Every row once at ``rate``, in a fixed order; p50 in ms."""
    row: dict[str, float | None] = {}
    if peer:
        from .peer import run_peer

        row["rpio-redis"] = _p50(run_peer("redis", [rate], cycles, 20)["rates"][0]["latencies_ns"])
    row["zenoh-echo"] = _p50(zenoh_echo(rate, cycles)["latencies_ns"])
    row["zenoh-relay"] = _p50(zenoh_relay(rate, cycles)["latencies_ns"])
    for variant in RAP_ROWS:
        with tempfile.TemporaryDirectory() as logs:
            uv = {"use_uvloop": True}
            res = anyio.run(run_rap, variant, [rate], cycles, 20, Path(logs), backend_options=uv)[0]
        if res["lost"]:
            raise RuntimeError(f"{variant} at {rate:g} Hz lost {res['lost']} cycle(s)")
        row[variant] = _p50(res["latencies_ns"])
    return row


def ratios(row: dict[str, float | None], base: str) -> dict[str, float | None]:
    b = row.get(base)
    return {k: (round(v / b, 2) if v and b else None) for k, v in row.items()}


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.loop.split", description=__doc__)
    ap.add_argument("--rates", type=float, nargs="+", default=[20.0, 100.0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--no-peer", action="store_true", help="leave the peer out (no RPIO venv)")
    a = ap.parse_args()
    out: list[dict[str, Any]] = []
    for rnd in range(a.rounds):
        for rate in a.rates:
            cycles = int(min(2000, max(30, rate * a.seconds)))
            row = one_round(rate, cycles, not a.no_peer)
            base = "zenoh-echo" if a.no_peer else "rpio-redis"
            out.append({"round": rnd, "rate_hz": rate, "p50_ms": row, "ratio": ratios(row, base)})
            print(f"round {rnd}, {rate:g} Hz, p50 ms: {row}", flush=True)
            print(f"  / {base}: {out[-1]['ratio']}", flush=True)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
