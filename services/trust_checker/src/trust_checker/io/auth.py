"""Who may replace the running spec: the hot swap over the fabric and over MQTT.

A checker with identities (``RAP_CERTS``, ``--certs``, or a verifier given to
:func:`trust_checker.service.open_service`) takes a new spec only from a request signed
by an ``operator`` of the system's CA (:mod:`rap_sdk.identity`):

- on the fabric, the query to ``rap/<system>/admin/<node>/swap`` carries the signature as
  its attachment, over the query's key, the verb ``swap`` and the payload (the sealed
  ``rap.TrustSpecUpdate``): :func:`fabric_swap`;
- on MQTT, the spec update carries it in its ``auth`` field, over the topic, the verb
  ``swap`` and :func:`update_body` (the update without ``auth``, as compact JSON):
  :func:`signed_update` makes the payload. A checker without identities ignores
  ``auth``, and one with identities refuses an update without it.

Every swap, refused ones included, leaves an audit record (``rap.audit``) with who asked.
"""

from __future__ import annotations

import hashlib
from typing import Final

import msgspec
from rap_schemas import TrustSpecStatus, TrustSpecUpdate
from rap_schemas.admin import SignedRequest
from rap_sdk import Fabric, Sealer
from rap_sdk.envelope import typed_decoder
from rap_sdk.errors import QueryError
from rap_sdk.identity import Signer

__all__ = [
    "SWAP_VERB",
    "SignedSpecUpdate",
    "fabric_swap",
    "outcome",
    "signed_update",
    "spec_summary",
    "update_body",
]

SWAP_VERB: Final = "swap"
_encode = msgspec.json.Encoder().encode
_open_status = typed_decoder(TrustSpecStatus)


class SignedSpecUpdate(msgspec.Struct, frozen=True, kw_only=True):
    """An MQTT spec update as the checker reads it: a ``rap.TrustSpecUpdate`` and, from
    a sender with an identity, its signature."""

    spec: str
    path: str = "<swap>"
    auth: SignedRequest | None = None


def update_body(spec: str, path: str = "<swap>") -> bytes:
    """The bytes an MQTT spec update's signature covers: the update without ``auth``."""
    return _encode(TrustSpecUpdate(spec=spec, path=path))


def signed_update(signer: Signer, topic: str, spec: str, path: str = "<swap>") -> bytes:
    """An MQTT spec update for ``topic`` (the checker's spec topic), signed by ``signer``:
    the JSON payload to publish."""
    auth = signer.sign(topic, SWAP_VERB, update_body(spec, path))
    return _encode(SignedSpecUpdate(spec=spec, path=path, auth=auth))


async def fabric_swap(
    fabric: Fabric,
    key: str,
    spec: str,
    *,
    signer: Signer | None = None,
    path: str = "<swap>",
    source: str = "operator",
    timeout: float = 10.0,
) -> TrustSpecStatus:
    """Ask the checker serving ``key`` (``rap/<system>/admin/<node>/swap``) to run
    ``spec``, signed by ``signer`` when given; its status (``ok``, or the spec's
    problems). Raises :class:`rap_sdk.QueryError` when it refuses the request (the
    reason) or does not answer."""
    payload, _ = Sealer(source).seal_message(key, TrustSpecUpdate(spec=spec, path=path))
    attachment = signer.attachment(key, SWAP_VERB, payload) if signer is not None else b""
    replies = await fabric.query(key, payload, timeout=timeout, attachment=attachment)
    if not replies:
        raise QueryError(f"no trust checker answers on {key} - is it running?")
    reply = replies[0]
    if not reply.ok:
        raise QueryError(f"{key}: {reply.payload.decode('utf-8', 'replace')}")
    try:
        status: TrustSpecStatus = _open_status(reply.payload).body
    except msgspec.DecodeError as exc:  # ValidationError is one
        raise QueryError(f"{key}: not a sealed {TrustSpecStatus.TYPE}: {exc}") from None
    return status


def spec_summary(spec: str, path: str) -> str:
    """A spec as an audit record names it: its path, size and a hash of its text."""
    digest = hashlib.sha256(spec.encode("utf-8", "replace")).hexdigest()[:16]
    return f"spec {path}: {len(spec)} characters, sha256 {digest}"


def outcome(status: TrustSpecStatus) -> tuple[str, str]:
    """An audit record's result and reason for a swap's status."""
    if status.ok:
        return "ok", (
            f"swapped at tick {status.tick}: inputs {', '.join(status.inputs) or 'none'}; "
            f"outputs {', '.join(status.outputs) or 'none'}"
        )
    more = f" (and {len(status.problems) - 3} more)" if len(status.problems) > 3 else ""
    return "error", "the spec has problems: " + "; ".join(status.problems[:3]) + more
