"""Seeded mutations of valid samples.

A :class:`Mutator` belongs to one target (a key or queryable) and draws everything from
its own ``random.Random(seed/target)``: the sequence of mutations and their positions is
the same on every run with the same seed (only ``uid`` and ``ts`` follow the clock).

Each sample starts from a valid message of the target's wire type, sealed in a valid
envelope (or, for knowledge requests, the plain request), and gets one mutation:

======================  =============================================================
mutation                what
======================  =============================================================
``bitflip``             1..8 random bits of the encoded sample flipped
``truncate``            cut at a random byte
``insert``              1..32 random bytes inserted at a random position
``delete``              1..32 bytes deleted at a random position
``wrong_type``          the envelope's ``type`` replaced (another wire type, another
                        version, empty, 1000 characters); for a request, its ``op``
``deep_nest``           the body, a field, a ``ctx`` value or the whole sample replaced
                        by nested arrays or maps, depth 100..100000
``huge_claim``          the same places replaced by an array, map, str, bin or ext
                        header that claims 2^32-1 (or 2^31) items and carries a few
``huge_real``           a field or the body replaced by a real array, map, str or bin
                        of 1k..5M bytes (some over the 4 MiB sample limit)
``nonfinite``           1..3 floats of the body set to NaN, inf or -inf (a float may be
                        a beam of a packed float32 array such as a scan's ``ranges``)
``packed``              a packed per-beam array (``ranges``: float32, ``occluded``: a
                        byte per flag) damaged: bytes flipped, cut or grown to a length
                        that is no whole number of beams, NaN, -inf or a negative
                        planted at a beam (a flag byte of 2..255), emptied, or sent as
                        the list ``rap.LaserScan/1`` had
``wrong_field_type``    a field of the envelope or the body given a value of another
                        type
``bad_utf8``            a string (or map key) of the envelope or body replaced by bytes
                        that are not UTF-8, same length
``future_ts``           the envelope's ``ts`` (or a body time: ``ts``, ``created``,
                        ``stamp``, ``version``) far in the future, at 2^63-1, 2^64-1, -1
``seq_edge``            ``seq`` near 2^63 (2^63-2 .. 2^63, 2^64-1), -1, -2^63
``uid_length``          ``uid``, ``cycle`` or ``cause`` of 0, 1, 15, 17, 32 or 4096 bytes,
                        or not bytes
``boundary_int``        1..3 integers of the body set to 0, -1, 2^31, 2^63-1, 2^64-1,
                        -2^63
``ctx_junk``            ``ctx`` with 1..5000 entries, invalid keys, negative or huge
                        versions, versions that are not integers
``ctx_never``           ``ctx`` promising versions of the loop's knowledge keys that
                        never come (a reader waits for them: rate-limited by the caller)
``raw_random``          0..4096 random bytes, no envelope at all
======================  =============================================================
"""

from __future__ import annotations

import math
import random
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import msgspec
from rap_schemas import (
    Empty,
    KbRecord,
    KnowledgeAccess,
    LaserScan,
    LidarMask,
    PlanProposal,
    Rejection,
    SpinPlan,
    StageTrace,
    TrustOutput,
    TrustSpecUpdate,
    Verdict,
)
from rap_sdk.envelope import new_uid

__all__ = ["MUTATIONS", "Mutator", "Sample"]

_encode = msgspec.msgpack.Encoder().encode

ENVELOPE_LEVEL: Final = ("wrong_type", "future_ts", "seq_edge", "uid_length", "ctx_junk")
"""Mutations that never touch the body (the only ones a locked body gets)."""

WEIGHTS: Final[dict[str, int]] = {
    "bitflip": 10,
    "truncate": 8,
    "insert": 6,
    "delete": 6,
    "wrong_type": 6,
    "deep_nest": 4,
    "huge_claim": 6,
    "huge_real": 1,
    "nonfinite": 8,
    "packed": 6,
    "wrong_field_type": 10,
    "bad_utf8": 6,
    "future_ts": 6,
    "seq_edge": 5,
    "uid_length": 5,
    "boundary_int": 6,
    "ctx_junk": 4,
    "ctx_never": 3,
    "raw_random": 8,
}
MUTATIONS: Final = tuple(WEIGHTS)
_UNSEALED: Final = frozenset(
    {
        "bitflip",
        "truncate",
        "insert",
        "delete",
        "wrong_type",
        "deep_nest",
        "huge_claim",
        "huge_real",
        "nonfinite",
        "packed",
        "wrong_field_type",
        "bad_utf8",
        "future_ts",
        "boundary_int",
        "raw_random",
    }
)
"""What applies to a plain request (no envelope)."""

HUGE_BUDGET: Final = 64 << 20
"""Bytes of real huge values per target; past it they are at most 64 KiB (the traffic
stays bounded on a long run)."""
U64: Final = 2**64 - 1
I63: Final = 2**63 - 1
_INTS: Final = (0, -1, 2**31, I63, U64, -(2**63), 2**32, 2**53 + 1)
_FLOATS: Final = (float("nan"), float("inf"), float("-inf"))
_TIME_FIELDS: Final = frozenset({"ts", "created", "stamp", "version", "since", "until"})
_WIRE_TYPES: Final = (
    Empty.TYPE,
    LaserScan.TYPE,
    LidarMask.TYPE,
    PlanProposal.TYPE,
    Verdict.TYPE,
    KbRecord.TYPE,
    StageTrace.TYPE,
    KnowledgeAccess.TYPE,
    TrustOutput.TYPE,
    TrustSpecUpdate.TYPE,
    Rejection.TYPE,
    SpinPlan.TYPE,
)
_PACKED: Final[dict[str, int]] = {"ranges": 4, "occluded": 1}
"""Packed per-beam arrays (``bytes`` fields) by name: bytes per beam (float32 ranges,
one byte per flag)."""
_PACKED_DAMAGE: Final = ("flip", "plant", "ragged", "empty", "list")
_PACKED_WEIGHTS: Final = (3, 3, 3, 1, 1)
_BAD_BEAMS: Final = (
    struct.pack("<f", math.nan),
    struct.pack("<f", -math.inf),
    struct.pack("<f", -1.0),
    b"\x01\x00\x00\x80",  # the negative float32 nearest zero
    b"\xff\xff\xff\xff",  # a negative NaN
)
"""float32 beams a scan refuses, packed."""
_OPS: Final = ("put", "delete", "get", "history", "list", "model-put", "model-get", "nope", "")


@dataclass(slots=True)
class Sample:
    payload: bytes
    mutation: str


def _other_value(rng: random.Random, old: Any) -> Any:
    """A value of another type than ``old``."""
    pool: list[Any] = [0, -1, 1.5, "x", b"\x00", [], {}, True, None, [1, "a"], {"a": 1}, U64]
    while True:
        v = rng.choice(pool)
        if type(v) is not type(old):
            return v


def _walk(rng: random.Random, root: Any, want: Callable[[Any], bool] | None = None) -> list[Any]:
    """A random path (keys and indices) from ``root`` into its data; with ``want``, to a
    value it accepts when one is found on the way (else wherever the walk stopped)."""
    path: list[Any] = []
    node = root
    for _ in range(32):
        if want is not None and path and want(node):
            return path
        if isinstance(node, dict) and node:
            k = rng.choice(list(node))
            path.append(k)
            node = node[k]
        elif isinstance(node, list) and node:
            i = rng.randrange(len(node))
            path.append(i)
            node = node[i]
        else:
            break
        if want is None and rng.random() < 0.25:
            break
    return path


def _leaves(root: Any, want: Callable[[Any, Any], bool], limit: int = 4096) -> list[list[Any]]:
    """Paths to up to ``limit`` values accepted by ``want(key, value)`` (iterative)."""
    out: list[list[Any]] = []
    stack: list[tuple[list[Any], Any]] = [([], root)]
    while stack and len(out) < limit:
        path, node = stack.pop()
        items: Any = (
            node.items()
            if isinstance(node, dict)
            else enumerate(node)
            if isinstance(node, list)
            else ()
        )
        for k, v in items:
            if want(k, v):
                out.append([*path, k])
            if isinstance(v, (dict, list)):
                stack.append(([*path, k], v))
    return out


def _set(root: Any, path: list[Any], value: Any) -> Any:
    """``root`` with the value at ``path`` replaced, copying only along the path."""
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(root, dict):
        copy = dict(root)
    elif isinstance(root, list):
        copy = list(root)
    else:
        return root
    copy[head] = _set(root[head], rest, value)
    return copy


def _rename_key(root: Any, path: list[Any], new: str) -> Any:
    """``root`` with the map key at ``path`` renamed to ``new`` (order kept)."""
    *parent, old = path
    holder = root
    for p in parent:
        holder = holder[p]
    if not isinstance(holder, dict):
        return root
    renamed = {(new if k == old else k): v for k, v in holder.items()}
    return _set(root, parent, renamed)


def _at(root: Any, path: list[Any]) -> Any:
    for p in path:
        root = root[p]
    return root


def _whole(value: Any, width: int) -> bool:
    """``value`` is bytes of at least one whole beam of ``width`` bytes."""
    return isinstance(value, bytes) and len(value) >= width and len(value) % width == 0


def _nested(rng: random.Random) -> bytes:
    depth = int(10 ** rng.uniform(2, 5))
    if rng.random() < 0.5:
        return b"\x91" * depth + b"\xc0"  # [[[...nil...]]]
    return b"\x81\xa1k" * depth + b"\xc0"  # {"k": {"k": ... nil}}


def _claim(rng: random.Random) -> bytes:
    n = rng.choice([b"\xff\xff\xff\xff", b"\x80\x00\x00\x00", b"\xff\xff\xff\xfe"])
    head = rng.choice([b"\xdd", b"\xdf", b"\xdb", b"\xc6", b"\xc9"])  # array, map, str, bin, ext
    tail = b"\x01" if head == b"\xc9" else b""
    return head + n + tail + rng.randbytes(rng.randrange(0, 16))


def _huge(rng: random.Random, cap: int) -> Any:
    """A real array, map, str or bin of 1k..5M bytes (mostly under 100k), at most
    ``cap`` bytes."""
    n = int(10 ** (rng.uniform(3, 5) if rng.random() < 0.9 else rng.uniform(5, 6.7)))
    n = max(min(n, cap), 16)
    kind = rng.randrange(4)
    if kind == 0:  # an array of n // 2 small ints
        return msgspec.Raw(b"\xdd" + (n // 2).to_bytes(4, "big") + b"\x01" * (n // 2))
    if kind == 1:  # a map of n // 3 entries (the same key again and again)
        return msgspec.Raw(b"\xdf" + (n // 3).to_bytes(4, "big") + b"\xa1a\x01" * (n // 3))
    if kind == 2:
        return "a" * n
    return b"\x00" * n


def _bad_utf8(rng: random.Random, n: int) -> bytes:
    n = max(n, 1)
    return b"\xff" + bytes(rng.randrange(0x80, 0x100) for _ in range(n - 1))


class Mutator:
    """Mutated samples for one target, from ``random.Random(f"{seed}/{name}")``."""

    def __init__(
        self,
        name: str,
        seed: int,
        *,
        sealed: bool = True,
        sources: list[str] | None = None,
        ctx_keys: list[str] | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.name = name
        self.rng = random.Random(f"{seed}/{name}")
        self.sealed = sealed
        self.sources = sources or ["fuzzer"]
        self.ctx_keys = ctx_keys or []
        self.now = clock
        self._seq: dict[tuple[str, str], int] = {}
        self.huge_bytes = 0
        """Bytes of ``huge_real`` values made so far (past ``HUGE_BUDGET``: 64 KiB each)."""
        names = [m for m in MUTATIONS if sealed or m in _UNSEALED]
        self._names = names
        self._weights = [WEIGHTS[m] for m in names]
        self._locked_names = [m for m in names if m in ENVELOPE_LEVEL]

    def choose(self, *, locked: bool = False, ctx_never: bool = True) -> str:
        """The next mutation (``locked``: envelope-level only; ``ctx_never=False``: not
        that one now, ``ctx_junk`` instead)."""
        rng = self.rng
        name = (
            rng.choice(self._locked_names) if locked else rng.choices(self._names, self._weights)[0]
        )
        if name == "ctx_never" and not ctx_never:
            return "ctx_junk"
        return name

    # -- envelopes ------------------------------------------------------------------------

    def envelope(self, key: str, type_name: str, body: Any) -> dict[str, Any]:
        """A valid envelope (as a map) around ``body`` (plain data)."""
        rng = self.rng
        source = rng.choice(self.sources)
        seq = self._seq.get((source, key), 0)
        self._seq[(source, key)] = seq + 1
        ts = self.now()
        env: dict[str, Any] = {
            "uid": new_uid(ts),
            "ts": ts,
            "source": source,
            "seq": seq,
            "type": type_name,
            "body": body,
        }
        if rng.random() < 0.5:
            env["cycle"] = rng.randbytes(16)
            env["cause"] = rng.randbytes(16)
        return env

    # -- one sample -----------------------------------------------------------------------

    def mutate(self, name: str, valid: Any, *, ctx_versions: dict[str, int] | None = None) -> bytes:
        """``valid`` (an envelope map, or a plain request) with mutation ``name``."""
        rng = self.rng
        fn = getattr(self, "_m_" + name)
        out = fn(rng, valid, ctx_versions or {})
        return out if isinstance(out, bytes) else _encode(out)

    def _body_path(self) -> list[Any]:
        return ["body"] if self.sealed else []

    def _body(self, valid: Any) -> Any:
        return valid["body"] if self.sealed else valid

    def _with_body(self, valid: Any, body: Any) -> Any:
        return {**valid, "body": body} if self.sealed else body

    def _m_bitflip(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        data = bytearray(_encode(valid))
        for _i in range(rng.randrange(1, 9)):
            bit = rng.randrange(len(data) * 8)
            data[bit // 8] ^= 1 << (bit % 8)
        return bytes(data)

    def _m_truncate(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        data = _encode(valid)
        return data[: rng.randrange(len(data))]

    def _m_insert(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        data = _encode(valid)
        at = rng.randrange(len(data) + 1)
        return data[:at] + rng.randbytes(rng.randrange(1, 33)) + data[at:]

    def _m_delete(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        data = _encode(valid)
        at = rng.randrange(len(data))
        return data[:at] + data[at + rng.randrange(1, 33) :]

    def _m_wrong_type(self, rng: random.Random, valid: Any, _: Any) -> Any:
        if not self.sealed:
            if isinstance(valid, dict):
                return {**valid, "op": rng.choice(_OPS)}
            return valid
        old = valid["type"]
        choice = rng.randrange(4)
        if choice == 0:
            new = rng.choice([t for t in _WIRE_TYPES if t != old])
        elif choice == 1:  # another version of the same message, older or newer
            name, _, version = old.partition("/")
            new = name + "/" + rng.choice([v for v in ("1", "2", "3") if v != version])
        elif choice == 2:
            new = rng.choice(["", "rap.", "/1", "rap.Nope/1"])
        else:
            new = "rap." + "X" * 1000 + "/1"
        return {**valid, "type": new}

    def _place(self, rng: random.Random, valid: Any, raw: Any) -> Any:
        """Put ``raw`` at the body, a field, a ctx value, or make it the whole sample."""
        where = rng.randrange(4)
        if where == 0:
            return raw if isinstance(raw, bytes) else _encode(raw)
        if where == 1 or not self.sealed:
            body = self._body(valid)
            path = _walk(rng, body)
            return self._with_body(valid, _set(body, path, raw) if path else raw)
        if where == 2:
            return {**valid, "ctx": {"laser_scan": raw}}
        return {**valid, "body": raw}

    def _m_deep_nest(self, rng: random.Random, valid: Any, _: Any) -> Any:
        return self._place(rng, valid, msgspec.Raw(_nested(rng)))

    def _m_huge_claim(self, rng: random.Random, valid: Any, _: Any) -> Any:
        return self._place(rng, valid, msgspec.Raw(_claim(rng)))

    def _m_huge_real(self, rng: random.Random, valid: Any, _: Any) -> Any:
        cap = 5 << 20 if self.huge_bytes < HUGE_BUDGET else 64 << 10
        huge = _huge(rng, cap)
        self.huge_bytes += len(huge)
        body = self._body(valid)
        path = _walk(rng, body)
        return self._with_body(valid, _set(body, path, huge) if path else huge)

    def _m_nonfinite(self, rng: random.Random, valid: Any, _: Any) -> Any:
        body = self._body(valid)
        floats = _leaves(body, lambda _k, v: isinstance(v, float))
        packed = _leaves(body, lambda k, v: _PACKED.get(k) == 4 and _whole(v, 4))
        if not floats and not packed:
            floats = [_walk(rng, body)] if isinstance(body, (dict, list)) and body else [[]]
        for _i in range(rng.randrange(1, 4)):
            if packed and (not floats or rng.random() < 0.5):  # a beam of packed float32
                path = rng.choice(packed)
                data = _at(body, path)
                at = 4 * rng.randrange(len(data) // 4)
                (was,) = struct.unpack_from("<f", data, at)
                beam = struct.pack("<f", rng.choice([f for f in _FLOATS if repr(f) != repr(was)]))
                body = _set(body, path, data[:at] + beam + data[at + 4 :])
                continue
            path = rng.choice(floats)
            old: Any = body
            for p in path:
                old = old[p]
            new = rng.choice([f for f in _FLOATS if repr(f) != repr(old)])  # never a no-op
            body = _set(body, path, new)
        return self._with_body(valid, body)

    def _m_packed(self, rng: random.Random, valid: Any, _: Any) -> Any:
        body = self._body(valid)
        fields = _leaves(body, lambda k, v: k in _PACKED and isinstance(v, bytes))
        if not fields:  # nothing packed in this message
            return self._m_bitflip(rng, valid, None)
        path = rng.choice(fields)
        old: bytes = _at(body, path)
        width = _PACKED[path[-1]]
        kind = rng.choices(_PACKED_DAMAGE, _PACKED_WEIGHTS)[0]
        data = bytearray(old)
        if kind == "flip" and data:  # 1..8 bytes flipped (each a different byte)
            for i in rng.sample(range(len(data)), min(len(data), rng.randrange(1, 9))):
                data[i] ^= rng.randrange(1, 256)
        elif kind == "plant" and len(data) >= width:  # a bad value at a beam
            beam = rng.randrange(len(data) // width)
            bad = rng.choice(_BAD_BEAMS) if width == 4 else bytes([rng.randrange(2, 256)])
            data[beam * width : (beam + 1) * width] = bad
        elif kind == "ragged" and data and rng.random() < 0.5:  # cut: no whole beam count
            cuts = [n for n in range(len(data)) if width == 1 or n % width]
            del data[rng.choice(cuts) :]
        elif kind == "empty" and data:  # no beams at all
            data.clear()
        elif kind == "list":  # a list, as version 1 of the message sent it
            n = len(old) // width
            items: list[Any] = (
                list(struct.unpack(f"<{n}f", old[: 4 * n]))
                if width == 4
                else [bool(b) for b in old]
            )
            return self._with_body(valid, _set(body, path, items or [1.0]))
        else:  # grown by 1..3 bytes (with width 4: no whole number of beams)
            data += rng.randbytes(rng.randrange(1, 4))
        return self._with_body(valid, _set(body, path, bytes(data)))

    def _m_wrong_field_type(self, rng: random.Random, valid: Any, _: Any) -> Any:
        if self.sealed and rng.random() < 0.4:
            k = rng.choice([k for k in valid if k != "body"])
            return {**valid, k: _other_value(rng, valid[k])}
        body = self._body(valid)
        path = _walk(rng, body)
        old: Any = body
        for p in path:
            old = old[p]
        return self._with_body(valid, _set(body, path, _other_value(rng, old)))

    def _m_bad_utf8(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        marker = "\x7fFZ" + rng.randbytes(4).hex()
        target: Any
        if self.sealed and rng.random() < 0.4:
            field = rng.choice(["source", "type", "ctx"])
            target = {**valid, "ctx": {marker: 1}} if field == "ctx" else {**valid, field: marker}
        else:
            body = self._body(valid)
            strs = _leaves(body, lambda k, v: isinstance(v, str) or isinstance(k, str), 256)
            if not strs:
                return self._m_raw_random(rng, valid, None)
            path = rng.choice(strs)
            holder: Any = body
            for p in path:
                holder = holder[p]
            if isinstance(holder, str) and (rng.random() < 0.6 or not isinstance(path[-1], str)):
                body = _set(body, path, marker)
            else:
                body = _rename_key(body, path, marker)
            target = self._with_body(valid, body)
        data = _encode(target)
        raw = marker.encode()
        return data.replace(raw, _bad_utf8(rng, len(raw)), 1)

    def _m_future_ts(self, rng: random.Random, valid: Any, _: Any) -> Any:
        now = self.now()
        value = rng.choice(
            [now + 6 * 10**9, now + 3600 * 10**9, now + 100 * 365 * 86400 * 10**9, I63, U64, -1]
        )
        if self.sealed and rng.random() < 0.6:
            return {**valid, "ts": value}
        body = self._body(valid)
        times = _leaves(body, lambda k, v: k in _TIME_FIELDS and isinstance(v, int))
        if not times:
            return {**valid, "ts": value} if self.sealed else valid
        if rng.random() < 0.5:  # a knowledge version ahead of every clock
            value = ((now // 10**6 - 1_704_067_200_000 + rng.choice([59_000, 3_600_000])) << 20) | 1
        return self._with_body(valid, _set(body, rng.choice(times), value))

    def _m_seq_edge(self, rng: random.Random, valid: Any, _: Any) -> Any:
        seq = rng.choice([I63 - 1, I63, 2**63, U64, -1, -(2**63)])
        return {**valid, "seq": seq}

    def _m_uid_length(self, rng: random.Random, valid: Any, _: Any) -> Any:
        field = rng.choice(["uid", "uid", "cycle", "cause"])
        value: Any = rng.randbytes(rng.choice([0, 1, 15, 17, 32, 4096]))
        if rng.random() < 0.15:
            value = rng.choice(["0123456789abcdef", 16, None, [1] * 16])
        return {**valid, field: value}

    def _m_boundary_int(self, rng: random.Random, valid: Any, _: Any) -> Any:
        body = self._body(valid)
        ints = _leaves(body, lambda _k, v: isinstance(v, int) and not isinstance(v, bool))
        if not ints:
            return self._m_wrong_field_type(rng, valid, None)
        for _i in range(rng.randrange(1, 4)):
            body = _set(body, rng.choice(ints), rng.choice(_INTS))
        return self._with_body(valid, body)

    def _m_ctx_junk(self, rng: random.Random, valid: Any, _: Any) -> Any:
        kind = rng.randrange(4)
        ctx: Any
        if kind == 0:
            n = int(10 ** rng.uniform(0, 3.7))
            base = rng.randrange(1, I63 - n)
            ctx = {f"k{i}/{base}": base + i for i in range(n)}
        elif kind == 1:
            ctx = {rng.choice(["", "a/**", "$*", "a//b", "_keys", "x" * 5000]): 1}
        elif kind == 2:
            ctx = {rng.choice(self.ctx_keys or ["k"]): rng.choice([-1, 0, U64, -(2**63)])}
        else:
            ctx = {rng.choice(self.ctx_keys or ["k"]): rng.choice(["1", 1.5, None, [1], b"1"])}
        return {**valid, "ctx": ctx}

    def _m_ctx_never(self, rng: random.Random, valid: Any, versions: dict[str, int]) -> Any:
        """Versions just ahead of what the loop holds (within the clocks' drift bound, so
        a reader waits for them) or far ahead (beyond it)."""
        now_ms = self.now() // 10**6 - 1_704_067_200_000
        ahead = rng.choice([30_000, 59_000, 3_600_000])
        keys = self.ctx_keys or ["laser_scan"]
        picked = rng.sample(keys, rng.randrange(1, len(keys) + 1))
        ctx = {k: max(versions.get(k, 0) + (1 << 8), (now_ms + ahead) << 20) for k in picked}
        return {**valid, "ctx": ctx}

    def _m_raw_random(self, rng: random.Random, valid: Any, _: Any) -> bytes:
        return rng.randbytes(int(2 ** rng.uniform(0, 12)))
