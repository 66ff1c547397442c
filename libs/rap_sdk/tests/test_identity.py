"""rap_sdk.identity: requests signed with the certificates rap certs makes, and every way
the check refuses one (unsigned, altered, another CA, out of date, out of the window,
replayed, without the role), each with its reason."""

from __future__ import annotations

import datetime
import time
from pathlib import Path

import msgspec
import pytest
from rap_sdk.identity import (
    OPERATOR,
    AuthError,
    Caller,
    IdentityError,
    SignedRequest,
    load_signer,
    load_verifier,
    require_role,
    signer_from_env,
    verifier_from_env,
)

from libs.rap_sdk.tests.certs_support import make_certs

KEY = "rap/demo/admin/monitor/pause"
PEOPLE = {"alice": "operator", "edge.runner": "process", "edge": "router", "old": ""}


class Clock:
    def __init__(self) -> None:
        self.now = time.time_ns()

    def __call__(self) -> int:
        return self.now


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_certs(tmp_path_factory.mktemp("certs"), PEOPLE)


@pytest.fixture(scope="module")
def foreign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another CA's folder, with an 'alice' operator of its own."""
    return make_certs(tmp_path_factory.mktemp("foreign"), {"alice": "operator"})


def refused(verifier: object, *args: object, **kw: object) -> str:
    with pytest.raises(AuthError) as info:
        verifier.verify(*args, **kw)  # type: ignore[attr-defined]
    return info.value.reason


def test_a_signed_request_names_its_signer_and_role(certs: Path) -> None:
    verifier = load_verifier(certs)
    for name, role in PEOPLE.items():
        signer = load_signer(certs, name)
        assert (signer.name, signer.role) == (name, role)
        att = signer.attachment(KEY, "pause", b'{"x": 1}')
        assert verifier.verify(KEY, "pause", b'{"x": 1}', att) == Caller(name, role)
    # a Struct works as well as its bytes
    signed = load_signer(certs, "alice").sign(KEY, "pause", b"")
    assert verifier.verify(KEY, "pause", b"", signed).name == "alice"


def test_what_is_signed_cannot_be_changed(certs: Path) -> None:
    verifier = load_verifier(certs)
    signer = load_signer(certs, "alice")
    for key, verb, body in (
        ("rap/demo/admin/analysis/pause", "pause", b""),  # another component
        (KEY, "resume", b""),  # another verb
        (KEY, "pause", b"{}"),  # another body
    ):
        att = signer.attachment(KEY, "pause", b"")
        assert "bad signature: 'alice' did not sign this request" in refused(
            verifier, key, verb, body, att
        )
    good = signer.sign(KEY, "pause", b"")
    forged = msgspec.structs.replace(good, nonce=bytes(16))  # a nonce of one's own
    assert "bad signature" in refused(verifier, KEY, "pause", b"", forged)


def test_unsigned_and_malformed_requests_are_refused(certs: Path) -> None:
    verifier = load_verifier(certs)
    for nothing in (None, b""):
        reason = refused(verifier, KEY, "pause", b"", nothing)
        assert reason.startswith("unsigned request")
        assert "--as NAME --certs DIR" in reason
    assert "malformed signature" in refused(verifier, KEY, "pause", b"", b"\x93junk")
    assert "over 16384" in refused(verifier, KEY, "pause", b"", b"x" * 20_000)
    signed = load_signer(certs, "alice").sign(KEY, "pause", b"")
    short = msgspec.structs.replace(signed, nonce=b"1")
    assert "a nonce of 1 bytes" in refused(verifier, KEY, "pause", b"", short)
    not_pem = msgspec.structs.replace(signed, cert="-----BEGIN CERTIFICATE-----\nAAAA\n")
    assert "not PEM" in refused(verifier, KEY, "pause", b"", not_pem)


def test_a_certificate_of_another_ca_is_refused(certs: Path, foreign: Path) -> None:
    verifier = load_verifier(certs)
    mallory = load_signer(foreign, "alice")  # same name and role, another CA
    reason = refused(verifier, KEY, "pause", b"", mallory.attachment(KEY, "pause", b""))
    assert "the certificate of 'alice' is not issued by this system's CA" in reason
    assert "rap test CA" in reason


def test_the_ca_itself_cannot_sign_requests(certs: Path) -> None:
    verifier = load_verifier(certs)
    ca = load_signer(certs, "ca")
    assert "is a CA's, not an identity's" in refused(
        verifier, KEY, "pause", b"", ca.attachment(KEY, "pause", b"")
    )


def test_expired_and_not_yet_valid_certificates(tmp_path: Path) -> None:
    past = datetime.datetime.now(datetime.UTC) - datetime.timedelta(days=3)
    old = make_certs(tmp_path / "old", {"alice": "operator"}, valid_from=past, days=1)
    att = load_signer(old, "alice").attachment(KEY, "pause", b"")
    assert "the certificate of 'alice' expired at" in refused(
        load_verifier(old), KEY, "pause", b"", att
    )
    soon = datetime.datetime.now(datetime.UTC) + datetime.timedelta(hours=2)
    new = make_certs(tmp_path / "new", {"alice": "operator"}, valid_from=soon)
    att = load_signer(new, "alice").attachment(KEY, "pause", b"")
    assert "is valid only from" in refused(load_verifier(new), KEY, "pause", b"", att)


def test_a_request_signed_outside_the_window_is_refused(certs: Path) -> None:
    clock = Clock()
    verifier = load_verifier(certs, clock=clock)
    late = load_signer(certs, "alice", clock=lambda: clock.now - 31_000_000_000)
    early = load_signer(certs, "alice", clock=lambda: clock.now + 31_000_000_000)
    reason = refused(verifier, KEY, "pause", b"", late.attachment(KEY, "pause", b""))
    assert "signed 31.0 s ago, outside the 30 s window" in reason
    reason = refused(verifier, KEY, "pause", b"", early.attachment(KEY, "pause", b""))
    assert "31.0 s ahead of this process's clock" in reason
    near = load_signer(certs, "alice", clock=lambda: clock.now - 29_000_000_000)
    assert verifier.verify(KEY, "pause", b"", near.attachment(KEY, "pause", b"")).name == "alice"


def test_a_replayed_request_is_refused_in_its_scope_only(certs: Path) -> None:
    clock = Clock()
    verifier = load_verifier(certs, clock=clock)
    att = load_signer(certs, "alice", clock=clock).attachment(KEY, "pause", b"")
    assert verifier.verify(KEY, "pause", b"", att, scope="monitor").name == "alice"
    reason = refused(verifier, KEY, "pause", b"", att, scope="monitor")
    assert "replayed request: 'alice''s nonce was taken already within 30 s" in reason
    # the same query reaching another component of the process (a wildcard) is taken
    assert verifier.verify(KEY, "pause", b"", att, scope="analysis").name == "alice"
    # past the window it is refused for its age, and its nonce is forgotten
    clock.now += 31_000_000_000
    assert "outside the 30 s window" in refused(verifier, KEY, "pause", b"", att, scope="x")
    fresh = load_signer(certs, "alice", clock=clock).attachment(KEY, "pause", b"")
    verifier.verify(KEY, "pause", b"", fresh, scope="monitor")
    assert len(verifier._seen) == 1


def test_the_nonces_remembered_are_bounded(certs: Path) -> None:
    clock = Clock()
    verifier = load_verifier(certs, clock=clock, max_nonces=3)
    signer = load_signer(certs, "alice", clock=clock)
    for _ in range(3):
        verifier.verify(KEY, "pause", b"", signer.attachment(KEY, "pause", b""))
    reason = refused(verifier, KEY, "pause", b"", signer.attachment(KEY, "pause", b""))
    assert reason.startswith("too many signed requests: 3 within 30 s")
    clock.now += 31_000_000_000
    verifier.verify(KEY, "pause", b"", signer.attachment(KEY, "pause", b""))


def test_roles(certs: Path) -> None:
    require_role(Caller("alice", OPERATOR), OPERATOR, "pause monitor")
    with pytest.raises(AuthError) as info:
        require_role(Caller("edge.runner", "process"), OPERATOR, "pause monitor")
    assert info.value.reason == (
        "'edge.runner' (role process) may not pause monitor: that needs the role operator "
        "- call it as one of the model's fabric.operators (rap ... --as NAME)"
    )
    assert info.value.caller == Caller("edge.runner", "process")
    with pytest.raises(AuthError, match="no role"):
        require_role(Caller("old", ""), OPERATOR, "pause monitor")


def test_credentials_that_cannot_be_loaded_say_which_file_and_how(
    certs: Path, tmp_path: Path
) -> None:
    with pytest.raises(IdentityError, match=r"bob\.pem: no such file .*rap certs MODEL"):
        load_signer(certs, "bob")
    with pytest.raises(IdentityError, match=r"ca\.pem: no such file"):
        load_verifier(tmp_path)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "x.pem").write_bytes((certs / "alice.pem").read_bytes())
    (mixed / "x.key").write_bytes((certs / "edge.key").read_bytes())
    with pytest.raises(IdentityError, match="the private key is not the certificate's"):
        load_signer(mixed, "x")
    (mixed / "ca.pem").write_bytes((certs / "alice.pem").read_bytes())
    with pytest.raises(IdentityError, match="not a CA certificate"):
        load_verifier(mixed)
    (mixed / "y.pem").write_text("not a certificate")
    (mixed / "y.key").write_bytes((certs / "alice.key").read_bytes())
    with pytest.raises(IdentityError, match=r"y\.pem: not a PEM certificate"):
        load_signer(mixed, "y")
    with pytest.raises(IdentityError, match="give the name of a certificate"):
        load_signer(certs, "../alice")


def test_the_environment_names_the_folder_and_the_identity(
    certs: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("RAP_CERTS", raising=False)
    monkeypatch.delenv("RAP_AS", raising=False)
    assert signer_from_env() is None
    assert verifier_from_env() is None
    monkeypatch.setenv("RAP_CERTS", str(certs))
    assert signer_from_env() is None  # no RAP_AS: nobody to sign as
    verifier = verifier_from_env()
    assert verifier is not None
    assert verifier_from_env() is verifier  # one per folder: the nonces are shared
    monkeypatch.setenv("RAP_AS", "edge.runner")
    signer = signer_from_env()
    assert signer is not None
    att = signer.attachment(KEY, "status", b"")
    assert verifier.verify(KEY, "status", b"", att) == Caller("edge.runner", "process")


def test_the_signed_request_is_plain_msgpack(certs: Path) -> None:
    att = load_signer(certs, "alice").attachment(KEY, "pause", b"")
    plain = msgspec.msgpack.decode(att)
    assert sorted(plain) == ["cert", "nonce", "sig", "ts"]
    assert plain["cert"].startswith("-----BEGIN CERTIFICATE-----")
    assert len(plain["nonce"]) == 16
    assert msgspec.msgpack.decode(att, type=SignedRequest).ts == plain["ts"]


def test_a_signed_request_struct_is_bounded_too(certs: Path) -> None:
    verifier = load_verifier(certs)
    signed = load_signer(certs, "alice").sign(KEY, "pause", b"")
    huge = msgspec.structs.replace(signed, cert=signed.cert + " " * 20_000)
    assert "over 16384" in refused(verifier, KEY, "pause", b"", huge)
