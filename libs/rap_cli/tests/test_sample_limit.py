"""The model's ``fabric.max_sample_bytes``: in every Zenoh config ``rap up`` and ``rap
generate`` write, and what it does on a real router.

The router runs as ``rap up`` runs it (``python -m rap_cli.router`` with the config
``plan_run`` makes), and two sessions reach it as ``rap up``'s processes do (the node's
client config laid over a ``ZenohConfig``, as ``RAP_ZENOH_CONFIG`` makes them). Samples
go out in order on one reliable channel, so that once the last one arrived, every one
before it that was going to arrive has: a sample over the limit is shown dropped by its
absence between two that arrive, with the link still up. The router is started with the
SDK's one-thread Zenoh runtime in its environment, as a RAP process passes it on: it
must take Zenoh's own, or it cannot forward a sample of the limit's size.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
import zenoh
from rap_cli.deploy import render_zenoh, router_config
from rap_cli.generate.deploy_files import zenoh_files
from rap_cli.up import plan_run
from rap_schemas import PlanDocument, load_plan
from rap_schemas.limits import MAX_MESSAGE_BYTES, MESSAGE_HEADROOM
from rap_sdk.fabric import ZenohConfig, ZenohFabric, node_overlay
from rap_sdk.testing import OutputLines, stop_process

LIMIT = 256 << 10
MODEL = f"""\
system: limits
compute_nodes:
  edge: {{}}
fabric:
  max_sample_bytes: {LIMIT}
"""
KEY = "rap/limits/data/big"


def _doc(tmp_path: Path, text: str = MODEL) -> tuple[PlanDocument, Path]:
    path = tmp_path / "model.yaml"
    path.write_text(text, encoding="utf-8")
    return load_plan(path), path


def _json5(text: str) -> dict[str, Any]:
    """A config as RAP writes it: JSON with whole-line ``//`` comments."""
    body = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//"))
    conf: dict[str, Any] = json.loads(body)
    return conf


def test_every_generated_config_carries_the_models_limit(tmp_path: Path) -> None:
    doc, model = _doc(tmp_path)
    (run,) = plan_run(doc, model, ["edge"], tmp_path / "run")
    router, client = zenoh_files(doc.plan, "edge")
    configs = {
        "rap up's router": run.router,
        "rap up's clients": run.client,
        "the compose router": _json5(router),
        "the compose clients": _json5(client),
    }
    for what, conf in configs.items():
        zconf = zenoh.Config.from_json5(json.dumps(conf))  # as Zenoh reads it
        rx = json.loads(zconf.get_json("transport/link/rx/max_message_size"))
        assert rx == LIMIT + MESSAGE_HEADROOM, what
        # shared memory would carry a bigger sample past the limit (see the test below)
        assert json.loads(zconf.get_json("transport/shared_memory/enabled")) is False, what
    # each of rap up's processes lays the client config over its own
    session = node_overlay(ZenohConfig(), render_zenoh(run.client, title="clients"))
    rx = json.loads(session.to_json5())["transport"]["link"]["rx"]
    assert rx == {"max_message_size": LIMIT + MESSAGE_HEADROOM}
    # without the field: room for what RAP itself sends (a model-store request)
    default, _ = _doc(tmp_path, MODEL.split("fabric:")[0])
    conf = router_config(default.plan, "edge", local=["tcp/127.0.0.1:7446"])
    assert conf["transport"]["link"]["rx"]["max_message_size"] == (
        MAX_MESSAGE_BYTES + MESSAGE_HEADROOM
    )
    # shared memory: the model may turn it on (large payloads between trusted processes)
    shm, shm_model = _doc(tmp_path, MODEL + "  shared_memory: true\n")
    (shm_run,) = plan_run(shm, shm_model, ["edge"], tmp_path / "run-shm")
    shm_router, shm_client = zenoh_files(shm.plan, "edge")
    for conf in (shm_run.router, shm_run.client, _json5(shm_router), _json5(shm_client)):
        assert conf["transport"]["shared_memory"] == {"enabled": True}


@pytest.mark.anyio
@pytest.mark.zenoh
@pytest.mark.timeout(60)
async def test_a_sample_over_the_limit_is_dropped_and_the_link_survives(tmp_path: Path) -> None:
    doc, model = _doc(tmp_path)
    (run,) = plan_run(doc, model, ["edge"], tmp_path / "run")
    path = tmp_path / "router.json5"
    path.write_text(render_zenoh(run.router, title="test router"), encoding="utf-8")
    client = render_zenoh(run.client, title="test clients")
    # (size, whether it arrives), sent in this order; each payload says which it is
    sends = [
        (1_000, True),
        (LIMIT, True),  # the model's limit: taken, whatever the key and headers
        (LIMIT + MESSAGE_HEADROOM, False),  # with its headers, over Zenoh's link limit
        (2_000, True),  # the link is still up
        (4 * LIMIT, False),
        (LIMIT, True),
    ]
    # started by a RAP process, the router inherits its one-thread Zenoh runtime, which
    # would leave it no thread to send a forwarded sample this big with: it takes its own
    env = {**os.environ, "ZENOH_RUNTIME": str(ZenohConfig().runtime)}
    async with (
        await anyio.open_process(
            [sys.executable, "-m", "rap_cli.router", "--config", str(path)],
            stderr=subprocess.STDOUT,
            env=env,
        ) as proc,
        anyio.create_task_group() as tg,
    ):
        log = OutputLines(proc, timeout=20)
        tg.start_soon(log.pump)
        try:
            await log.line("listening on")
            async with (
                ZenohFabric(node_overlay(ZenohConfig(), client)) as receiver,
                ZenohFabric(node_overlay(ZenohConfig(), client)) as sender,
            ):
                sub = receiver.subscribe(KEY)
                await sender.wait_matched(KEY, timeout=20)
                for i, (size, _) in enumerate(sends):
                    await sender.publish(KEY, bytes([i]) * size)
                got: list[tuple[int, int]] = []
                with anyio.fail_after(20):
                    while not got or got[-1][0] != len(sends) - 1:
                        sample = await sub.get()
                        got.append((sample.payload[0], len(sample.payload)))
                expected = [(i, size) for i, (size, arrives) in enumerate(sends) if arrives]
                assert got == expected
                assert sender.stats.links_down == receiver.stats.links_down == 0
                assert not [line for line in log.lines if " lost " in line], log.lines
        finally:
            await stop_process(proc)
            tg.cancel_scope.cancel()
