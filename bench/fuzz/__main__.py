"""``python -m bench.fuzz [--seconds S] [--samples N] [--seed K]``: a bounded fuzz run
against a running lidar-occlusion loop (bench/fuzz/run.py says how).

Writes ``bench/results/fuzz.json`` (``--out``) and, on a full run (``--samples`` of at
least 100 000 and no ``--no-doc``), the figures section of docs/reliability.md; prints a
table. Exit codes: 0 all well; 1 a crash (a process died or stopped answering) or the
loop did not close after the flood; 3 the samples could not all be sent within the time
bound (the machine is too slow for ``--samples`` in ``--seconds``); 2 bad arguments.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import re
import sys
from pathlib import Path
from typing import Any

import anyio
from lidar_occlusion.demo import default_plan_path
from trust_checker.specs import MAPLEK_OUTPUTS

from ..report import ROOT, hardware, hardware_line, table
from .run import Options, run

RESULTS = ROOT / "bench" / "results" / "fuzz.json"
DOC = ROOT / "docs" / "reliability.md"
FULL = 100_000


def _mib(kib: int | None) -> str:
    return "-" if kib is None else f"{kib / 1024:.0f}"


def render(r: dict[str, Any], hw: dict[str, Any]) -> str:
    targets = r.get("targets", {})
    out = [
        f"fuzz: {len(targets)} targets x {r['samples_per_target']:,} samples "
        f"({r['samples_total']:,} in all), flood {r.get('flood_seconds', '-')} s of a "
        f"{r['seconds_budget']:g} s budget, seed {r['seed']}; wall {r['wall_seconds']} s",
        f"on {hardware_line(hw)}",
        "",
    ]
    rows = []
    for name, t in targets.items():
        replies = ", ".join(f"{k} {v:,}" for k, v in list(t.get("replies", {}).items())[:4])
        rows.append([f"`{name}`", t["kind"], f"{t['sent']:,}", t["mib"], replies or "-"])
    out += [table(["target", "kind", "sent", "MiB", "replies / publish errors"], rows), ""]
    prow = []
    for name, p in r["processes"].items():
        lf = p["log_findings"]
        prow.append(
            [
                name,
                _mib(p["rss_before_kib"]),
                _mib(p["rss_after_kib"]),
                _mib(p["peak_rss_kib"]),
                "-" if p["cpu_s"] is None else p["cpu_s"],
                "-" if p.get("cpu_s_while_closing") is None else p["cpu_s_while_closing"],
                p["exit_code"],
                sum(tb["count"] for tb in lf["tracebacks"].values()),
            ]
        )
    out += [
        table(
            [
                "process",
                "RSS before MiB",
                "after MiB",
                "peak MiB",
                "CPU s",
                "CPU s closing",
                "exit",
                "tracebacks",
            ],
            prow,
        ),
        "",
    ]
    nrows = []
    for name, p in r["processes"].items():
        for node, st in p["log_findings"]["node_stats"].items():
            nrows.append(
                [
                    f"{node}@{name}",
                    f"{st.get('received', 0):,}",
                    f"{st.get('handled', 0):,}",
                    f"{st.get('failed', 0):,}",
                    f"{st.get('rejected', 0):,}",
                    f"{st.get('dropped_by_a_full_inbox', 0):,}",
                ]
            )
    if nrows:
        out += [
            table(
                ["node", "received", "handled", "failed", "rejected", "dropped (inbox full)"], nrows
            ),
            "",
        ]
    crashes = r["crashes"]
    out.append(f"crashes: {len(crashes)}")
    for c in crashes:
        desc = {k: v for k, v in c.items() if k not in ("tracebacks", "last_samples")}
        out.append(f"  - {json.dumps(desc)}")
        out += [f"      {tb['count']} x {kind}" for kind, tb in c.get("tracebacks", {}).items()]
    rej = r["rejections"]
    out += [
        "",
        f"rejections by reason ({rej['records']:,} rap.Rejection records on log/**; "
        f"{sum(rej['by_reason'].values()):,} samples):",
    ]
    out += [f"  {n:>9,}  {k[:100]}" for k, n in list(rej["by_reason"].items())[:25]]
    if rej["from_logs"]:
        out.append("rejected by readers that publish no records (their log lines):")
        out += [
            f"  {e['count']:>9,}  {e['who']}: {e['reason'][:90]}" for e in rej["from_logs"][:20]
        ]
    for name, p in r["processes"].items():
        cs = p["log_findings"]["checker_stats"]
        if cs:
            out.append(
                f"  {name}: {cs['rejected']:,} rejected, {cs['ticks']:,} ticks, "
                f"{p['log_findings']['inputs_lost']:,} inputs lost (inbox full)"
            )
    after = r.get("after", {})
    out += [
        "",
        "loop closed after the flood: "
        + (
            f"yes, {after.get('plan_after_s')} s after the first scan ({after.get('scans')} scans)"
            if r["loop_closed_after"]
            else f"NO (within {after.get('seconds')} s, {after.get('scans')} scans)"
        ),
        f"every target got {r['samples_per_target']:,} samples: "
        + ("yes" if r["target_reached"] else "NO (the time bound ran out)"),
    ]
    return "\n".join(out)


def portable(text: str) -> str:
    """``text`` with this machine's paths (the checkout, the Python installation) cut out:
    paths relative to the repository, ``<python>/...`` for the interpreter's."""
    return text.replace(str(ROOT) + "/", "").replace(sys.base_prefix, "<python>")


def as_markdown(text: str) -> str:
    """The printed report as markdown: its tables as they are, the rest fenced."""
    parts = []
    for block in text.strip().split("\n\n"):
        if block.startswith("|"):
            parts.append(block)
        else:
            parts.append(f"```text\n{block}\n```")
    return "\n\n".join(parts)


def write_doc(text: str) -> None:
    begin, end = "<!-- fuzz:begin -->", "<!-- fuzz:end -->"
    doc = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Reliability\n"
    block = f"{begin}\n{as_markdown(text)}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    doc = (
        pattern.sub(lambda _: block, doc)
        if pattern.search(doc)
        else doc.rstrip() + "\n\n" + block + "\n"
    )
    DOC.write_text(doc, encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.fuzz", description=__doc__)
    ap.add_argument("--seconds", type=float, default=420.0, help="flood time bound (s)")
    ap.add_argument("--samples", type=int, default=FULL, help="samples per target")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--plan", type=Path, default=None, help="deployment plan (default: demo)")
    ap.add_argument(
        "--specs",
        default="stage_order,unread_overwrite",
        help="MAPLE-K specs, one trust checker process each (comma-separated; all: "
        + ",".join(sorted(MAPLEK_OUTPUTS))
        + ")",
    )
    ap.add_argument(
        "--close-timeout", type=float, default=120.0, help="s the loop has to close after the flood"
    )
    ap.add_argument("--out", type=Path, default=RESULTS, help="the JSON report")
    ap.add_argument("--logs", type=Path, default=Path("out/fuzz/logs"), help="process logs")
    ap.add_argument("--no-doc", action="store_true", help="leave docs/reliability.md alone")
    args = ap.parse_args(argv)
    if args.seconds <= 0 or args.samples <= 0:
        ap.error("--seconds and --samples must be > 0")
    logging.basicConfig(level="WARNING", format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    opts = Options(
        plan=args.plan or default_plan_path("demo"),
        seconds=args.seconds,
        samples=args.samples,
        seed=args.seed,
        specs=[s for s in args.specs.split(",") if s],
        logs=args.logs,
        close_timeout=args.close_timeout,
    )
    hw = hardware()
    print(f"bench/fuzz on {hardware_line(hw)}", file=sys.stderr)
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    report = anyio.run(run, opts, backend_options={"use_uvloop": use_uvloop})
    report["hardware"] = hw
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        portable(json.dumps(report, indent=2, default=str)) + "\n", encoding="utf-8"
    )
    text = render(report, hw)
    if not args.no_doc and args.samples >= FULL:
        write_doc(text)
    print(text)
    print(f"written: {args.out}", file=sys.stderr)
    if report["crashes"] or not report["loop_closed_after"]:
        return 1
    if not report["target_reached"]:
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
