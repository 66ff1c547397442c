"""Where a deployed loop's CPU goes, process by process and thread by thread.

    python -m bench.loop.threads [--variant rap-5proc] [--rate 20] [--seconds 10]

Deploys ``variant`` as ``make bench-loop`` does, runs the robot at ``rate`` Hz, and reads
each process's threads' CPU time and run count from ``/proc/<pid>/task/<tid>/schedstat``
over a window of ``seconds`` in the middle of the round: CPU microseconds and times a
thread was scheduled, per loop cycle. Threads are grouped as ``loop`` (the process's
Python thread: the event loop, handlers, RAP's runtime), ``zenoh`` (Zenoh's worker
threads, which also run RAP's transport callbacks: the payload copy, the hand-off to the
loop and the decoding done there) and ``other``. Idle work (timers, keep-alives) is
counted too: it competes for the same cores. Linux only.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import anyio
import yaml

from .rap import PLANS, run_rap

ZENOH_THREADS = ("rx-", "tx-", "net-", "acc-", "app-")


def _label(pid: int) -> str | None:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return None
    if pid == os.getpid():
        return "robot"
    if "--node" in argv:
        return f"runner {argv[argv.index('--node') + 1]}"
    if "knowledge" in argv:
        return "knowledge"
    return None


def _processes() -> dict[int, str]:
    """This process and its descendants that are part of the loop."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            status = Path(f"/proc/{entry}/status").read_text()
        except OSError:
            continue
        for line in status.splitlines():
            if line.startswith("PPid:"):
                parent[int(entry)] = int(line.split()[1])
                break
    found, todo = {}, [os.getpid()]
    while todo:
        pid = todo.pop()
        label = _label(pid)
        if label is not None:
            found[pid] = label
        todo += [child for child, ppid in parent.items() if ppid == pid]
    return found


def _snapshot(procs: dict[int, str]) -> dict[tuple[str, str], tuple[int, int]]:
    """(process, thread group) -> (CPU ns, times scheduled), summed over threads."""
    totals: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0])
    for pid, label in procs.items():
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                cpu, _, runs = Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()
                name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            except (OSError, ValueError):
                continue
            group = (
                "loop"
                if tid == str(pid)
                else "zenoh"
                if name.startswith(ZENOH_THREADS)
                else "other"
            )
            t = totals[(label, group)]
            t[0] += int(cpu)
            t[1] += int(runs)
    return {k: (v[0], v[1]) for k, v in totals.items()}


def _expected(variant: str) -> int:
    """Processes of ``variant``'s deployment: a runner per compute node, the knowledge
    service and this one (the robot)."""
    plan = yaml.safe_load(PLANS[variant].read_text())
    return len(plan["compute_nodes"]) + 2


def measure(variant: str, rate: float, seconds: float, settle: float = 3.0) -> dict[str, Any]:
    """The round lasts the window, ``settle`` s before it (the loop past its first
    cycles) and a margin for the robot's start; a window that the round does not cover
    whole is an error, not a figure."""
    cycles = int(rate * (settle + seconds + 5.0))
    window: dict[str, Any] = {}

    def watch() -> None:
        deadline = time.monotonic() + 60.0
        while len(procs := _processes()) < _expected(variant):  # deployed yet?
            if time.monotonic() > deadline:
                window["error"] = f"{variant}'s processes did not all start within 60 s"
                return
            time.sleep(0.2)
        time.sleep(settle)
        a, t0 = _snapshot(procs), time.monotonic()
        time.sleep(seconds)
        b, t1 = _snapshot(procs), time.monotonic()
        if set(a) != set(b):
            window["error"] = "a process of the loop ended inside the measuring window"
            return
        n = (t1 - t0) * rate
        window["end"] = t1
        window["rows"] = [
            {
                "process": k[0],
                "threads": k[1],
                "cpu_us_per_cycle": round((b[k][0] - a[k][0]) / 1e3 / n, 1),
                "runs_per_cycle": round((b[k][1] - a[k][1]) / n, 1),
            }
            for k in sorted(b)
        ]

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    with tempfile.TemporaryDirectory() as logs:
        res = anyio.run(
            run_rap,
            variant,
            [rate],
            cycles,
            20,
            Path(logs),
            backend_options={"use_uvloop": True},
        )[0]
    round_end = time.monotonic()
    watcher.join(timeout=seconds + settle + 70.0)
    if "error" in window:
        raise RuntimeError(window["error"])
    if window.get("end", round_end + 1) > round_end:
        raise RuntimeError("the round ended before the measuring window did")
    lat = sorted(res["latencies_ns"])
    return {
        "variant": variant,
        "rate_hz": rate,
        "p50_ms": round(lat[len(lat) // 2] / 1e6, 3) if lat else None,
        "lost": res["lost"],
        "rows": window["rows"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.loop.threads", description=__doc__)
    ap.add_argument("--variant", default="rap-5proc", choices=sorted(PLANS))
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    a = ap.parse_args()
    out = measure(a.variant, a.rate, a.seconds)
    print(f"{out['variant']} at {out['rate_hz']:g} Hz: p50 {out['p50_ms']} ms, lost {out['lost']}")
    print(f"{'process':<12} {'threads':<7} {'CPU us/cycle':>13} {'runs/cycle':>11}")
    total = 0.0
    for r in out["rows"]:
        total += r["cpu_us_per_cycle"]
        print(
            f"{r['process']:<12} {r['threads']:<7} {r['cpu_us_per_cycle']:>13.1f} "
            f"{r['runs_per_cycle']:>11.1f}"
        )
    print(f"{'all':<20} {total:>13.1f}")


if __name__ == "__main__":
    main()
