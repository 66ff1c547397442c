"""A node in its own OS process for the two-process test: echoes ``ping`` to ``pong``.

python peer_echo.py <zenoh endpoint to connect to> <system>
"""

from __future__ import annotations

import logging
import sys

from rap_schemas import LaserScan
from rap_sdk import Context, Node, ZenohConfig, run

echo = Node("echo", stage="monitor")


@echo.on_data("ping")
async def ping(ctx: Context, scan: LaserScan) -> None:
    await ctx.publish("pong", scan)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    run([echo], system=sys.argv[2], zenoh_config=ZenohConfig(connect=[sys.argv[1]]))
