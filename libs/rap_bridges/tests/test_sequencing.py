"""The numbering that TCP and WebSocket bridges share (rap_bridges.sequencing): what a
peer writes in rap-seq and rap-ack is never trusted to be a number, a resend is passed
over once, and a frame no receiver of the spec would take is refused before it is sent."""

from __future__ import annotations

import pytest
from rap_bridges import BridgeSpec, Frame, FrameRefused, LinkContext
from rap_bridges.sequencing import HEADER_ACK, HEADER_SENDER, HEADER_SEQ, Sequencer
from rap_bridges.tcp import TcpLink
from rap_bridges.websocket import WebSocketLink

pytestmark = [pytest.mark.anyio]


class _Taken:
    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self.rejected: list[str] = []
        self.acked: list[int] = []

    async def deliver(self, frame: Frame) -> None:
        self.frames.append(frame)


async def _take(seq: Sequencer, taken: _Taken, headers: dict[str, str]) -> str | None:
    return await seq.incoming(
        dict(headers), b"x", taken.deliver, taken.rejected.append, taken.acked.append
    )


@pytest.mark.parametrize("bad", ["\u00b2", "1" * 5000, "-1", "0x10", " 7", "\uff11\uff12"])
async def test_what_is_not_a_plain_number_is_rejected_never_fatal(bad: str) -> None:
    seq, taken = Sequencer(numbered=True), _Taken()
    assert await _take(seq, taken, {HEADER_SEQ: bad, HEADER_SENDER: "a"}) is None
    assert await _take(seq, taken, {HEADER_ACK: bad}) is None
    assert taken.frames == []
    assert taken.acked == []
    assert len(taken.rejected) == 2
    assert "rap-seq header is not a number" in taken.rejected[0]
    assert "rap-ack header is not a number" in taken.rejected[1]


async def test_a_resend_is_acknowledged_again_and_passed_over() -> None:
    seq, taken = Sequencer(numbered=True), _Taken()
    for n in ("0", "1", "1", "0", "2"):
        assert await _take(seq, taken, {HEADER_SEQ: n, HEADER_SENDER: "a"}) == n
    assert len(taken.frames) == 3
    assert seq.duplicates == 2
    assert await _take(seq, taken, {HEADER_ACK: "41"}) is None
    assert taken.acked == [41]


def test_a_frame_keeps_its_number_when_sent_again() -> None:
    seq = Sequencer(numbered=True)
    first, second = Frame(b"a"), Frame(b"b")
    h1, n1 = seq.outgoing(first)
    assert (h1[HEADER_SEQ], h1[HEADER_SENDER], n1) == ("0", seq.sender, 0)
    assert seq.outgoing(first)[1] == 0  # after a reconnect: the same number
    assert seq.outgoing(second)[1] == 1
    assert Sequencer(numbered=False).outgoing(first) == ({}, -1)


@pytest.mark.parametrize(
    ("link", "url"), [(TcpLink, "tcp://127.0.0.1:9"), (WebSocketLink, "ws://127.0.0.1:9")]
)
def test_a_frame_over_max_frame_is_refused_not_sent(link: type, url: str) -> None:
    proto = "tcp" if link is TcpLink else "websocket"
    spec = BridgeSpec(protocol=proto, url=url, max_frame=1000)  # type: ignore[arg-type]
    made = link(spec, LinkContext("t", "out", reject=lambda reason: None))
    with pytest.raises(FrameRefused, match="over max_frame"):
        made._numbered(Frame(b"x" * 1001))
    with pytest.raises(FrameRefused, match="headers of"):
        made._numbered(Frame(b"x", {"h": "y" * 70_000}))
