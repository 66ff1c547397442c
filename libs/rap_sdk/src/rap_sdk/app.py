"""The process entry for nodes: one fabric, the nodes, SIGTERM/SIGINT handling."""

from __future__ import annotations

import importlib.util
import logging
from collections.abc import Sequence

import anyio
import zenoh

from .fabric import Fabric, MemoryFabric, ZenohConfig, ZenohFabric
from .node import Node
from .runtime import serve

__all__ = ["run"]


def run(
    nodes: Sequence[Node],
    *,
    system: str,
    zenoh_config: ZenohConfig | None = None,
    memory: bool = False,
    grace: float = 5.0,
    use_uvloop: bool = True,
) -> None:
    """Run ``nodes`` in this process until SIGTERM/SIGINT: the one Zenoh session of the
    process (or an in-process MemoryFabric with ``memory=True``), graceful stop."""
    log = logging.getLogger(__name__)
    log.info("starting %d node(s) on system %r", len(nodes), system)
    if use_uvloop and importlib.util.find_spec("uvloop") is None:
        log.info("uvloop is not installed; running on the standard asyncio loop")
        use_uvloop = False
    if not memory:
        zenoh.try_init_log_from_env()

    async def main() -> None:
        fabric: Fabric = MemoryFabric() if memory else ZenohFabric(zenoh_config)
        async with fabric:
            await serve(nodes, fabric=fabric, system=system, grace=grace)

    anyio.run(main, backend_options={"use_uvloop": use_uvloop})
