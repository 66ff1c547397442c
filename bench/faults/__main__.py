"""``python -m bench.faults [--quick] [--only kills,redis,partition,fifo,fuzz,memory]``: bounded
fault injection into the lidar-occlusion loop run as a user runs it (``rap up``), with
measured figures against targets.

Scenarios (each in its own module of bench/faults, which says what it does):

1. ``kills``: kill -9 of knowledge, the adaptation manager, both runners and the
   simulator under ``rap up --all``, with SQLite and with Redis (append-only) knowledge:
   next plan within 2 s of the restart, 0 acknowledged writes lost, 0 plans twice;
2. ``redis``: the Redis under knowledge killed and started again: reconnects, 0
   acknowledged writes lost, 0 writes reported failed and applied;
3. ``partition``: a 5 s and a 15 s cut between two network namespaces (robot, edge):
   time to the next plan, lost liveliness and reconnects logged;
4. ``fifo``: 1 kHz events for 10 minutes into a FIFO inbox: 0 lost, RSS bounded, no
   latency drift;
5. ``fuzz``: bench/fuzz's 100 000 samples per target over mutual TLS, as an operator:
   0 crashes, the loop closes afterwards;
6. ``memory``: peers that sent 1 MiB samples killed -9 mid-stream, one after the other, 10
   per router config (Zenoh's defaults, the model's limit, shared memory off, both): a
   router as rap up configures it keeps at most 2 MiB per disconnected peer.

``--quick`` (a smoke test) runs each for a few seconds (the FIFO for 10 s, fuzz with 2 000
samples, 3 peers per router config). Writes ``bench/results/faults.json`` (``--out``)
and, on a full run of every scenario without ``--no-doc``, the faults section of
docs/reliability.md; prints the table. Exit codes: 0 every target met; 1 a target
missed or a scenario that could not be carried out (the report says which and why); 2
bad arguments.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import anyio

from ..fuzz.__main__ import portable
from ..report import RESULTS, hardware, hardware_line
from .common import say
from .fifo import run_fifo
from .fuzz_tls import run_fuzz_tls
from .kills import TARGETS, run_kills
from .memory import run_memory
from .partition import run_partition
from .redis_kill import run_redis_kill
from .report import render, write_doc

SCENARIOS = ("kills", "redis", "partition", "fifo", "fuzz", "memory")
OUT = RESULTS / "faults.json"


def _scenarios(args: argparse.Namespace) -> dict[str, Callable[[Path], Awaitable[dict[str, Any]]]]:
    q = args.quick
    return {
        "kills": lambda f: run_kills(f, backends=args.backends, targets=args.kill_targets, quick=q),
        "redis": lambda f: run_redis_kill(
            f, down=[1.0] if q else [3.0, 10.0], settle=1.0 if q else 3.0
        ),
        "partition": lambda f: run_partition(
            f, cuts=[4.0] if q else [5.0, 15.0], settle=1.0 if q else 3.0
        ),
        "fifo": lambda f: run_fifo(
            f,
            seconds=args.fifo_seconds,
            window=2.0 if q else 60.0,
            rss_every=1.0 if q else 10.0,
        ),
        "fuzz": lambda f: run_fuzz_tls(
            f, samples=args.fuzz_samples, seconds=args.fuzz_seconds, seed=args.seed
        ),
        "memory": lambda f: run_memory(f, peers=args.memory_peers, settle=1.0 if q else 5.0),
    }


def _clear(folder: Path) -> None:
    shutil.rmtree(folder, ignore_errors=True)


async def _run(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    t0 = time.monotonic()
    report: dict[str, Any] = {"quick": args.quick, "scenarios": {}}
    table = _scenarios(args)
    for name in args.only:
        folder = work / name
        await anyio.to_thread.run_sync(_clear, folder)
        start = time.monotonic()
        try:
            with anyio.fail_after(args.scenario_timeout):
                result = await table[name](folder)
        except Exception as exc:  # reported as a scenario not carried out; the others run
            say(f"{name}: NOT carried out: {type(exc).__name__}: {exc}")
            result = {"error": f"{type(exc).__name__}: {exc}", "ok": False}
        result["wall_s"] = round(time.monotonic() - start, 1)
        report["scenarios"][name] = result
        say(f"{name}: {'all targets met' if result['ok'] else 'a target MISSED'} "
            f"({result['wall_s']} s)")  # fmt: skip
    report["ok"] = all(r["ok"] for r in report["scenarios"].values())
    report["wall_seconds"] = round(time.monotonic() - t0, 1)
    return report


def _list(text: str, known: tuple[str, ...] | list[str], what: str) -> list[str]:
    items = [x.strip() for x in text.split(",") if x.strip()]
    bad = [x for x in items if x not in known]
    if bad or not items:
        raise argparse.ArgumentTypeError(
            f"{what} {text!r}: use a comma-separated list of {', '.join(known)}"
        )
    return items


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.faults", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--quick", action="store_true", help="a few seconds per scenario")
    ap.add_argument(
        "--only",
        type=lambda t: _list(t, SCENARIOS, "--only"),
        default=list(SCENARIOS),
        help=f"scenarios to run, comma-separated (default: {','.join(SCENARIOS)})",
    )
    ap.add_argument(
        "--backends",
        type=lambda t: _list(t, ("sqlite", "redis"), "--backends"),
        default=["sqlite", "redis"],
        help="knowledge backends of the kills (default: sqlite,redis)",
    )
    ap.add_argument(
        "--kill-targets",
        type=lambda t: _list(t, list(TARGETS), "--kill-targets"),
        default=None,
        help=f"processes to kill (default: {','.join(TARGETS)}; quick: knowledge,robot-runner)",
    )
    ap.add_argument("--fifo-seconds", type=float, default=None, help="default 600 (quick: 10)")
    ap.add_argument("--fuzz-samples", type=int, default=None, help="default 100000 (quick: 2000)")
    ap.add_argument("--fuzz-seconds", type=float, default=None, help="default 420 (quick: 10)")
    ap.add_argument(
        "--memory-peers",
        type=int,
        default=None,
        help="peers killed per router config (default 10; quick: 3)",
    )
    ap.add_argument("--seed", type=int, default=1, help="the fuzzer's seed")
    ap.add_argument(
        "--scenario-timeout", type=float, default=1200.0, help="s one scenario may take"
    )
    ap.add_argument("--out", type=Path, default=OUT, help="the JSON report")
    ap.add_argument(
        "--work", type=Path, default=Path("out/faults"), help="model copies, run folders, logs"
    )
    ap.add_argument("--no-doc", action="store_true", help="leave docs/reliability.md alone")
    args = ap.parse_args(argv)
    q = args.quick
    if args.kill_targets is None:
        args.kill_targets = ["knowledge", "robot-runner"] if q else list(TARGETS)
    if args.fifo_seconds is None:
        args.fifo_seconds = 10.0 if q else 600.0
    if args.fuzz_samples is None:
        args.fuzz_samples = 2_000 if q else 100_000
    if args.fuzz_seconds is None:
        args.fuzz_seconds = 10.0 if q else 420.0
    if args.memory_peers is None:
        args.memory_peers = 3 if q else 10
    if args.fifo_seconds <= 0 or args.fuzz_samples <= 0 or args.fuzz_seconds <= 0:
        ap.error("--fifo-seconds, --fuzz-samples and --fuzz-seconds must be > 0")
    if args.memory_peers < 2:
        ap.error("--memory-peers must be >= 2 (the figure is a slope)")
    hw = hardware()
    say(f"bench/faults on {hardware_line(hw)}: {', '.join(args.only)}{' (quick)' if q else ''}")
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    work = args.work.resolve()
    report = anyio.run(_run, args, work, backend_options={"use_uvloop": use_uvloop})
    report["hardware"] = hw
    report["options"] = {
        "only": args.only,
        "backends": args.backends,
        "kill_targets": args.kill_targets,
        "fifo_seconds": args.fifo_seconds,
        "fuzz_samples": args.fuzz_samples,
        "fuzz_seconds": args.fuzz_seconds,
        "memory_peers": args.memory_peers,
        "seed": args.seed,
    }
    text = render(report, hw)
    report["table"] = text.splitlines()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    body = json.dumps(report, indent=2, default=str).replace(str(work) + "/", "<work>/")
    args.out.write_text(portable(body) + "\n", encoding="utf-8")
    full = not q and set(args.only) == set(SCENARIOS) and args.fuzz_samples >= 100_000
    if full and not args.no_doc:
        write_doc(portable(text.replace(str(work) + "/", "")))
    print(text)
    say(f"written: {args.out}")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
