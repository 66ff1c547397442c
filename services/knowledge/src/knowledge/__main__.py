"""``python -m knowledge``: the knowledge service on its own Zenoh session."""

from __future__ import annotations

import importlib.util
import logging
import signal
from pathlib import Path
from typing import Annotated, Literal

import anyio
import msgspec
import typer
from rap_sdk import ZenohConfig, ZenohFabric

from .app import open_service
from .config import HistoryRule, KnowledgeConfig

cli = typer.Typer(add_completion=False, help=__doc__)
Backend = Literal["memory", "sqlite", "redis"]


@cli.command()
def main(
    system: Annotated[str, typer.Option(help="System name: serves rap/<system>/kb/**.")] = "rap",
    backend: Annotated[Backend, typer.Option(help="memory, sqlite or redis.")] = "memory",
    sqlite_path: Annotated[str, typer.Option(help="SQLite file.")] = "knowledge.sqlite3",
    redis_url: Annotated[str, typer.Option(help="Redis URL.")] = "redis://127.0.0.1:6379/0",
    listen: Annotated[list[str] | None, typer.Option(help="Zenoh listen endpoint.")] = None,
    connect: Annotated[list[str] | None, typer.Option(help="Zenoh endpoint to connect.")] = None,
    history_max: Annotated[int, typer.Option(help="Versions kept per key.")] = 1000,
    config_file: Annotated[
        Path | None,
        typer.Option("--config", help="YAML KnowledgeConfig; when given, it sets everything."),
    ] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
) -> None:
    """Serve knowledge for one system until SIGTERM or SIGINT."""
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if config_file is not None:
        config = load_config(config_file)
    else:
        config = KnowledgeConfig(
            system=system,
            backend=backend,
            sqlite_path=sqlite_path,
            redis_url=redis_url,
            history=[HistoryRule(max_count=history_max)],
        )
    zconf = ZenohConfig(
        listen=listen or ["tcp/127.0.0.1:0"],
        connect=connect or [],
        query_handler_timeout=config.handler_timeout,
    )
    # uvloop when present (as node processes run): a cheaper wake-up per write received
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    anyio.run(_serve, config, zconf, backend_options={"use_uvloop": use_uvloop})


def load_config(path: Path) -> KnowledgeConfig:
    """A KnowledgeConfig from YAML; a mistake is reported with the file and field."""
    try:
        return msgspec.yaml.decode(path.read_bytes(), type=KnowledgeConfig)
    except OSError as exc:
        raise typer.BadParameter(f"cannot read {path}: {exc}") from None
    except msgspec.ValidationError as exc:
        raise typer.BadParameter(f"{path}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise typer.BadParameter(f"{path}: not valid YAML: {exc}") from None


async def _serve(config: KnowledgeConfig, zconf: ZenohConfig) -> None:
    log = logging.getLogger("knowledge")
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with ZenohFabric(zconf) as fabric, open_service(config, fabric=fabric):
            log.info("ready: system %r, %s backend", config.system, config.backend)
            print("READY", flush=True)
            async for _ in signals:
                log.info("stopping")
                break


if __name__ == "__main__":
    cli()
