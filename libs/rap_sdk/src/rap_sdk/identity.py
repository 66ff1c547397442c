"""Who calls: the identities ``rap certs`` makes, requests signed with them, and the check
a receiver makes before it acts.

A Zenoh queryable cannot tell who sent a query (the router's access control says who may
send one, not who did), so a process that acts on requests (the admin verbs, the trust
checker's hot swap) checks them itself::

    signer = load_signer("certs", "alice")              # certs/alice.pem, .key, ca.pem
    signed = signer.sign(key, "pause", body)            # a rap_schemas.admin.SignedRequest
    # ... sent beside the request (a query's attachment: signer.attachment(...))

    verifier = load_verifier("certs")                   # certs/ca.pem
    caller = verifier.verify(key, "pause", body, attachment, scope="monitor")
    require_role(caller, OPERATOR, "pause monitor")     # AuthError when it is not one

The folder is what ``rap certs`` writes: ``ca.pem`` (the system's CA) and, per identity,
``<name>.pem`` and ``<name>.key`` (EC P-256). A certificate's common name is the
identity, its organizational unit the role (:data:`OPERATOR`, :data:`ROUTER`,
:data:`PROCESS`). Under ``rap up`` with TLS each process gets ``RAP_CERTS`` (the folder)
and ``RAP_AS`` (its identity): :func:`signer_from_env` and :func:`verifier_from_env`.

What is signed, with the signer's key (ECDSA with SHA-256), is the canonical encoding
(msgpack, in this order) of ``["rap.signed-request/1", target, verb, body, ts, nonce]``:
the key expression or topic the request goes to, the verb, the request's own bytes, when
it was signed (UTC ns) and 16 random bytes. :meth:`Verifier.verify` takes a request
when the certificate was issued by the CA and is valid now, the signature is good for
this target, verb and body, ``ts`` is within :data:`WINDOW_S` of the receiver's clock
and the nonce was not taken before within that window (per ``scope``: a query to
``*/status`` reaches every component of a process with the same nonce). Anything else
raises :class:`AuthError` with the reason.
"""

from __future__ import annotations

import datetime
import heapq
import os
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import msgspec
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from rap_schemas.admin import SignedRequest

from .errors import ConfigError, RapError

__all__ = [
    "AS_ENV",
    "CA_FILE",
    "CERTS_ENV",
    "MAX_NONCES",
    "MAX_SIGNED_BYTES",
    "OPERATOR",
    "PROCESS",
    "ROLES",
    "ROUTER",
    "UNAUTHENTICATED",
    "WINDOW_S",
    "AuthError",
    "Caller",
    "IdentityError",
    "SignedRequest",
    "Signer",
    "Verifier",
    "canonical",
    "load_signer",
    "load_verifier",
    "require_role",
    "signer_from_env",
    "verifier_from_env",
]

CERTS_ENV: Final = "RAP_CERTS"
"""The folder ``rap certs`` wrote (``rap up`` sets it for each process with TLS)."""
AS_ENV: Final = "RAP_AS"
"""This process's (or operator's) identity: the stem of ``<name>.pem`` in the folder."""
CA_FILE: Final = "ca.pem"
OPERATOR: Final = "operator"
"""The role of the model's ``fabric.operators``: the only one that may change things."""
ROUTER: Final = "router"
"""The role of a compute node's router."""
PROCESS: Final = "process"
"""The role of a RAP process (``edge.runner``, ``edge.manager``, ...)."""
ROLES: Final = (OPERATOR, ROUTER, PROCESS)
UNAUTHENTICATED: Final = "unauthenticated"
"""Who a request is from when it could not be authenticated (for logs and audits)."""
WINDOW_S: Final = 30.0
"""Seconds a signed request stays valid either side of the receiver's clock."""
MAX_SIGNED_BYTES: Final = 16 * 1024
"""Bytes an encoded :class:`SignedRequest` may have (a certificate is about 700)."""
MAX_NONCES: Final = 100_000
"""Nonces a verifier remembers at most (each for :data:`WINDOW_S`); past it, signed
requests are refused until older ones expire."""
DOMAIN: Final = "rap.signed-request/1"
NONCE_BYTES: Final = 16
_CACHE: Final = 256
"""Certificates a verifier keeps parsed (by their PEM text)."""

_encode = msgspec.msgpack.encode
_decode_signed = msgspec.msgpack.Decoder(SignedRequest).decode
_PEM = serialization.Encoding.PEM


class IdentityError(ConfigError):
    """Credentials that cannot be loaded (a file missing or not what it should be); the
    message names the file and how to fix it."""


class AuthError(RapError):
    """A request refused: not signed, badly signed, or its signer may not do this."""

    def __init__(self, reason: str, *, kind: str = "refused", caller: Caller | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.kind = kind
        """The reason in a few fixed words (``unsigned``, ``bad signature``, ``replayed``,
        ``not an operator``, ...): what counters count by."""
        self.caller = caller
        """Who it is from, when that was established (a signer without the role)."""


@dataclass(frozen=True, slots=True)
class Caller:
    """An authenticated identity: the certificate's common name and its role."""

    name: str
    role: str
    """:data:`OPERATOR`, :data:`ROUTER`, :data:`PROCESS`, or what the certificate's
    organizational unit says ("" when it says none)."""

    def __str__(self) -> str:
        return f"{self.name} ({self.role or 'no role'})"


def canonical(target: str, verb: str, body: bytes, ts: int, nonce: bytes) -> bytes:
    """The bytes a :class:`SignedRequest` signs (see the module docstring)."""
    return _encode([DOMAIN, target, verb, body, ts, nonce])


def _utc(when: datetime.datetime) -> str:
    return when.strftime("%Y-%m-%d %H:%M:%S UTC")


def _name_of(cert: x509.Certificate, oid: x509.ObjectIdentifier) -> str:
    attrs = cert.subject.get_attributes_for_oid(oid)
    if not attrs:
        return ""
    value = attrs[0].value
    return value if isinstance(value, str) else value.decode("utf-8", "replace")


def _caller(cert: x509.Certificate) -> Caller:
    return Caller(
        _name_of(cert, NameOID.COMMON_NAME), _name_of(cert, NameOID.ORGANIZATIONAL_UNIT_NAME)
    )


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise IdentityError(
            f"{path}: no such file ({what}) - make the certificates with `rap certs MODEL` "
            f"and give the folder it wrote (--certs DIR, or ${CERTS_ENV})"
        ) from None
    except OSError as exc:
        raise IdentityError(f"{path}: cannot read it ({exc.strerror or exc}) - {what}") from None


def _load_cert(path: Path, what: str) -> x509.Certificate:
    data = _read(path, what)
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError as exc:
        raise IdentityError(
            f"{path}: not a PEM certificate ({exc}) - {what}; make it again with `rap certs`"
        ) from None


def _key_matches(cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> bool:
    spki = serialization.PublicFormat.SubjectPublicKeyInfo
    der = serialization.Encoding.DER
    return cert.public_key().public_bytes(der, spki) == key.public_key().public_bytes(der, spki)


class Signer:
    """Signs requests as one identity (its certificate and private key)."""

    def __init__(
        self,
        certificate: x509.Certificate,
        key: ec.EllipticCurvePrivateKey,
        *,
        clock: Callable[[], int] = time.time_ns,
        source: str = "",
    ) -> None:
        if not _key_matches(certificate, key):
            raise IdentityError(
                f"{source or 'the signer'}: the private key is not the certificate's - give "
                "the .key that rap certs wrote with this .pem"
            )
        self.certificate = certificate
        self.caller = _caller(certificate)
        if not self.caller.name:
            raise IdentityError(
                f"{source or 'the signer'}: the certificate names no identity (no common "
                "name) - use one rap certs made"
            )
        self._key = key
        self._pem = certificate.public_bytes(_PEM).decode("ascii")
        self._clock = clock

    @property
    def name(self) -> str:
        return self.caller.name

    @property
    def role(self) -> str:
        return self.caller.role

    def sign(self, target: str, verb: str, body: bytes) -> SignedRequest:
        """A fresh signature of ``body`` sent to ``target`` (a key expression or topic)
        for ``verb``: a new nonce, now's time."""
        ts = self._clock()
        nonce = secrets.token_bytes(NONCE_BYTES)
        sig = self._key.sign(canonical(target, verb, body, ts, nonce), ec.ECDSA(hashes.SHA256()))
        return SignedRequest(cert=self._pem, ts=ts, nonce=nonce, sig=sig)

    def attachment(self, target: str, verb: str, body: bytes) -> bytes:
        """:meth:`sign`, encoded as a query's attachment (msgpack)."""
        return _encode(self.sign(target, verb, body))

    def __repr__(self) -> str:
        return f"Signer({self.caller})"


@dataclass(frozen=True, slots=True)
class _Known:
    """A certificate seen before: who it names and whether the CA issued it."""

    caller: Caller
    key: ec.EllipticCurvePublicKey | None
    not_before: datetime.datetime
    not_after: datetime.datetime
    problem: str = ""
    """Why it is refused whatever the time ("" when the CA issued it)."""


class Verifier:
    """Checks signed requests against a CA (see the module docstring). One per process
    is enough; ``scope`` keeps the nonces of different receivers apart."""

    def __init__(
        self,
        ca: x509.Certificate,
        *,
        window: float = WINDOW_S,
        clock: Callable[[], int] = time.time_ns,
        max_nonces: int = MAX_NONCES,
        source: str = "",
    ) -> None:
        try:
            constraints = ca.extensions.get_extension_for_class(x509.BasicConstraints).value
        except x509.ExtensionNotFound:
            constraints = None
        if constraints is None or not constraints.ca:
            raise IdentityError(
                f"{source or 'the CA'}: not a CA certificate (basic constraints say it is "
                f"not one) - give the {CA_FILE} that rap certs wrote"
            )
        self.ca = ca
        self.source = source
        self.window_ns = int(window * 1e9)
        self._clock = clock
        self._max_nonces = max_nonces
        self._seen: dict[tuple[str, bytes], int] = {}
        self._expiry: list[tuple[int, tuple[str, bytes]]] = []
        self._known: OrderedDict[str, _Known] = OrderedDict()
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"Verifier({self.source or self.ca.subject.rfc4514_string()})"

    # -- the certificate --------------------------------------------------------------

    def _examine(self, pem: str) -> _Known:
        known = self._known.get(pem)
        if known is not None:
            self._known.move_to_end(pem)
            return known
        epoch = datetime.datetime.min.replace(tzinfo=datetime.UTC)
        try:
            cert = x509.load_pem_x509_certificate(pem.encode("utf-8", "replace"))
        except ValueError as exc:
            known = _Known(
                Caller("", ""), None, epoch, epoch, f"the signer's certificate is not PEM ({exc})"
            )
        else:
            known = self._issued(cert)
        self._known[pem] = known
        if len(self._known) > _CACHE:
            self._known.popitem(last=False)
        return known

    def _issued(self, cert: x509.Certificate) -> _Known:
        caller = _caller(cert)
        key = cert.public_key()
        start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
        who = f"the certificate of {caller.name!r}" if caller.name else "the certificate"
        ca_name = self.ca.subject.rfc4514_string()
        try:
            cert.verify_directly_issued_by(self.ca)
        except (ValueError, TypeError, InvalidSignature):
            return _Known(
                caller,
                None,
                start,
                end,
                f"{who} is not issued by this system's CA ({ca_name}) - sign with a "
                "certificate rap certs made for this system",
            )
        try:
            constraints = cert.extensions.get_extension_for_class(x509.BasicConstraints).value
            is_ca = constraints.ca
        except x509.ExtensionNotFound:
            is_ca = False
        problem = ""
        if is_ca:
            problem = f"{who} is a CA's, not an identity's - sign with an identity's certificate"
        elif not caller.name:
            problem = "the certificate names no identity (no common name)"
        elif not isinstance(key, ec.EllipticCurvePublicKey):
            problem = f"{who} holds a {type(key).__name__}, not an EC key"
        else:
            try:
                usage = cert.extensions.get_extension_for_class(x509.KeyUsage).value
                if not usage.digital_signature:
                    problem = f"{who} may not sign (its key usage excludes digital signatures)"
            except x509.ExtensionNotFound:
                pass
        if problem or not isinstance(key, ec.EllipticCurvePublicKey):
            return _Known(caller, None, start, end, problem)
        return _Known(caller, key, start, end)

    # -- a request --------------------------------------------------------------------

    def verify(
        self,
        target: str,
        verb: str,
        body: bytes,
        signed: SignedRequest | bytes | None,
        *,
        scope: str = "",
    ) -> Caller:
        """The identity that signed this request for ``target`` and ``verb``; raises
        :class:`AuthError` with the reason when it is not signed, badly signed, signed
        by a certificate the CA did not issue or that is not valid now, outside the
        time window, or replayed (a nonce taken before in ``scope``)."""
        if signed is None or (isinstance(signed, bytes | bytearray) and not signed):
            raise AuthError(
                "unsigned request: this process checks who calls it (it has "
                f"${CERTS_ENV}) - sign it with a certificate of the system's CA (rap "
                f"commands: --as NAME --certs DIR, or ${AS_ENV} and ${CERTS_ENV})",
                kind="unsigned",
            )
        if not isinstance(signed, SignedRequest):
            if len(signed) > MAX_SIGNED_BYTES:
                raise AuthError(
                    f"malformed signature: {len(signed)} bytes, over {MAX_SIGNED_BYTES}",
                    kind="malformed signature",
                )
            try:
                signed = _decode_signed(bytes(signed))
            except (msgspec.DecodeError, msgspec.ValidationError) as exc:
                raise AuthError(
                    f"malformed signature: {exc} - attach a rap SignedRequest (msgpack)",
                    kind="malformed signature",
                ) from None
        size = len(signed.cert) + len(signed.sig) + len(signed.nonce)
        if size > MAX_SIGNED_BYTES:
            raise AuthError(
                f"malformed signature: {size} bytes, over {MAX_SIGNED_BYTES}",
                kind="malformed signature",
            )
        if not 8 <= len(signed.nonce) <= 64:
            raise AuthError(
                f"malformed signature: a nonce of {len(signed.nonce)} bytes (8 to 64)",
                kind="malformed signature",
            )
        now = self._clock()
        drift = (now - signed.ts) / 1e9
        if abs(now - signed.ts) > self.window_ns:
            side = "ago" if drift > 0 else "ahead of this process's clock"
            raise AuthError(
                f"signed {abs(drift):.1f} s {side}, outside the {self.window_ns / 1e9:g} s "
                "window - sign the request anew, and check that both clocks are right (NTP)",
                kind="outside the time window",
            )
        with self._lock:
            known = self._examine(signed.cert)
        if known.problem or known.key is None:
            raise AuthError(
                known.problem or "the signer's certificate cannot be used",
                kind="certificate refused",
            )
        when = datetime.datetime.fromtimestamp(now / 1e9, tz=datetime.UTC)
        name = known.caller.name
        if when < known.not_before:
            raise AuthError(
                f"the certificate of {name!r} is valid only from {_utc(known.not_before)} - "
                "check this machine's clock",
                kind="certificate not valid now",
            )
        if when > known.not_after:
            raise AuthError(
                f"the certificate of {name!r} expired at {_utc(known.not_after)} - make new "
                "ones (rap certs MODEL --force) and hand them out",
                kind="certificate not valid now",
            )
        try:
            known.key.verify(
                signed.sig,
                canonical(target, verb, body, signed.ts, signed.nonce),
                ec.ECDSA(hashes.SHA256()),
            )
        except InvalidSignature:
            raise AuthError(
                f"bad signature: {name!r} did not sign this request (signed for another "
                "key, verb or body, or altered on the way)",
                kind="bad signature",
            ) from None
        self._remember(scope, signed.nonce, signed.ts, now, known.caller)
        return known.caller

    def _remember(self, scope: str, nonce: bytes, ts: int, now: int, caller: Caller) -> None:
        key = (scope, nonce)
        with self._lock:
            seen, expiry = self._seen, self._expiry
            while expiry and expiry[0][0] < now:
                _, old = heapq.heappop(expiry)
                seen.pop(old, None)
            if key in seen:
                raise AuthError(
                    f"replayed request: {caller.name!r}'s nonce was taken already within "
                    f"{self.window_ns / 1e9:g} s - sign each request anew",
                    kind="replayed",
                    caller=caller,
                )
            if len(seen) >= self._max_nonces:
                raise AuthError(
                    f"too many signed requests: {len(seen)} within "
                    f"{self.window_ns / 1e9:g} s - retry later",
                    kind="too many requests",
                    caller=caller,
                )
            until = ts + self.window_ns
            seen[key] = until
            heapq.heappush(expiry, (until, key))


def require_role(caller: Caller, role: str, what: str) -> None:
    """Raise :class:`AuthError` unless ``caller`` has ``role``; ``what`` says what it
    asked (``pause monitor``)."""
    if caller.role == role:
        return
    has = f"role {caller.role}" if caller.role else "no role (its certificate names none)"
    raise AuthError(
        f"{caller.name!r} ({has}) may not {what}: that needs the role {role} - call it as "
        "one of the model's fabric.operators (rap ... --as NAME)",
        kind=f"not an {role}" if role[:1] in "aeiou" else f"not a {role}",
        caller=caller,
    )


# -- loading ---------------------------------------------------------------------------


def load_signer(
    folder: str | Path, name: str, *, clock: Callable[[], int] = time.time_ns
) -> Signer:
    """Identity ``name``'s signer from ``folder`` (``<name>.pem``, ``<name>.key``);
    :class:`IdentityError` saying which file is wrong and how to fix it. ``clock``: the
    wall clock its signatures are dated by (UTC ns)."""
    base = Path(folder)
    if not name or "/" in name or name in (".", ".."):
        raise IdentityError(f"identity {name!r}: give the name of a certificate in {base}")
    cert_path, key_path = base / f"{name}.pem", base / f"{name}.key"
    what = f"identity {name!r}"
    cert = _load_cert(cert_path, what)
    data = _read(key_path, f"{what}'s private key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise IdentityError(
            f"{key_path}: not an unencrypted PEM private key ({exc}) - give the .key rap "
            "certs wrote"
        ) from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise IdentityError(f"{key_path}: a {type(key).__name__}, not an EC key - use rap certs")
    return Signer(cert, key, clock=clock, source=str(cert_path))


def load_verifier(
    folder: str | Path,
    *,
    window: float = WINDOW_S,
    clock: Callable[[], int] = time.time_ns,
    max_nonces: int = MAX_NONCES,
) -> Verifier:
    """A verifier of the CA in ``folder`` (``ca.pem``); see :class:`Verifier`."""
    path = Path(folder) / CA_FILE
    ca = _load_cert(path, "the system's CA certificate")
    return Verifier(ca, window=window, clock=clock, max_nonces=max_nonces, source=str(path))


def signer_from_env() -> Signer | None:
    """The signer ``RAP_AS`` names in ``RAP_CERTS`` (None when either is unset)."""
    folder, name = os.environ.get(CERTS_ENV), os.environ.get(AS_ENV)
    if not folder or not name:
        return None
    return load_signer(folder, name)


_verifiers: dict[str, Verifier] = {}
_verifiers_lock = threading.Lock()


def verifier_from_env() -> Verifier | None:
    """The process's verifier of ``$RAP_CERTS/ca.pem`` (None when ``RAP_CERTS`` is
    unset): one per folder, so that a process's receivers share the nonces they took.
    Reads a file the first time: call it in a worker thread from an event loop."""
    folder = os.environ.get(CERTS_ENV)
    if not folder:
        return None
    with _verifiers_lock:
        verifier = _verifiers.get(folder)
        if verifier is None:
            verifier = _verifiers[folder] = load_verifier(folder)
        return verifier
