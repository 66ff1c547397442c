"""The admin verbs of a process with identities (RAP_CERTS): only signed requests are
taken, reads from any identity of the system's CA, changes from an operator only; every
request, refused ones included, leaves an audit record (rap.audit) with who asked."""

from __future__ import annotations

import importlib
import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from rap_schemas import LogRecord, keys
from rap_schemas.admin import AuditRecord, ComponentState, ConfigRequest
from rap_sdk.admin import _reply_decoder, audit, call
from rap_sdk.envelope import typed_decoder
from rap_sdk.identity import Caller, load_signer
from rap_sdk.logs import LogContext, publish_logs
from rap_sdk.rejections import Throttle
from rap_sdk.testing import Harness

from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = pytest.mark.anyio

SYSTEM = "admin"
PEOPLE = {"alice": "operator", "edge.runner": "process", "edge.manager": "process"}


@pytest.fixture
def nodes(monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    mod = importlib.import_module("admin_nodes")
    for v in mod.HANDLED.values():
        v.clear()
    return mod


@pytest.fixture
def certs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = make_certs(tmp_path / "certs", PEOPLE, system=SYSTEM)
    monkeypatch.setenv("RAP_CERTS", str(folder))
    monkeypatch.delenv("RAP_AS", raising=False)
    return folder


@pytest.fixture(params=["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def harness(request: pytest.FixtureRequest) -> AsyncIterator[Harness]:
    async with Harness(system=SYSTEM, fabric=request.param, timeout=10) as h:
        yield h


@pytest.fixture
def audits(caplog: pytest.LogCaptureFixture) -> list[AuditRecord]:
    """The audit records logged during the test, decoded (filled in as they come)."""
    caplog.set_level(logging.DEBUG, logger="rap.audit")

    class Records(list[AuditRecord]):
        def __getitem__(self, i: Any) -> Any:
            self._refresh()
            return super().__getitem__(i)

        def __len__(self) -> int:
            self._refresh()
            return super().__len__()

        def __iter__(self) -> Any:
            self._refresh()
            return super().__iter__()

        def _refresh(self) -> None:
            got = [
                msgspec.json.decode(r.getMessage(), type=AuditRecord)
                for r in caplog.records
                if r.name == "rap.audit"
            ]
            super().clear()
            super().extend(got)

    return Records()


async def test_unsigned_changes_are_refused_and_nothing_changes(
    certs: Path, harness: Harness, nodes: Any, audits: list[AuditRecord]
) -> None:
    group = await harness.start(nodes.v1())
    (reply,) = await call(harness.fabric, SYSTEM, "counter", "pause")
    assert not reply.ok
    assert reply.message.startswith("unsigned request: this process checks who")
    assert reply.denied
    assert not group["counter"].paused
    (reply,) = await call(harness.fabric, SYSTEM, "counter", "status")
    assert not reply.ok  # even a read needs an identity of the system
    assert reply.status is None
    (last,) = audits[-1:]
    assert (last.who, last.role, last.verb, last.result) == (
        "unauthenticated",
        "",
        "status",
        "refused",
    )
    assert last.checked
    assert [(a.verb, a.result, a.who) for a in audits] == [
        ("pause", "refused", "unauthenticated"),
        ("status", "refused", "unauthenticated"),
    ]
    assert audits[0].reason.startswith("unsigned request")
    assert audits[0].key == keys.admin(SYSTEM, "counter", "pause")
    assert audits[0].component == "counter"


async def test_a_process_may_read_but_not_change(
    certs: Path, harness: Harness, nodes: Any, audits: list[AuditRecord]
) -> None:
    group = await harness.start(nodes.v1())
    runner = load_signer(certs, "edge.runner")
    (st,) = await call(harness.fabric, SYSTEM, "*", "status", signer=runner)
    assert st.ok, st.message
    assert st.status is not None
    assert st.status.state is ComponentState.IDLE
    (got,) = await call(harness.fabric, SYSTEM, "counter", "config", signer=runner)
    assert got.ok
    assert got.config == {"step": 1, "label": "a", "limit": 10.0}
    for verb, request in (
        ("pause", None),
        ("config", ConfigRequest(values={"step": 5})),
        ("restart", None),
        ("snapshot", None),
    ):
        (no,) = await call(harness.fabric, SYSTEM, "counter", verb, request, signer=runner)
        assert not no.ok
        assert no.denied
        assert no.message == (
            f"'edge.runner' (role process) may not {verb} counter: that needs the "
            "role operator - call it as one of the model's fabric.operators (rap ... --as NAME)"
        )
    assert not group["counter"].paused
    assert group["counter"].node.config.step == 1
    assert group["counter"].restarts == 0
    assert [(a.verb, a.result, a.who, a.role) for a in audits] == [
        ("status", "ok", "edge.runner", "process"),
        ("config", "ok", "edge.runner", "process"),
        ("pause", "refused", "edge.runner", "process"),
        ("config", "refused", "edge.runner", "process"),
        ("restart", "refused", "edge.runner", "process"),
        ("snapshot", "refused", "edge.runner", "process"),
    ]
    assert audits[3].request == '{"values":{"step":5}}'


async def test_an_operator_changes_and_each_change_is_audited(
    certs: Path, harness: Harness, nodes: Any, audits: list[AuditRecord]
) -> None:
    group = await harness.start(nodes.v1())
    alice = load_signer(certs, "alice")
    (paused,) = await call(harness.fabric, SYSTEM, "counter", "pause", signer=alice)
    assert paused.ok, paused.message
    assert group["counter"].paused
    (resumed,) = await call(harness.fabric, SYSTEM, "counter", "resume", signer=alice)
    assert resumed.ok
    (bad,) = await call(
        harness.fabric,
        SYSTEM,
        "counter",
        "config",
        ConfigRequest(values={"step": "x"}),
        signer=alice,
    )
    assert not bad.ok
    assert bad.path == "$.step"
    (ok,) = await call(
        harness.fabric, SYSTEM, "counter", "config", ConfigRequest(values={"step": 3}), signer=alice
    )
    assert ok.ok
    assert group["counter"].node.config.step == 3
    rows = [(a.verb, a.result, a.who, a.role, a.reason) for a in audits]
    assert rows[0] == ("pause", "ok", "alice", "operator", "paused")
    assert rows[1] == ("resume", "ok", "alice", "operator", "resumed")
    assert rows[2][:4] == ("config", "error", "alice", "operator")
    assert "unchanged" in rows[2][4]
    assert rows[3] == ("config", "ok", "alice", "operator", "set step")
    assert all(a.checked and a.via == "fabric" and a.ts > 0 for a in audits)


async def test_forged_and_replayed_signatures_are_refused(
    certs: Path, tmp_path: Path, harness: Harness, nodes: Any, audits: list[AuditRecord]
) -> None:
    group = await harness.start(nodes.v1())
    other = make_certs(tmp_path / "other", {"alice": "operator"})
    mallory = load_signer(other, "alice")  # an operator of another CA, named alice
    (no,) = await call(harness.fabric, SYSTEM, "counter", "pause", signer=mallory)
    assert not no.ok
    assert "the certificate of 'alice' is not issued by this system's CA" in no.message
    # a request of the real alice, signed for resume, sent as a pause
    key = keys.admin(SYSTEM, "counter", "pause")
    alice = load_signer(certs, "alice")
    wrong = alice.attachment(keys.admin(SYSTEM, "counter", "resume"), "resume", b"")
    (r,) = await harness.fabric.query(key, b"", attachment=wrong, timeout=5)
    assert "bad signature" in _reply_decoder.decode(r.payload).message
    # a good one, then the same bytes again
    att = alice.attachment(key, "pause", b"")
    (first,) = await harness.fabric.query(key, b"", attachment=att, timeout=5)
    assert _reply_decoder.decode(first.payload).ok
    (again,) = await harness.fabric.query(key, b"", attachment=att, timeout=5)
    assert _reply_decoder.decode(again.payload).message.startswith("replayed request")
    assert group["counter"].paused  # by the good one only
    assert [(a.result, a.who) for a in audits] == [
        ("refused", "unauthenticated"),
        ("refused", "unauthenticated"),
        ("ok", "alice"),
        ("refused", "alice"),  # the replay: alice's signature, taken once
    ]


async def test_a_process_whose_ca_cannot_be_read_refuses_everything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, harness: Harness, nodes: Any
) -> None:
    good = make_certs(tmp_path / "good", PEOPLE)
    monkeypatch.setenv("RAP_CERTS", str(tmp_path / "missing"))
    group = await harness.start(nodes.v1())
    (no,) = await call(
        harness.fabric, SYSTEM, "counter", "pause", signer=load_signer(good, "alice")
    )
    assert not no.ok
    assert "this process cannot check who calls it" in no.message
    assert "ca.pem: no such file" in no.message
    assert not group["counter"].paused


async def test_without_identities_everything_is_taken_and_audited_as_unchecked(
    monkeypatch: pytest.MonkeyPatch, harness: Harness, nodes: Any, audits: list[AuditRecord]
) -> None:
    monkeypatch.delenv("RAP_CERTS", raising=False)
    group = await harness.start(nodes.v1())
    (reply,) = await call(harness.fabric, SYSTEM, "counter", "pause")
    assert reply.ok
    assert group["counter"].paused
    (rec,) = audits
    assert (rec.who, rec.checked, rec.result, rec.verb) == ("unauthenticated", False, "ok", "pause")


async def test_audit_records_reach_the_fabric_log_stream(
    certs: Path, nodes: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    opened = typed_decoder(LogRecord)
    async with Harness(system=SYSTEM, timeout=10) as h:
        await h.start(nodes.v1())
        ctx = LogContext(system=SYSTEM, process="runner")
        monkeypatch.setattr(logging.getLogger("rap.audit"), "level", logging.INFO)
        with h.fabric.subscribe(keys.pattern(SYSTEM, keys.Kind.LOG)) as sub:
            async with publish_logs(h.fabric, ctx, node="runner"):
                no = await call(h.fabric, SYSTEM, "counter", "pause")
                assert not no[0].ok
                with anyio.fail_after(5):
                    while True:
                        env = opened((await sub.get()).payload)
                        if env.body.logger == "rap.audit":
                            break
    line = env.body
    assert line.level == "WARNING"
    assert line.component == "counter"
    rec = msgspec.json.decode(line.message, type=AuditRecord)
    assert (rec.who, rec.verb, rec.result) == ("unauthenticated", "pause", "refused")


def test_a_flood_of_refusals_is_recorded_once_a_second_with_a_count(
    audits: list[AuditRecord],
) -> None:
    now = [0]
    throttle = Throttle(now_ns=lambda: now[0])

    def refuse(kind: str, who: Caller | None = None) -> None:
        audit(
            verb="pause",
            component="counter",
            result="refused",
            caller=who,
            checked=True,
            reason=f"{kind}: ...",
            kind=kind,
            throttle=throttle,
        )

    for _ in range(50):
        refuse("unsigned")
    refuse("bad signature")  # another kind: recorded at once
    refuse("not an operator", Caller("edge.runner", "process"))  # another caller too
    now[0] += 1_000_000_001
    refuse("unsigned")  # a second later: recorded, with the 49 it stands for
    audit(verb="pause", component="counter", result="ok", caller=None, checked=True)
    assert [(a.result, a.reason.split(":")[0], a.repeated) for a in audits] == [
        ("refused", "unsigned", 0),
        ("refused", "bad signature", 0),
        ("refused", "not an operator", 0),
        ("refused", "unsigned", 49),
        ("ok", "", 0),  # what is done is never throttled
    ]
