"""``python -m knowledge``: the knowledge service on its own Zenoh session.

Backends: ``memory`` (the default) keeps everything in this process and loses every
write, acknowledged or not, when the service stops; ``sqlite`` (a file on this machine)
and ``redis`` (shared, append-only recommended) keep acknowledged writes across
restarts; ``memcached`` keeps the latest values in memcached and history, the key list
and models in the SQLite file (which refills memcached after an eviction or a restart);
``kafka`` keeps everything in the SQLite file and appends every record stored to a Kafka
topic (the knowledge stream, at least once, kept in the file's outbox while the broker is
away).
"""

from __future__ import annotations

import importlib.util
import logging
import signal
from functools import partial
from pathlib import Path
from typing import Annotated, Literal

import anyio
import msgspec
import typer
from rap_schemas.yamlconf import YamlError, load_yaml, read_text_file
from rap_sdk import FabricError, LifecycleError, ZenohConfig, ZenohFabric
from rap_sdk.entry import (
    LogFileOpt,
    LogRedisOpt,
    MetricsOpt,
    check_endpoints,
    check_system,
    fail,
    leaf,
    run_cli,
    setup_logging,
)
from rap_sdk.knowledge import SERVICE_NODE
from rap_sdk.logs import LogContext, check_redis_url, open_file_log, publish_logs
from rap_sdk.metrics import KnowledgeServiceCollector, check_metrics_option, start_metrics
from rap_sdk.peers import PeerWatch

from .adapters import kafka_store
from .adapters.memcached_store import parse_url
from .app import open_service
from .config import HistoryRule, KnowledgeConfig
from .errors import BadRequest, ServiceError

__all__ = ["MEMORY_WARNING", "cli", "load_config", "main"]

cli = typer.Typer(add_completion=False, help=__doc__, rich_markup_mode=None)
Backend = Literal["memory", "sqlite", "redis", "memcached", "kafka"]
log = logging.getLogger("knowledge")

MEMORY_WARNING = (
    "knowledge backend 'memory': every write, acknowledged or not, is lost when this "
    "service stops; use --backend sqlite or --backend redis to keep them"
)


@cli.command()
def main(
    system: Annotated[str, typer.Option(help="System name: serves rap/<system>/kb/**.")] = "rap",
    backend: Annotated[
        Backend,
        typer.Option(
            help="memory (lost on restart), sqlite (a file), redis (shared), memcached "
            "(latest values in memcached, the rest in the SQLite file) or kafka (the SQLite "
            "file, and every record stored appended to a Kafka topic)."
        ),
    ] = "memory",
    sqlite_path: Annotated[
        str, typer.Option(help="SQLite file (sqlite, kafka; memcached: history and models).")
    ] = "knowledge.sqlite3",
    redis_url: Annotated[str, typer.Option(help="Redis URL.")] = "redis://127.0.0.1:6379/0",
    memcached_url: Annotated[
        str, typer.Option(help="memcached URL: memcached://HOST[:PORT].")
    ] = "memcached://127.0.0.1:11211",
    kafka_url: Annotated[
        str, typer.Option(help="Kafka broker (kafka): kafka://HOST[:PORT].")
    ] = "kafka://127.0.0.1:9092",
    kafka_topic: Annotated[
        str | None, typer.Option(help="The knowledge stream's topic (default rap.<system>.kb).")
    ] = None,
    listen: Annotated[list[str] | None, typer.Option(help="Zenoh listen endpoint.")] = None,
    connect: Annotated[list[str] | None, typer.Option(help="Zenoh endpoint to connect.")] = None,
    history_max: Annotated[int, typer.Option(help="Versions kept per key (>= 1).")] = 1000,
    model_grants: Annotated[
        str | None,
        typer.Option(
            help="JSON: identity -> model name -> read or write, what the model store "
            "takes from whom when the service has identities (RAP_CERTS); operators may "
            "do everything. rap up derives it from the model's models: fields.",
            show_default=False,
        ),
    ] = None,
    config_file: Annotated[
        Path | None,
        typer.Option("--config", help="YAML KnowledgeConfig; when given, it sets everything."),
    ] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
    metrics: MetricsOpt = None,
    log_file: LogFileOpt = None,
    log_redis: LogRedisOpt = None,
) -> None:
    """Serve knowledge for one system until SIGTERM or SIGINT.

    The memory backend (the default) loses every write, acknowledged or not, when the
    service stops; sqlite, redis, memcached and kafka keep acknowledged writes
    (memcached: in the SQLite file, which refills memcached; kafka: in the SQLite file,
    which also sends each to the Kafka topic).

    Example: python -m knowledge --system demo --backend sqlite --metrics 127.0.0.1:9465"""
    setup_logging(log_level)
    metrics = check_metrics_option(metrics)
    log_redis = check_redis_url(log_redis)
    if config_file is not None:
        config = load_config(config_file)
    else:
        check_system(system)
        if history_max < 1:
            raise fail(f"--history-max {history_max}: keep at least 1 version per key")
        config = KnowledgeConfig(
            system=system,
            backend=backend,
            sqlite_path=sqlite_path,
            redis_url=redis_url,
            memcached_url=memcached_url,
            kafka_url=kafka_url,
            kafka_topic=kafka_topic,
            history=[HistoryRule(max_count=history_max)],
            model_grants=_grants(model_grants),
        )
    try:
        if config.backend == "memcached":
            parse_url(config.memcached_url)
        elif config.backend == "kafka":
            kafka_store.parse_url(config.kafka_url)
            kafka_store.check_topic(config.kafka_topic or kafka_store.default_topic(config.system))
    except BadRequest as exc:
        raise fail(str(exc)) from None
    zconf = ZenohConfig(
        listen=check_endpoints("--listen", listen) or ["tcp/127.0.0.1:0"],
        connect=check_endpoints("--connect", connect),
        query_handler_timeout=config.handler_timeout,
    )
    logs = LogContext(system=config.system, process="knowledge")
    open_file_log(log_file, logs)
    if config.backend == "memory":
        log.warning("%s", MEMORY_WARNING)
    # uvloop when present (as node processes run): a cheaper wake-up per write received
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    try:
        anyio.run(
            partial(_serve, logs=logs, metrics=metrics, log_redis=log_redis),
            config,
            zconf,
            backend_options={"use_uvloop": use_uvloop},
        )
    except (ServiceError, FabricError, LifecycleError, BaseExceptionGroup) as exc:
        inner = leaf(exc)
        if isinstance(inner, ServiceError):  # the store cannot be opened
            raise fail(f"{inner} - check the {config.backend} backend's settings") from None
        if isinstance(inner, FabricError):  # a listen endpoint that is taken, say
            raise fail(f"{inner} - check --listen and --connect", 1) from None
        if isinstance(inner, LifecycleError):  # a service of this system is running
            raise fail(f"{inner}", 1) from None
        raise


def _grants(text: str | None) -> dict[str, dict[str, Literal["read", "write"]]]:
    """``--model-grants``; a usage error says what is wrong."""
    if text is None:
        return {}
    try:
        return msgspec.json.decode(text, type=dict[str, dict[str, Literal["read", "write"]]])
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise fail(
            f"--model-grants: {exc} - give JSON such as "
            '{"edge.runner": {"occlusion": "write"}} (identity -> model -> read or write)'
        ) from None


def load_config(path: Path) -> KnowledgeConfig:
    """A KnowledgeConfig from YAML; a mistake is reported with file:line:col."""
    try:
        text = read_text_file(path, what="knowledge config")
        config = load_yaml(text, KnowledgeConfig, str(path), what="knowledge config")
    except YamlError as exc:
        raise fail(str(exc)) from None
    check_system(config.system, f"{path}: system")
    return config


async def _serve(
    config: KnowledgeConfig,
    zconf: ZenohConfig,
    *,
    logs: LogContext,
    metrics: str | None = None,
    log_redis: str | None = None,
) -> None:
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with (
            ZenohFabric(zconf) as fabric,
            publish_logs(fabric, logs, node=SERVICE_NODE, redis_url=log_redis),
            open_service(config, fabric=fabric) as service,
            anyio.create_task_group() as tg,
        ):
            # served from a daemon thread of its own until the process ends
            collector = KnowledgeServiceCollector(service, system=config.system)
            start_metrics(metrics, [collector], what="knowledge")
            await tg.start(PeerWatch(fabric=fabric, system=config.system, mine={"knowledge"}).run)
            log.info(
                "ready: system %r, %s backend, %s",
                config.system,
                config.backend,
                fabric.reach,
            )
            print("READY", flush=True)
            async for _ in signals:
                log.info("stopping")
                break
            tg.cancel_scope.cancel()


if __name__ == "__main__":
    run_cli(cli)
