"""What /proc says about a process (Linux): memory, CPU time, listen endpoints, and what
its log says (tracebacks, rejections, per-node counters)."""

from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import anyio
from rap_sdk.rejections import reason_kind

__all__ = ["LogFindings", "listen_endpoints", "read_log", "snapshot"]

_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


async def snapshot(pid: int) -> dict[str, Any]:
    """VmRSS, VmHWM (KiB), CPU seconds and state of ``pid`` (``alive: False`` when gone)."""
    base = anyio.Path(f"/proc/{pid}")
    try:
        status = await (base / "status").read_text()
        stat = await (base / "stat").read_text()
    except OSError:
        return {"alive": False}
    fields: dict[str, str] = {}
    for line in status.splitlines():
        k, _, v = line.partition(":")
        fields[k] = v.strip()
    after = stat.rsplit(")", 1)[1].split()
    cpu = (int(after[11]) + int(after[12])) / _TICKS  # utime, stime
    state = fields.get("State", "?")
    return {
        "alive": not state.startswith(("Z", "X")),
        "state": state,
        "rss_kib": int(fields.get("VmRSS", "0 kB").split()[0]),
        "hwm_kib": int(fields.get("VmHWM", "0 kB").split()[0]),
        "threads": int(fields.get("Threads", "0")),
        "cpu_s": round(cpu, 2),
    }


async def listen_endpoints(pid: int) -> list[str]:
    """The ``--listen`` endpoints on ``pid``'s command line (how local_deployment starts
    its processes: each listens on one free loopback port)."""
    raw = await anyio.Path(f"/proc/{pid}/cmdline").read_bytes()
    args = [a.decode() for a in raw.split(b"\0") if a]
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--listen"]


_REJECTED = re.compile(
    r" (?P<level>WARNING|INFO|ERROR) [\w.]+: (?P<who>.+?) rejected (?P<n>\d+) (?P<more>more )?"
    r"sample\(s\) on (?P<key>\S+?)(?:: (?P<reason>.*?))?(?: \(from '.*'\))?"
    r"(?: \(see the earlier reason\))?$"
)
_CHECKER_REJECT = re.compile(
    r" rejected a message on (?P<key>\S+): (?P<reason>.*?)(?: \((?P<n>\d+) so far\))?$"
)
_STOPPED = re.compile(r" (?P<node>\S+) stopped: (?P<rest>\d+ received, .*)$")
_COUNT = re.compile(r"(\d+) ([a-z][a-z/ ]*[a-z])")
_CHECKER_STOPPED = re.compile(
    r"stopped after (?P<ticks>\d+) ticks: (?P<outputs>\d+) outputs, (?P<verdicts>\d+) verdicts, "
    r"(?P<rejected>\d+) rejected, (?P<input_errors>\d+) input errors, "
    r"(?P<eval_errors>\d+) eval errors"
)
_LOST = re.compile(r"input samples lost \((?P<n>\d+) in all")
_TB_START = re.compile(r"^[ +|]*(Exception Group )?Traceback \(most recent call last\):")
_EXC_LINE = re.compile(
    r"^(?P<exc>[A-Za-z_][\w.]*(Error|Exception|Group|Exit|Interrupt|Warning)\b.*)$"
)
_HANDLER_FAILED = re.compile(r"handler (?P<handler>\S+) failed on (?P<key>\S+)")


@dataclass
class LogFindings:
    lines: int = 0
    errors: int = 0
    """Lines logged at ERROR or CRITICAL."""
    tracebacks: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Exception (its last line, numbers as N) -> count, what was logged before it, and
    the first full traceback."""
    rejected: Counter[tuple[str, str]] = field(default_factory=Counter)
    """(who, reason kind) -> samples, from the Rejections log lines."""
    checker_rejected: Counter[str] = field(default_factory=Counter)
    """Trust checker: reason kind -> the highest count it logged ("so far")."""
    node_stats: dict[str, dict[str, int]] = field(default_factory=dict)
    checker_stats: dict[str, int] = field(default_factory=dict)
    inputs_lost: int = 0
    handler_failures: Counter[str] = field(default_factory=Counter)

    def as_dict(self) -> dict[str, Any]:
        return {
            "lines": self.lines,
            "errors": self.errors,
            "tracebacks": self.tracebacks,
            "rejected_in_log": [
                {"who": w, "reason": r, "count": n} for (w, r), n in self.rejected.most_common()
            ],
            "checker_rejected_in_log": dict(self.checker_rejected.most_common()),
            "node_stats": self.node_stats,
            "checker_stats": self.checker_stats,
            "inputs_lost": self.inputs_lost,
            "handler_failures": dict(self.handler_failures.most_common()),
        }


async def read_log(path: anyio.Path | str) -> LogFindings:
    """Scan one process log."""
    out = LogFindings()
    try:
        text = await anyio.Path(path).read_text(errors="replace")
    except OSError:
        return out
    lines = text.splitlines()
    out.lines = len(lines)
    i = 0
    while i < len(lines):
        line = lines[i]
        if " ERROR " in line or " CRITICAL " in line:
            out.errors += 1
        if _TB_START.match(line):
            j = i + 1
            while j < len(lines) and (lines[j].startswith((" ", "\t")) or not lines[j].strip()):
                j += 1
            block = lines[i:j]
            if j < len(lines) and _EXC_LINE.match(lines[j]):
                block.append(lines[j])
                j += 1
            found = [m["exc"] for b in block if (m := _EXC_LINE.match(b.strip(" |+")))]
            causes = [
                f for f in found if not f.startswith(("ExceptionGroup", "BaseExceptionGroup"))
            ]
            kind = " + ".join(dict.fromkeys(reason_kind(f) for f in causes)) or reason_kind(
                block[-1]
            )
            before = lines[i - 1] if i > 0 else ""
            entry = out.tracebacks.setdefault(
                kind, {"count": 0, "logged_before": before, "traceback": "\n".join(block)}
            )
            entry["count"] += 1
            i = j
            continue
        if m := _REJECTED.search(line):
            reason = m["reason"] or "further samples rejected (see the earlier reason)"
            out.rejected[(m["who"], reason_kind(reason))] += int(m["n"])
        elif m := _CHECKER_REJECT.search(line):
            kind = reason_kind(m["reason"])
            out.checker_rejected[kind] = max(out.checker_rejected[kind], int(m["n"] or 1))
        elif m := _STOPPED.search(line):
            counts = _COUNT.findall(m["rest"])
            out.node_stats[m["node"]] = {label.replace(" ", "_"): int(n) for n, label in counts}
        elif m := _CHECKER_STOPPED.search(line):
            out.checker_stats = {k: int(v) for k, v in m.groupdict().items()}
        elif m := _LOST.search(line):
            out.inputs_lost = max(out.inputs_lost, int(m["n"]))
        if m := _HANDLER_FAILED.search(line):
            out.handler_failures[f"{m['handler']} on {m['key']}"] += 1
        i += 1
    return out
