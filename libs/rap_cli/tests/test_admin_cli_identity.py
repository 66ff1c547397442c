"""The admin commands against components whose process has identities (RAP_CERTS), as
an operator runs them (the ``rap`` command, over Zenoh on loopback): unsigned or signed
by a process, a change is refused and the command says why; signed by an operator
(``--as``/``--certs``, or ``RAP_AS``/``RAP_CERTS``) it is done. Then ``rap logs --audit``
reads who did what from the components' JSON lines file."""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

import anyio
import pytest
from rap_sdk import run_nodes
from rap_sdk.logs import LogContext, add_file_log
from rap_sdk.testing import Harness

from libs.rap_sdk.tests.certs_support import make_certs
from services.adaptation_manager.tests.loop import loop_nodes

S = "admincli"
RAP = str(Path(sys.executable).with_name("rap"))


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("RAP_CERTS", "RAP_AS")}
    env.pop("RAP_ZENOH_CONFIG", None)
    return {**env, **extra}


async def _rap(*args: str, **env: str) -> tuple[int, str, str]:
    res = await anyio.run_process([RAP, *args], check=False, env=_env(**env))
    return res.returncode, res.stdout.decode(), res.stderr.decode()


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_changes_need_an_operator_and_the_audit_says_who(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    certs = make_certs(tmp_path / "certs", {"alice": "operator", "edge.runner": "process"})
    monkeypatch.setenv("RAP_CERTS", str(certs))  # the components' process checks identities
    audit_logger = logging.getLogger("rap.audit")
    monkeypatch.setattr(audit_logger, "level", logging.INFO)
    run = tmp_path / "run"
    ctx = LogContext(system=S, compute_node="edge", process="runner")
    file = add_file_log(run / "edge" / "logs" / "runner.jsonl", ctx, logger=audit_logger)
    try:
        async with Harness(system=S, fabric="zenoh", timeout=10) as h:
            await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system=S, compute_node="edge"))
            where = ["-s", S, "-c", h.endpoint]
            code, _, err = await _rap("pause", "monitor", *where)
            assert code == 1
            assert "rap: error: pause monitor: refused: unsigned request" in err
            code, _, err = await _rap(
                "pause", "monitor", *where, "--as", "edge.runner", "--certs", str(certs)
            )
            assert code == 1
            assert "'edge.runner' (role process) may not pause monitor" in err
            code, out, err = await _rap(
                "pause", "monitor", *where, "--as", "alice", "--certs", str(certs)
            )
            assert code == 0, err
            assert out.strip() == "monitor: paused (now paused)"
            # the identity from the environment, as rap up's operators have it
            code, out, err = await _rap(
                "resume", "monitor", *where, RAP_AS="alice", RAP_CERTS=str(certs)
            )
            assert code == 0, err
            assert out.strip() == "monitor: resumed (now idle)"
            # a process may read
            code, out, err = await _rap(
                "status", *where, "--as", "edge.runner", "--certs", str(certs)
            )
            assert code == 0, err
            assert "monitor" in out
            # unsigned, every component refuses to tell, and the command says why
            code, out, err = await _rap("status", *where)
            assert code == 1
            assert "rap: warning: monitor: refused: unsigned request" in err
            # an identity that is not there: a usage error
            code, _, err = await _rap(
                "pause", "monitor", *where, "--as", "bob", "--certs", str(certs)
            )
            assert code == 2
            assert f"rap: error: --as bob: {certs / 'bob.pem'}: no such file" in err
    finally:
        file.close()

    code, out, err = await _rap("logs", "--audit", "--run-dir", str(run))
    assert code == 0, err
    lines = out.splitlines()
    assert any(
        "AUDIT    REFUSED unauthenticated: pause monitor - unsigned request" in line
        for line in lines
    ), out
    assert any(
        "AUDIT    REFUSED edge.runner (process): pause monitor - 'edge.runner'" in line
        for line in lines
    ), out
    assert any(
        "AUDIT    OK      alice (operator): pause monitor - paused" in line for line in lines
    )
    assert any(
        "AUDIT    OK      alice (operator): resume monitor - resumed" in line for line in lines
    )
    assert all("AUDIT" in line for line in lines)  # only audit records
    code, out, err = await _rap("logs", "--audit", "--json", "--run-dir", str(run))
    assert code == 0, err
    records = [json.loads(line) for line in out.splitlines()]
    ok = [r for r in records if r["result"] == "ok" and r["verb"] == "pause"]
    assert ok == [
        {
            "ts": ok[0]["ts"],
            "who": "alice",
            "role": "operator",
            "checked": True,
            "verb": "pause",
            "component": "monitor",
            "key": f"rap/{S}/admin/monitor/pause",
            "result": "ok",
            "reason": "paused",
            "system": S,
            "compute_node": "edge",
            "process": "runner",
        }
    ]
