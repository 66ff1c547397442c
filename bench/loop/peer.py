"""The peer of the loop latency race, driven from the RAP workspace: RPIO 0.4.3 over Redis and
over MQTT, run by ``rpio_peer.py`` in the peer's own venv (``bench/.rpio-venv``).

    run_peer(variant, rates, cycles, warmup) -> {"variant", "meta", "rates": [per-rate result]}
    sustained_rate(variant, ...)             -> the highest ladder rate the chain sustains
    verdict(rate_result)                     -> {"lossless", "keeps_up", "why"}
    summarize(rate_result)                   -> p50/p90/p99 (ms), lost, send rate, CPU

A per-rate result (from rpio_peer.py) holds ``rate_hz, warmup, sent, received, lost,
lost_superseded, late_over_2s, duplicates, latencies_ns`` (the measured cycles in send order,
lost ones left out), ``send_rate_hz, late_sends, window_s, startup_s, cpu_pct`` ({process: %
of one core} over the measured window: the five nodes, redis-server, mosquitto, the robot
driver), ``cpu_pct_total, system_busy_pct`` (the whole machine, so that foreign load shows),
``node_stats, run_wall_s``; or ``rate_hz, error`` when the chain did not come up.

``python -m bench.loop.peer [--variants redis,mqtt] [--rates 5,20,100] [--cycles 200]
[--warmup 20] [--no-ladder] [--out FILE]`` runs both and prints a table (a look, not a report:
``python -m bench.loop`` writes bench/results and docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..report import hardware, hardware_line, pct, table
from .peer_venv import PeerVenvError, ensure_venv

HERE = Path(__file__).resolve().parent
RPIO_PEER = HERE / "rpio_peer.py"
VARIANTS = ("redis", "mqtt")
LADDER: tuple[float, ...] = (5, 20, 50, 100, 200, 300, 500)
STARTUP_BUDGET_S = 45.0
"""Per rate, on top of the sending time: node start, priming (<= 30 s), drain (2.5 s)."""


class PeerError(RuntimeError):
    """The peer could not be set up or run; the message says why."""


_venv_python: Path | None = None


def peer_python() -> Path:
    """The peer venv's python, created on first use (once per process)."""
    global _venv_python
    if _venv_python is None:
        try:
            _venv_python = ensure_venv()
        except PeerVenvError as exc:
            raise PeerError(str(exc)) from exc
    return _venv_python


def _check_binaries(variant: str) -> None:
    need = ["redis-server"] + (["mosquitto"] if variant == "mqtt" else [])
    missing = [b for b in need if shutil.which(b) is None and not Path("/usr/sbin", b).exists()]
    if missing:
        raise PeerError(f"the {variant} peer needs {', '.join(missing)} (apt-get install them)")


def run_peer(
    variant: str,
    rates: list[float],
    cycles: int,
    warmup: int,
    *,
    timeout: float | None = None,
    echo: bool = True,
) -> dict[str, Any]:
    """Run the RPIO chain over ``variant`` (redis | mqtt) at each rate in ``rates`` (Hz):
    ``warmup`` cycles, then ``cycles`` measured ones, fresh node processes per rate.
    Progress goes to stderr when ``echo``. Raises PeerError when the peer cannot run at all;
    a rate whose chain did not come up has an ``error`` entry instead."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, not {variant!r}")
    if not rates or min(rates) <= 0 or cycles < 2 or warmup < 0:
        raise ValueError("need positive rates, cycles >= 2 and warmup >= 0")
    _check_binaries(variant)
    python = peer_python()
    if timeout is None:
        timeout = 30.0 + sum((warmup + cycles) / r + STARTUP_BUDGET_S for r in rates)
    with tempfile.TemporaryDirectory(prefix="rap_loop_peer_") as tmp:
        out = Path(tmp) / "peer.json"
        args = [str(python), str(RPIO_PEER), "run", "--variant", variant]
        args += ["--rates", ",".join(f"{r:g}" for r in rates), "--cycles", str(cycles)]
        args += ["--warmup", str(warmup), "--out", str(out)]
        err_path = Path(tmp) / "stderr.txt"
        with open(err_path, "wb") as err:
            proc = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=None if echo else err,
            )
            try:
                rc = proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                _stop(proc)  # SIGTERM first: the peer stops its brokers and nodes
                raise PeerError(
                    f"rpio_peer.py ({variant}) timed out after {timeout:.0f} s"
                ) from None
            except BaseException:
                _stop(proc)
                raise
        if rc not in (0, 2) or not out.exists():
            tail = err_path.read_text(errors="replace")[-3000:] if not echo else "(see above)"
            raise PeerError(f"rpio_peer.py ({variant}) exited with {rc}:\n{tail}")
        data: dict[str, Any] = json.loads(out.read_text())
    return data


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def summarize(r: dict[str, Any]) -> dict[str, Any]:
    """p50/p90/p99/max (ms, nearest rank), lost cycles, achieved send rate, CPU of one rate."""
    if "error" in r:
        return {"rate_hz": r["rate_hz"], "error": r["error"].splitlines()[0]}
    lat = r["latencies_ns"]
    out: dict[str, Any] = {"rate_hz": r["rate_hz"], "n": len(lat)}
    for name, q in (("p50_ms", 0.5), ("p90_ms", 0.9), ("p99_ms", 0.99), ("max_ms", 1.0)):
        out[name] = round(pct(lat, q) / 1e6, 3) if lat else None
    out.update(
        sent=r["sent"],
        lost=r["lost"],
        lost_superseded=r["lost_superseded"],
        duplicates=r["duplicates"],
        stale_reads=sum(s.get("stale", 0) for s in r["node_stats"].values()),
        send_rate_hz=r["send_rate_hz"],
        growth_ms_per_s=round(1000 * growth(r), 2) if lat else None,
        cpu_pct_total=r["cpu_pct_total"],
        system_busy_pct=r["system_busy_pct"],
    )
    return out


MAX_GROWTH = 0.01
"""Backlog threshold: seconds of latency gained per second of sending."""


def growth(r: dict[str, Any]) -> float:
    """How fast the latency climbed through the run: (p50 of the last fifth of the cycles -
    p50 of the first fifth) / the time between them, in seconds per second (0 if it fell)."""
    lat = r["latencies_ns"]
    fifth = max(1, len(lat) // 5)
    rise_s = (pct(lat[-fifth:], 0.5) - pct(lat[:fifth], 0.5)) / 1e9
    span_s = max(0.8 * (r["window_s"] or 0.0), 1.0 / r["rate_hz"])
    return max(0.0, rise_s / span_s)


def verdict(r: dict[str, Any]) -> dict[str, Any]:
    """Was one rate held? ``lossless``: every measured cycle got its own plan within 2 s.
    ``keeps_up``: every scan was answered within 2 s by its own plan or a newer cycle's (RPIO's
    knowledge is last-value: a scan overwritten before Analysis read it gets no plan of its
    own). Both also need the robot to have sent at >= 95 % of the rate and no backlog: the
    p50 latency of the last fifth of the cycles may exceed that of the first fifth by at most
    1 % of the time between them (see ``growth``), i.e. the chain drains >= ~99 % of the
    offered rate; an overloaded chain queues, and its latency climbs long before cycles pass
    2 s. A latency that steps up and stays (e.g. held for one send period) is no backlog.
    Returns ``{"lossless", "keeps_up", "why"}``."""
    no = {"lossless": False, "keeps_up": False}
    if "error" in r:
        return {**no, "why": "error: " + r["error"].splitlines()[0]}
    if r["send_rate_hz"] is None or r["send_rate_hz"] < 0.95 * r["rate_hz"]:
        return {**no, "why": f"robot sent at {r['send_rate_hz']} Hz only"}
    lat = r["latencies_ns"]
    if not lat:
        return {**no, "why": "no cycle answered"}
    if growth(r) > MAX_GROWTH:
        why = f"backlog: latency grows {1000 * growth(r):.0f} ms per s of sending"
        return {**no, "why": why}
    unanswered = r["lost"] - r["lost_superseded"]
    if unanswered:
        return {**no, "why": f"{unanswered} of {r['sent']} scans never answered"}
    if r["lost"]:
        why = f"{r['lost']} of {r['sent']} cycles lost, all answered by a newer plan"
        return {"lossless": False, "keeps_up": True, "why": why}
    return {"lossless": True, "keeps_up": True, "why": "ok"}


def sustained_rate(
    variant: str,
    *,
    ladder: Sequence[float] = LADDER,
    seconds: float = 3.0,
    min_cycles: int = 20,
    max_cycles: int = 1500,
    warmup_seconds: float = 0.5,
    stop_at_first_loss: bool = True,
    echo: bool = True,
) -> dict[str, Any]:
    """Climb ``ladder`` (Hz, ascending) until a step loses a cycle (``stop_at_first_loss``,
    the default) or, if False, until a step does not keep up; see ``verdict``.

    Each step is one ``run_peer`` that sends for about ``seconds`` (cycles = rate x seconds,
    clamped to [min_cycles, max_cycles]) after ``warmup_seconds`` of warm-up (>= 10 cycles).
    Returns ``{"variant", "sustained_hz"`` (highest rate with no lost cycle at it or any lower
    step; None if the first step lost one), ``"keeps_up_hz"`` (the same for ``keeps_up``),
    ``"stopped_at_hz"`` (None when the whole ladder held), ``"reason"``, ``"steps"``
    (summaries with the verdict), ``"best"`` (the raw result at sustained_hz or None),
    ``"results"`` (every step's raw result)``}``."""
    steps: list[dict[str, Any]] = []
    raw: list[dict[str, Any]] = []
    best: dict[str, Any] | None = None
    keeps_up: float | None = None
    lossless_so_far = keeps_up_so_far = True
    stopped: float | None = None
    reason = "whole ladder held"
    for rate in sorted(set(ladder)):
        cycles = min(max_cycles, max(min_cycles, math.ceil(rate * seconds)))
        warmup = max(10, math.ceil(rate * warmup_seconds))
        r = run_peer(variant, [rate], cycles, warmup, echo=echo)["rates"][0]
        raw.append(r)
        v = verdict(r)
        steps.append({**summarize(r), **v})
        lossless_so_far = lossless_so_far and v["lossless"]
        keeps_up_so_far = keeps_up_so_far and v["keeps_up"]
        if lossless_so_far:
            best = r
        if keeps_up_so_far:
            keeps_up = rate
        if not keeps_up_so_far or (stop_at_first_loss and not lossless_so_far):
            stopped, reason = rate, v["why"]
            break
    return {
        "variant": variant,
        "sustained_hz": None if best is None else best["rate_hz"],
        "keeps_up_hz": keeps_up,
        "stopped_at_hz": stopped,
        "reason": reason,
        "steps": steps,
        "best": best,
        "results": raw,
    }


_LAT = ("p50_ms", "p90_ms", "p99_ms", "lost", "lost_superseded", "send_rate_hz")
FIXED_COLS = (*_LAT, "cpu_pct_total", "system_busy_pct", "error")
LADDER_COLS = ("n", *_LAT, "why")


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.loop.peer", description=__doc__)
    ap.add_argument("--variants", default="redis,mqtt")
    ap.add_argument("--rates", default="5,20,100")
    ap.add_argument("--cycles", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--no-ladder", action="store_true", help="skip the sustained-rate search")
    ap.add_argument("--ladder-seconds", type=float, default=3.0)
    ap.add_argument(
        "--ladder-past-loss", action="store_true", help="climb on while the chain keeps up"
    )
    ap.add_argument("--out", help="write everything (with raw latencies) to this JSON file")
    a = ap.parse_args()
    variants = [v for v in a.variants.split(",") if v]
    rates = [float(x) for x in a.rates.split(",") if x]
    hw = hardware()
    print(f"bench/loop peer on {hardware_line(hw)}", file=sys.stderr)
    t0 = time.monotonic()
    everything: dict[str, Any] = {"hardware": hw, "fixed": {}, "ladder": {}}
    rows: list[list[Any]] = []
    try:
        for v in variants:
            t = time.monotonic()
            res = run_peer(v, rates, a.cycles, a.warmup)
            everything["fixed"][v] = res
            for r in res["rates"]:
                s = summarize(r)
                rows.append([v, f"{s['rate_hz']:g}", *(s.get(k, "") for k in FIXED_COLS)])
            print(f"  {v} fixed rates: {time.monotonic() - t:.0f} s", file=sys.stderr)
            if not a.no_ladder:
                t = time.monotonic()
                everything["ladder"][v] = sustained_rate(
                    v, seconds=a.ladder_seconds, stop_at_first_loss=not a.ladder_past_loss
                )
                print(f"  {v} ladder: {time.monotonic() - t:.0f} s", file=sys.stderr)
    except PeerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    headers = ["peer", "Hz", "p50 ms", "p90 ms", "p99 ms", "lost", "superseded", "sent Hz", "cpu %"]
    print(table([*headers, "machine busy %", ""], rows))
    for v, lad in everything["ladder"].items():
        end = "whole ladder held"
        if lad["stopped_at_hz"] is not None:
            end = f"stopped at {lad['stopped_at_hz']:g} Hz: {lad['reason']}"
        print(f"\n{v}: sustained {lad['sustained_hz']} Hz, keeps up to {lad['keeps_up_hz']} Hz")
        print(f"({end})")
        print(
            table(
                ["Hz", "n", "p50 ms", "p90 ms", "p99 ms", "lost", "superseded", "sent Hz", ""],
                [[f"{s['rate_hz']:g}", *(s.get(k, "") for k in LADDER_COLS)] for s in lad["steps"]],
            )
        )
    print(f"\ntotal wall time {time.monotonic() - t0:.0f} s", file=sys.stderr)
    if a.out:
        Path(a.out).write_text(json.dumps(everything, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
