"""``rap models list|pin|unpin|rollback`` against a running knowledge service with
identities (the system's CA), over Zenoh on loopback, as an operator runs them (the
``rap`` command): the versions with their sha256, size, creation time, tags and which is
in force; a pin, a rollback, an unpin; the errors name the fix; a process the model
grants only reading is refused; the service audits who did what."""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

import anyio
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_sdk.identity import load_signer, load_verifier
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import Harness

from libs.rap_sdk.tests.certs_support import make_certs

S = "modelscli"
RAP = str(Path(sys.executable).with_name("rap"))
MODEL = f"""\
system: {S}
compute_nodes: {{edge: {{}}}}
components:
  analysis: {{stage: analyse, node: edge, models: {{occlusion: read}}}}
fabric: {{tls: true, operators: [ops]}}
"""


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("RAP_CERTS", "RAP_AS")}
    env.pop("RAP_ZENOH_CONFIG", None)
    return {**env, **extra}


async def _rap(*args: str, **env: str) -> tuple[int, str, str]:
    res = await anyio.run_process([RAP, *args], check=False, env=_env(**env))
    return res.returncode, res.stdout.decode(), res.stderr.decode()


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_an_operator_lists_pins_and_rolls_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    certs = make_certs(tmp_path / "certs", {"ops": "operator", "edge.runner": "process"}, system=S)
    model = tmp_path / "model.yaml"
    model.write_text(MODEL)
    config = KnowledgeConfig(system=S, model_grants={"edge.runner": {"occlusion": "read"}})
    async with (
        Harness(system=S, fabric="zenoh", timeout=10) as h,
        open_service(config, fabric=h.fabric, verifier=load_verifier(certs)),
        KnowledgeClient(
            fabric=h.fabric, system=S, writer="trainer", signer=load_signer(certs, "ops")
        ) as kb,
    ):
        m1 = await kb.put_model("occlusion", b"x" * 3000, tags={"arch": "cnn", "run": "7"})
        m2 = await kb.put_model("occlusion", b"second")
        where = [str(model), "occlusion", "-c", h.endpoint]
        signed = ["--as", "ops", "--certs", str(certs)]

        # with TLS in the model, an identity is needed: the error says which to give
        code, _, err = await _rap("models", "list", *where)
        assert code == 2
        assert "give --as NAME (one of fabric.operators: ops)" in err

        code, out, err = await _rap("models", "list", *where, *signed)
        assert code == 0, err
        lines = out.splitlines()
        assert lines[0] == (
            "model occlusion: 2 version(s); in force: the latest, version 2 (none pinned)"
        )
        assert lines[1].split() == ["VERSION", "SHA256", "SIZE", "CREATED", "TAGS"]
        first, second = lines[2].split(), lines[3].split()
        assert first[:4] == ["1", m1.sha256[:12], "2.9", "KiB"]
        assert first[-1] == "arch=cnn,run=7"
        assert second[:4] == ["2", m2.sha256[:12], "6", "B"]
        assert second[-4:] == ["-", "latest", "(in", "force)"]  # no tags; the one in force
        assert lines[2].endswith("  arch=cnn,run=7")  # not in force

        # pin, then see it; the operator's identity from the environment too
        code, out, err = await _rap("models", "pin", *where, "1", *signed)
        assert code == 0, err
        assert out.strip() == "model occlusion: version 1 pinned (in force)"
        code, out, err = await _rap(
            "models", "list", *where, "--json", RAP_AS="ops", RAP_CERTS=str(certs)
        )
        assert code == 0, err
        data = json.loads(out)
        assert data["pinned"] == 1
        assert [v["version"] for v in data["versions"]] == [1, 2]
        assert data["versions"][0]["tags"] == {"arch": "cnn", "run": "7"}
        code, out, err = await _rap("models", "list", *where, *signed)
        assert "pinned (in force)" in out.splitlines()[2]

        # errors name the fix
        code, _, err = await _rap("models", "pin", *where, "9", *signed)
        assert code == 1
        assert (
            "rap: error: pin occlusion 9: model 'occlusion' has no version 9; it has [1, 2]" in err
        )
        assert f"- `rap models list {model} occlusion` shows its versions" in err
        code, _, err = await _rap("models", "pin", *where, "0", *signed)
        assert code == 2
        assert "versions count from 1" in err
        code, _, err = await _rap(
            "models", "list", str(model), "nothing", "-c", h.endpoint, *signed
        )
        assert code == 1
        assert "no model 'nothing' in the store of system 'modelscli' - put one first" in err
        code, _, err = await _rap("models", "list", str(model), "bad*name", "-c", h.endpoint)
        assert code == 2
        assert "'bad*name' is not a model name" in err
        code, _, err = await _rap("models", "rollback", *where, *signed)
        assert code == 1
        assert "nothing older than version 1 to roll back to" in err

        # a process the model grants only reading: it lists, and may not pin
        process = ["--as", "edge.runner", "--certs", str(certs)]
        code, out, err = await _rap("models", "list", *where, *process)
        assert code == 0, err
        code, _, err = await _rap("models", "pin", *where, "2", *process)
        assert code == 1
        assert "'edge.runner' may not pin model 'occlusion'" in err
        assert "models: {occlusion: write}" in err

        # unpin, pin the latest, roll back
        code, out, err = await _rap("models", "unpin", *where, *signed)
        assert code == 0, err
        assert out.strip() == "model occlusion: unpinned, the latest version is in force"
        assert (await kb.list_models("occlusion"))[1] is None
        code, out, err = await _rap("models", "rollback", *where, *signed)
        assert code == 0, err
        assert out.strip() == "model occlusion: rolled back, version 1 pinned (in force)"
        assert (await kb.get_model("occlusion"))[1] == b"x" * 3000

    records = [json.loads(r.getMessage()) for r in caplog.records if r.name == "rap.audit"]
    ops = [(r["verb"], r["reason"]) for r in records if r["who"] == "ops" and r["result"] == "ok"]
    assert ("model-pin", "pinned version 1") in ops
    assert ("model-pin", "unpinned: the latest version is in force") in ops
    assert ("model-rollback", "rolled back to version 1") in ops
    refused = [(r["who"], r["verb"]) for r in records if r["result"] == "refused"]
    assert refused == [("edge.runner", "model-pin")]
