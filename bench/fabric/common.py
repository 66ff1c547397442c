"""What the benchmark's two processes share."""

from __future__ import annotations

import json
from typing import Any

import zenoh
from rap_schemas import Message
from rap_sdk import ZenohConfig

SYSTEM = "bench"
RAW_PING, RAW_PONG, RAW_BLAST = "bench/raw/ping", "bench/raw/pong", "bench/raw/blast"


class Blob(Message, frozen=True):
    """A benchmark payload of a chosen size."""

    TYPE = "bench.Blob/1"

    data: bytes


def raw_session(listen: list[str], connect: list[str]) -> zenoh.Session:
    conf: dict[str, Any] = {
        "mode": "peer",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": connect},
        "scouting": {"multicast": {"enabled": False}},
    }
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))


def sdk_config(connect: str, *, direct: bool = True) -> ZenohConfig:
    return ZenohConfig(connect=[connect], direct_callbacks=direct)
