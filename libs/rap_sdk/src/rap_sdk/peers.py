"""Who else is on the fabric: a process's view of the other nodes of its system.

    watch = PeerWatch(fabric=fabric, system="demo", mine={"monitor", "analysis"})
    tg.start_soon(watch.run)

From the liveliness tokens of ``rap/<system>/alive/*``, :class:`PeerWatch` logs (rate
limited per node) and counts each node that goes away (stopped, crashed or cut off by a
partition) and each that comes back, and warns once, ``alone_after`` seconds after it
starts, when nothing else of the system is alive (a system name that nobody else uses)
or when no knowledge service is (with ``expect_knowledge``).
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import dataclass, field

import anyio
from anyio.abc import TaskStatus
from rap_schemas import keys

from .errors import LifecycleError
from .fabric import Fabric
from .rejections import Throttle

__all__ = ["PeerStats", "PeerWatch"]

log = logging.getLogger(__name__)

KNOWLEDGE = "knowledge"
"""The node name of the knowledge service."""


@dataclass(slots=True)
class PeerStats:
    lost: int = 0
    """Nodes whose liveliness went away."""
    back: int = 0
    """Nodes that came back after going away."""
    alive: set[str] = field(default_factory=set)
    """Other nodes of the system alive now."""
    warnings: list[str] = field(default_factory=list)
    """The start-up warnings given (alone, no knowledge service)."""


class PeerWatch:
    def __init__(
        self,
        *,
        fabric: Fabric,
        system: str,
        mine: Collection[str] = (),
        expect_knowledge: bool = False,
        alone_after: float = 5.0,
    ) -> None:
        """``mine``: node names of this process (not counted as others).
        ``expect_knowledge``: warn when no knowledge service is alive ``alone_after`` s
        after start."""
        keys.system_pattern(system)
        self.fabric = fabric
        self.system = system
        self.mine = frozenset(mine)
        self.expect_knowledge = expect_knowledge
        self.alone_after = alone_after
        self.stats = PeerStats()
        self._gone: set[str] = set()
        self._throttle = Throttle()

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Watch until cancelled (or the fabric closes)."""
        pattern = keys.pattern(self.system, keys.Kind.ALIVE, "*")
        with self.fabric.watch_liveliness(pattern) as watch:
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._check_later)
                task_status.started()
                while True:
                    try:
                        change = await watch.get()
                    except LifecycleError:
                        tg.cancel_scope.cancel()
                        return
                    self._change(keys.parse(change.key).name, change.alive)

    def _change(self, name: str, alive: bool) -> None:
        if name in self.mine:
            return
        st = self.stats
        if alive:
            st.alive.add(name)
            if name in self._gone:
                self._gone.discard(name)
                st.back += 1
                if self._throttle.hit(f"{name} back"):
                    log.warning("system %r: node %s is alive again", self.system, name)
            return
        st.alive.discard(name)
        self._gone.add(name)
        st.lost += 1
        if self._throttle.hit(f"{name} lost"):
            log.warning(
                "system %r: node %s lost its liveliness (stopped, crashed, or cut off from "
                "this process)",
                self.system,
                name,
            )

    async def _check_later(self) -> None:
        await anyio.sleep(self.alone_after)  # a timer: the grace given to the others
        st = self.stats
        if not st.alive:
            self._warn(
                f"system {self.system!r}: no other node has been alive for "
                f"{self.alone_after:g} s; do the other processes use the same system "
                "name, and do their Zenoh endpoints connect to this one (listen/connect)?"
            )
        elif self.expect_knowledge and KNOWLEDGE not in st.alive:
            self._warn(
                f"system {self.system!r}: no knowledge service has been alive for "
                f"{self.alone_after:g} s; reads that need the service will fail: start "
                f"one ('python -m knowledge --system {self.system}') or check its endpoints"
            )

    def _warn(self, message: str) -> None:
        self.stats.warnings.append(message)
        log.warning("%s", message)
