"""The faults report: the text printed, and the section of docs/reliability.md."""

from __future__ import annotations

import re
from typing import Any

from ..fuzz.__main__ import as_markdown
from ..report import ROOT, hardware_line, table

__all__ = ["DOC", "render", "write_doc"]

DOC = ROOT / "docs" / "reliability.md"
BEGIN, END = "<!-- faults:begin -->", "<!-- faults:end -->"


def _v(x: Any, unit: str = "") -> str:
    return "-" if x is None else f"{x}{unit}"


def _ok(b: Any) -> str:
    return "pass" if b else "FAIL"


def _summary(r: dict[str, Any]) -> list[list[str]]:
    rows: list[list[str]] = []
    sc = r["scenarios"]
    if "kills" in sc:
        k = sc["kills"]
        if "error" in k:
            rows.append(["1 kill -9", "-", f"not carried out: {k['error'][:80]}", "FAIL"])
        for b, res in k.get("backends", {}).items():
            worst = max(
                (x["plan_after_restart_s"] for x in res["kills"] if x["plan_after_restart_s"]),
                default=None,
            )
            missing = [x["target"] for x in res["kills"] if x["plan_after_restart_s"] is None]
            rows += [
                [
                    f"1 kill -9 x {len(res['kills'])} ({b})",
                    "next plan <= 2 s after the restart",
                    f"worst {_v(worst, ' s')}" + (f"; none after {missing}" if missing else ""),
                    _ok(all(x["ok"] for x in res["kills"])),
                ],
                [
                    f"1 kill -9 ({b})",
                    "acknowledged writes lost: 0",
                    f"{res['writes']['acknowledged_lost']} of {res['writes']['acknowledged']:,}",
                    _ok(res["writes"]["acknowledged_lost"] == 0),
                ],
                [
                    f"1 kill -9 ({b})",
                    "plans executed twice: 0",
                    f"{res['plans']['executed_twice']} of {res['plans']['distinct_plans']} plans",
                    _ok(res["plans"]["executed_twice"] == 0),
                ],
            ]
    if "redis" in sc:
        x = sc["redis"]
        if "error" in x:
            rows.append(["2 Redis kill", "-", f"not carried out: {x['error'][:80]}", "FAIL"])
        else:
            w = x["writes"]
            back = ", ".join(_v(c["first_ack_after_back_s"], " s") for c in x["cycles"])
            rows += [
                [
                    "2 Redis kill",
                    "knowledge reconnects",
                    f"first ack {back} after",
                    _ok(x["reconnected"]),
                ],
                [
                    "2 Redis kill",
                    "acknowledged writes lost: 0",
                    f"{w['acknowledged_lost']} of {w['acknowledged']:,}",
                    _ok(w["acknowledged_lost"] == 0),
                ],
                [
                    "2 Redis kill",
                    "reported failed, applied later: 0",
                    f"{w['refused_but_applied']} of {w['outcomes'].get('refused', 0)} refused",
                    _ok(w["refused_but_applied"] == 0),
                ],
            ]
    if "partition" in sc:
        x = sc["partition"]
        if "error" in x:
            rows.append(["3 partition", "-", f"not carried out: {x['error'][:80]}", "FAIL"])
        for c in x.get("cuts", []):
            rows.append(
                [
                    f"3 partition {c['cut_s']:g} s",
                    "loop resumes; loss and return logged",
                    f"next plan {_v(c['plan_after_link_back_s'], ' s')} after the link; "
                    f"logged: {'yes' if c['logged'] else 'NO'}",
                    _ok(c["ok"]),
                ]
            )
    if "fifo" in sc:
        x = sc["fifo"]
        if "error" in x:
            rows.append(["4 FIFO 1 kHz", "-", f"not carried out: {x['error'][:80]}", "FAIL"])
        else:
            rows += [
                [
                    f"4 FIFO 1 kHz, {x['seconds']:g} s",
                    "events lost: 0",
                    f"{x['lost']} of {x['sent']:,} ({x['received']['duplicates']} twice)",
                    _ok(x["lost"] == 0 and x["received"]["duplicates"] == 0),
                ],
                [
                    "4 FIFO 1 kHz",
                    "RSS bounded",
                    f"{_v(x['rss']['start_mib'])} / {_v(x['rss']['max_mib'])} / "
                    f"{_v(x['rss']['end_mib'])} MiB (start/max/end)",
                    _ok(x["rss"]["ok"]),
                ],
                [
                    "4 FIFO 1 kHz",
                    "no latency drift",
                    _drift(x["drift"]),
                    _ok(x["drift"]["ok"]),
                ],
            ]
    if "fuzz" in sc:
        x = sc["fuzz"]
        if "error" in x:
            rows.append(
                ["5 fuzz over TLS + ACL", "-", f"not carried out: {x['error'][:80]}", "FAIL"]
            )
        else:
            rows.append(
                [
                    f"5 fuzz over TLS + ACL, {len(x['targets'])} targets"
                    f" x {x['samples_per_target']:,}",
                    "crashes: 0; loop closes after",
                    f"{len(x['crashes'])} crash(es); loop closed: "
                    f"{'yes' if x['loop_closed_after'] else 'NO'}; all sent: "
                    f"{'yes' if x['target_reached'] else 'NO'}",
                    _ok(x["ok"]),
                ]
            )
    if "memory" in sc:
        x = sc["memory"]
        if "error" in x:
            rows.append(["6 peers killed", "-", f"not carried out: {x['error'][:80]}", "FAIL"])
        else:
            v = x["variants"]

            def per(name: str) -> str:
                return _v(v[name]["per_peer_mib"] if name in v else None, " MiB")

            rows.append(
                [
                    f"6 {x['peers']} peers x {x['samples_per_peer']} x 1 MiB, killed -9",
                    f"router keeps <= {x['target_mib_per_peer']:g} MiB per peer gone",
                    f"{per('rap')} per peer (Zenoh's defaults: {per('zenoh')}; the limit "
                    f"alone: {per('limit')}; shared memory off alone: {per('no-shm')})",
                    _ok(x["ok"]),
                ]
            )
    return rows


def _memory(x: dict[str, Any]) -> list[str]:
    if "variants" not in x:
        return []
    rows = []
    for name, v in x["variants"].items():
        rss = v["rss_mib"]
        rows.append(
            [
                f"{name}: {v['what']}",
                f"{v['message_limit_bytes']:,}",
                "on" if v["shared_memory"] else "off",
                f"{rss[0]:g} / {rss[1]:g} / {rss[-1]:g} / {v['end_mib']['rss']:g}",
                _v(v["per_peer_mib"]),
                _v(v["per_peer_shmem_mib"]),
                _v(v["per_peer_anon_mib"]),
            ]
        )
    return [
        table(
            [
                "router config",
                "link message limit (bytes)",
                "shared memory",
                "router RSS MiB: before / 1st peer gone / last gone / "
                f"{next(iter(x['variants'].values()))['settle_s']:g} s later",
                "kept per peer gone MiB",
                "of it shared memory",
                "of it anonymous",
            ],
            rows,
        ),
        "",
        f"Each peer: a client of the router that published {x['samples_per_peer']} "
        f"samples of {x['sample_bytes']:,} bytes (to a receiver, another client) and got "
        "SIGKILL while still publishing; the model says max_sample_bytes: "
        f"{x['max_sample_bytes']:,}. Kept per peer gone: (RSS after the last kill - after "
        "the first) / (peers - 1).",
        "",
    ]


def _drift(d: dict[str, Any]) -> str:
    if "p50_ms" not in d:
        return f"{d['windows_compared']} full window(s): too short to tell"
    return (
        f"p50 {d['p50_ms']['first']} -> {d['p50_ms']['last']} ms, "
        f"p99 {d['p99_ms']['first']} -> {d['p99_ms']['last']} ms (first -> last window)"
    )


def _kills(k: dict[str, Any]) -> list[str]:
    out: list[str] = []
    rows = [
        [
            b,
            x["what"],
            _v(x["restart_after_s"]),
            _v(x["plan_after_restart_s"]),
            _v(x["serving_after_restart_s"]),
            _v(x["plan_after_serving_s"]),
            str(x["plans_while_down"]),
            _ok(x["ok"]),
        ]
        for b, res in k.get("backends", {}).items()
        for x in res["kills"]
    ]
    if rows:
        out += [
            table(
                [
                    "backend",
                    "killed (SIGKILL, mid-cycle)",
                    "restarted after s",
                    "next plan after restart s",
                    "serving again after restart s",
                    "plan after serving s",
                    "plans while down",
                    "<= 2 s",
                ],
                rows,
            ),
            "",
        ]
    lines = []
    for b, res in k.get("backends", {}).items():
        w, p, u = res["writes"], res["plans"], res["undisturbed"]
        failed = ", ".join(f"{k} {n}" for k, n in w["outcomes"].items() if k != "ok")
        lines.append(
            f"{b}: undisturbed loop: a plan every {_v(u.get('median_gap_s'))} s (median; "
            f"max gap {_v(u.get('max_gap_s'))} s); probe: {w['writes']:,} durable writes, "
            f"{w['acknowledged']:,} acknowledged, {w['acknowledged_lost']} of them lost; "
            f"failed {w['writes'] - w['acknowledged']} ({failed or 'none'}); "
            f"plans sent {p['plans_sent']}, distinct {p['distinct_plans']}, twice "
            f"{p['executed_twice']}"
        )
    if lines:
        out += ["\n".join(lines), ""]
    return out


def _partition(x: dict[str, Any]) -> list[str]:
    rows = []
    for c in x.get("cuts", []):
        r, e = c["robot_logs"], c["edge_logs"]
        rows.append(
            [
                f"{c['cut_s']:g} s",
                _v(c["plan_after_link_back_s"]),
                str(c["plans_while_cut"]),
                f"lost {', '.join(r['liveliness_lost']) or '-'}; back "
                f"{', '.join(r['alive_again']) or '-'}",
                f"lost {', '.join(e['liveliness_lost']) or '-'}; back "
                f"{', '.join(e['alive_again']) or '-'}",
                f"{r['router_links']['lost']}/{r['router_links']['restored']}, "
                f"{e['router_links']['lost']}/{e['router_links']['restored']}",
            ]
        )
    if not rows:
        return []
    return [
        table(
            [
                "cut",
                "next plan after the link is back s",
                "plans while cut",
                "robot runner logged",
                "edge runner logged",
                "router links lost/restored (robot, edge)",
            ],
            rows,
        ),
        "",
    ]


def _fifo(x: dict[str, Any]) -> list[str]:
    if "windows" not in x:
        return []
    rows = [
        [
            str(w["window"] + 1),
            f"{w['events']:,}",
            _v(w["p50_ms"]),
            _v(w["p99_ms"]),
            _v(w["max_ms"]),
        ]
        for w in x["windows"]
    ]
    rss = " ".join(f"{t:g}s:{m:g}" for t, m in x["rss"]["samples"])
    return [
        table([f"window ({x['window_s']:g} s)", "events", "p50 ms", "p99 ms", "max ms"], rows),
        "",
        f"FIFO inbox capacity {x['inbox']['capacity']}; sent {x['sent']:,} in "
        f"{x['send_seconds']} s (sender at most {x['worst_behind_ms']} ms behind its "
        f"schedule); handled {x['received']['handled']:,}, lost {x['lost']}, dropped by the "
        f"inbox {x['received']['dropped_by_inbox']}; receiver RSS MiB by time: {rss}",
        "",
    ]


def _fuzz(x: dict[str, Any]) -> list[str]:
    if "targets" not in x:
        return []
    prow = [
        [
            name,
            _v(None if p["rss_before_kib"] is None else round(p["rss_before_kib"] / 1024)),
            _v(None if p["rss_after_kib"] is None else round(p["rss_after_kib"] / 1024)),
            _v(None if p["peak_rss_kib"] is None else round(p["peak_rss_kib"] / 1024)),
            _v(p["cpu_s"]),
            _v(p["exit_code"]),
            str(sum(tb["count"] for tb in p["log_findings"]["tracebacks"].values())),
        ]
        for name, p in x["processes"].items()
    ]
    rej = x["rejections"]
    after = x.get("after", {})
    return [
        f"fuzz over TLS with access control (operator {x['operator']!r} on "
        f"{x['endpoint'].split(':')[0]}:...): "
        f"{len(x['targets'])} targets ({', '.join(x['targets'])}) x "
        f"{x['samples_per_target']:,} samples ({x['samples_total']:,} in all), flood "
        f"{x.get('flood_seconds')} s of a {x['seconds_budget']:g} s budget, seed {x['seed']}; "
        f"{rej['records']:,} rejection records ({sum(rej['by_reason'].values()):,} samples); "
        f"loop closed after the flood: "
        + (f"yes, {after.get('plan_after_s')} s" if x["loop_closed_after"] else "NO")
        + f"; crashes: {len(x['crashes'])}",
        "",
        table(
            ["process", "RSS before MiB", "after MiB", "peak MiB", "CPU s", "exit", "tracebacks"],
            prow,
        ),
        "",
    ]


def render(r: dict[str, Any], hw: dict[str, Any]) -> str:
    sc = r["scenarios"]
    out = [
        f"faults: {', '.join(sc)}{' (quick)' if r['quick'] else ''}; wall {r['wall_seconds']} s",
        f"on {hardware_line(hw)}",
        "",
        table(["scenario", "target", "measured", "result"], _summary(r)),
        "",
    ]
    if "kills" in sc:
        out += _kills(sc["kills"])
    if "redis" in sc and "cycles" in sc["redis"]:
        x = sc["redis"]
        w = x["writes"]
        out += [
            "Redis killed: "
            + "; ".join(
                f"down {c['down_s']:g} s, {c['failed_writes']} write(s) failed meanwhile, "
                f"first acknowledged {_v(c['first_ack_after_back_s'])} s after it was back"
                for c in x["cycles"]
            )
            + f". Probe: {w['writes']:,} durable writes, outcomes {w['outcomes']}; unsure "
            f"and stored {w['unsure_and_stored']}, unsure and not stored "
            f"{w['unsure_and_not_stored']}; knowledge logged {x['knowledge_log_redis_lines']} "
            "Redis retry line(s).",
            "",
        ]
    if "partition" in sc:
        out += _partition(sc["partition"])
    if "fifo" in sc:
        out += _fifo(sc["fifo"])
    if "fuzz" in sc:
        out += _fuzz(sc["fuzz"])
    if "memory" in sc:
        out += _memory(sc["memory"])
    out.append(f"all targets met: {'yes' if r['ok'] else 'NO'}")
    return "\n".join(out)


def write_doc(text: str) -> None:
    doc = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Reliability\n"
    block = f"{BEGIN}\n{as_markdown(text)}\n{END}"
    pattern = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
    if pattern.search(doc):
        doc = pattern.sub(lambda _: block, doc)
    else:
        doc = doc.rstrip() + "\n\n## Fault injection: last figures\n\n" + block + "\n"
    DOC.write_text(doc, encoding="utf-8")
