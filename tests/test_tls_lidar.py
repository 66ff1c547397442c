"""The lidar-occlusion case with ``fabric: {tls: true}``: after ``rap certs``, ``rap up
--all`` links the edge's and the robot's routers over mutual TLS (``tls/`` endpoints,
each router presenting its compute node's certificate) and the loop still closes: an
approved verdict, and the plan at the robot. An operator reaches a router over TLS only with a
certificate of the model's CA (``rap health --as``). Without the certificates ``rap up``
refuses and says to run ``rap certs``.

The test watches as a Zenoh client of the robot's router (its loopback ``tcp/`` endpoint,
as the robot's own processes reach it).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_cli.testing import model_copy, rap_command, rap_up
from rap_schemas import Verdict, keys
from rap_sdk.fabric import CONFIG_ENV, ZenohConfig, ZenohFabric, node_overlay
from rap_sdk.testing import Harness, Record

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
PLAN_TOPIC = "tb1/spin_config"
PLAN_KEY = keys.data(SYSTEM, PLAN_TOPIC)


def _approved(r: Record) -> bool:
    """An approving verdict."""
    return r.kind is keys.Kind.EVENT and r.name == "verdict" and r.decode(Verdict[Any]).approved


def _config(path: Path) -> dict[str, Any]:
    """A Zenoh config rap up wrote (JSON with whole-line ``//`` comments)."""
    text = path.read_text()
    conf = json.loads("\n".join(x for x in text.splitlines() if not x.lstrip().startswith("//")))
    assert isinstance(conf, dict)
    return conf


def _tls_copy(folder: Path) -> Path:
    copy = model_copy(MODEL, folder)
    copy.write_text(copy.read_text() + "\nfabric:\n  tls: true\n  operators: [ops]\n")
    return copy


def test_rap_up_refuses_a_tls_model_without_certificates(tmp_path: Path) -> None:
    model = _tls_copy(tmp_path)
    out = subprocess.run(
        [rap_command(), "up", str(model), "--all", "--run-dir", str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert out.returncode == 2, out.stdout + out.stderr
    assert "rap certs" in out.stderr
    assert "robot" in out.stderr or "edge" in out.stderr
    assert not (tmp_path / "run").exists()  # nothing started, nothing written


async def test_rap_up_all_over_mutual_tls_closes_the_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = _tls_copy(tmp_path)
    certs = await anyio.run_process([rap_command(), "certs", str(model)], check=False)
    assert certs.returncode == 0, certs.stderr.decode()
    for name in ("ca", "robot", "edge", "ops"):
        assert (tmp_path / "certs" / f"{name}.pem").is_file()
    run = tmp_path / "run"
    async with rap_up(model, run) as out:
        # the routers link over TLS: the edge listens on tls/, the robot connects there
        edge = _config(run / "edge" / "zenoh-router.json5")
        robot = _config(run / "robot" / "zenoh-router.json5")
        local, *tls_listen = edge["listen"]["endpoints"]  # its own clients', the model's
        assert local.startswith("tls/127.0.0.1:"), edge["listen"]  # over TLS too
        assert len(tls_listen) == 1
        assert tls_listen[0].startswith("tls/127.0.0.1:")
        assert robot["connect"]["endpoints"] == tls_listen
        client = _config(run / "robot" / "zenoh-client.json5")
        assert client["connect"]["endpoints"][0].startswith("tls/127.0.0.1:")
        assert "connect_certificate" not in client["transport"]["link"]["tls"]  # RAP_AS
        for conf, node in ((edge, "edge"), (robot, "robot")):
            tls = conf["transport"]["link"]["tls"]
            assert tls["enable_mtls"] is True
            assert tls["listen_certificate"] == str((tmp_path / "certs" / f"{node}.pem").resolve())
        assert any("listens on" in line and "tls/127.0.0.1:" in line for line in out.lines)
        # the robot's processes reach their router over TLS, each as itself; we watch as
        # the operator
        monkeypatch.setenv(CONFIG_ENV, str(run / "robot" / "zenoh-client.json5"))
        monkeypatch.setenv("RAP_AS", "ops")
        monkeypatch.setenv("RAP_CERTS", str(tmp_path / "certs"))
        async with Harness(system=SYSTEM, fabric="zenoh", timeout=30) as h:
            anomaly = await h.expect_event("anomaly")
            # the verdict is given on the edge: it crossed the TLS link to reach us
            verdict = await h.wait_for(_approved, after=h.records.index(anomaly))
            plan = await h.expect_data(PLAN_TOPIC, after=h.records.index(verdict))
            assert plan.envelope is not None
            assert plan.envelope.source == "executor"
        # with the loop running, a process of the robot that the model does not let
        # plan or approve (the simulator's identity) forges an approval of a 50 rad/s
        # spin and puts a plan straight on spin_config: the robot's router refuses both
        # and logs them with the identity; the operator sees neither
        client_text = (run / "robot" / "zenoh-client.json5").read_text()
        forged = b'{"approved": true, "legitimator": "legitimate", "rate": 50.0}'

        def session(identity: str) -> ZenohFabric:
            env = {"RAP_AS": identity, "RAP_CERTS": str(tmp_path / "certs")}
            return ZenohFabric(node_overlay(ZenohConfig(), client_text, env=env))

        # laid over these sessions' configs, they would make both the operator
        for env in (CONFIG_ENV, "RAP_AS", "RAP_CERTS"):
            monkeypatch.delenv(env)
        async with session("ops") as ops, session("robot.robot") as rogue:
            seen = [ops.subscribe(keys.event(SYSTEM, "verdict")), ops.subscribe(PLAN_KEY)]
            for _ in range(10):
                await rogue.publish(keys.event(SYSTEM, "verdict"), forged)
                await rogue.publish(PLAN_KEY, forged)
                await anyio.sleep(0.1)
            for key in (keys.event(SYSTEM, "verdict"), PLAN_KEY):
                await out.line(f"refused: robot.robot may not put (ingress) on {key}")
            # the loop goes on (the executor's plans still arrive), and nothing forged does
            with anyio.fail_after(30):
                genuine = await seen[1].get()
            assert genuine.payload != forged
            for sub in seen:
                while (sample := sub.get_nowait()) is not None:
                    assert sample.payload != forged, "a forged message got through"

        # an operator reaches the edge's router over TLS with its certificate ...
        rap, where = rap_command(), ["--node", "edge", "--connect", tls_listen[0]]
        health = [rap, "health", str(model), *where, "--timeout", "10"]
        ok = await anyio.run_process([*health, "--as", "ops"], check=False)
        assert ok.returncode == 0, ok.stdout.decode() + ok.stderr.decode()
        assert b"alive: " in ok.stdout
        # the operate commands too: rap status over the TLS link, as the operator
        status = await anyio.run_process(
            [
                rap,
                "status",
                "--json",
                "-s",
                SYSTEM,
                "-c",
                tls_listen[0],
                "--as",
                "ops",
                "--certs",
                str(tmp_path / "certs"),
            ],
            check=False,
        )
        assert status.returncode == 0, status.stdout.decode() + status.stderr.decode()
        rows = {r["name"]: r for r in json.loads(status.stdout)}
        assert rows["analysis"]["compute_node"] == "edge"
        # ... is told to present one without it ...
        none = await anyio.run_process(health, check=False)
        assert none.returncode == 2
        assert b"--as NAME" in none.stderr
        # ... and is refused with a certificate of another CA
        other = tmp_path / "other"
        made = await anyio.run_process([rap, "certs", str(model), "-o", str(other)], check=False)
        assert made.returncode == 0, made.stderr.decode()
        refused = await anyio.run_process(
            [*health, "--as", "ops", "--certs", str(other)], check=False
        )
        assert refused.returncode == 1, refused.stdout.decode() + refused.stderr.decode()
        assert b"cannot reach the fabric" in refused.stderr
