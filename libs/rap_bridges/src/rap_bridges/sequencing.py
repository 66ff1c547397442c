"""At least once on the wire, once on the fabric, for links whose frames carry a header
map and that acknowledge frames themselves (TCP frames, WebSocket messages).

A sender at QoS >= 1 numbers each frame (``rap-seq``, growing, with its ``rap-sender``
id) and sends one at a time until it is acknowledged; after a reconnect it sends the
unacknowledged frame again under the same number. A receiver acknowledges each
numbered frame (``rap-ack``) once the bridge has taken it (or it was rejected for good)
and passes over a number it already took from that sender.
"""

from __future__ import annotations

import os
from collections.abc import Awaitable, Callable, Collection
from typing import Final, TypeVar

import anyio

from .core import Deliver, Frame, LinkDown

__all__ = [
    "HEADER_ACK",
    "HEADER_SENDER",
    "HEADER_SEQ",
    "MAX_SENDERS",
    "Acks",
    "Sequencer",
    "to_every_peer",
]

P = TypeVar("P")

HEADER_SEQ: Final = "rap-seq"
HEADER_SENDER: Final = "rap-sender"
HEADER_ACK: Final = "rap-ack"
MAX_SENDERS: Final = 4096
"""Senders whose last frame number is remembered (for passing over resent frames)."""


def _number(text: str) -> int | None:
    """A frame number as the other side wrote it: ASCII digits, at most 19 (an int64);
    None for anything else (``"²".isdigit()`` holds, and ``int`` of 5,000 digits
    raises: neither may end the link)."""
    if not (text.isascii() and text.isdigit() and len(text) <= 19):
        return None
    return int(text)


class Sequencer:
    """One link's numbering (sending) and its memory of what it took (receiving)."""

    __slots__ = ("_last", "_seen", "_seq", "duplicates", "numbered", "sender")

    def __init__(self, *, numbered: bool) -> None:
        self.numbered = numbered
        """Whether outgoing frames are numbered (QoS >= 1)."""
        self.sender = os.urandom(8).hex()
        """This link's ``rap-sender`` id."""
        self.duplicates = 0
        """Numbered frames received again (a resend after a reconnect) and passed over."""
        self._seq = -1
        self._last: tuple[Frame, int] | None = None
        self._seen: dict[str, int] = {}

    def outgoing(self, frame: Frame) -> tuple[dict[str, str], int]:
        """The headers to send ``frame`` with, and its number (-1: not numbered). The
        same frame object sent again (after a reconnect) keeps its number."""
        headers = dict(frame.headers)
        if not self.numbered:
            return headers, -1
        last = self._last
        if last is not None and last[0] is frame:
            seq = last[1]
        else:
            self._seq += 1
            seq = self._seq
            self._last = (frame, seq)
        headers[HEADER_SEQ] = str(seq)
        headers[HEADER_SENDER] = self.sender
        return headers, seq

    async def incoming(
        self,
        headers: dict[str, str],
        payload: bytes,
        deliver: Deliver,
        reject: Callable[[str], None],
        acked: Callable[[int], None],
    ) -> str | None:
        """Take one received frame: an acknowledgement goes to ``acked``, a frame to
        ``deliver`` (once per sender and number), a bad number to ``reject``. Returns the
        number to acknowledge to the other side, or None."""
        ack = headers.get(HEADER_ACK)
        if ack is not None:
            number = _number(ack)
            if number is not None:
                acked(number)
            else:
                reject(f"{HEADER_ACK} header is not a number: {ack[:40]!r}")
            return None
        seq_text = headers.pop(HEADER_SEQ, None)
        sender = headers.pop(HEADER_SENDER, "")
        if seq_text is None:
            await deliver(Frame(payload, headers))
            return None
        seq = _number(seq_text)
        if seq is None:
            reject(f"{HEADER_SEQ} header is not a number: {seq_text[:40]!r}")
            return None
        seen = self._seen
        if seq <= seen.get(sender, -1):
            self.duplicates += 1
        else:
            await deliver(Frame(payload, headers))
            seen.pop(sender, None)  # the most recent sender last: the oldest goes first
            if len(seen) >= MAX_SENDERS:
                del seen[next(iter(seen))]
            seen[sender] = seq
        return seq_text


class Acks:
    """What one peer has acknowledged; a sender waits here for its frame's number."""

    __slots__ = ("_changed", "acked", "gone")

    def __init__(self) -> None:
        self.acked = -1
        self.gone = False
        self._changed: anyio.Event | None = None  # made on the event loop, when waited on

    def _wake(self) -> None:
        if self._changed is not None:
            self._changed.set()
            self._changed = None

    def ack(self, seq: int) -> None:
        if seq > self.acked:
            self.acked = seq
            self._wake()

    def leave(self) -> None:
        """The peer is gone: a sender waiting for it stops waiting."""
        self.gone = True
        self._wake()

    async def wait(self, seq: int, name: str, timeout: float) -> None:
        """Until ``seq`` is acknowledged; :class:`LinkDown` if the peer leaves first or
        does not acknowledge within ``timeout`` s."""
        with anyio.move_on_after(timeout):
            while self.acked < seq:
                if self.gone:
                    raise LinkDown(f"{name} left before acknowledging frame {seq}")
                if self._changed is None:
                    self._changed = anyio.Event()
                await self._changed.wait()
            return
        raise LinkDown(
            f"{name} did not acknowledge frame {seq} within {timeout:g} s",
            "is the peer reading, and does it answer rap-seq with rap-ack?",
        )


async def to_every_peer(
    peers: Collection[P],
    send: Callable[[P], Awaitable[None]],
    drop: Callable[[P, LinkDown], Awaitable[None]],
    wait_for_one: Callable[[], Awaitable[None]],
) -> None:
    """A serving link's send: to every peer connected (each that fails is dropped),
    waiting for one while there is none, until at least one took it."""
    while True:
        while not peers:
            await wait_for_one()
        sent = 0
        for peer in list(peers):
            try:
                await send(peer)
                sent += 1
            except LinkDown as exc:
                await drop(peer, exc)
        if sent:
            return
