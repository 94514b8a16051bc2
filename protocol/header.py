"""Reading a frame's header: every check that needs only the few header bytes, in order.

:func:`parse_frame` runs before any large allocation: sizes against the caps of
:class:`~protocol.expectation.Expectation`, schema, kind, swarm, sender, round, signature,
encoding, the array table against the model spec, and that the declared sizes add up. Each step
is a function of its own and raises :class:`~protocol.messages.Rejected` with its reason; the
payload itself is left to :mod:`protocol.payload`. Pure Python + numpy + msgpack.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from protocol.array_table import ArrayTable, check_array_table, table_bytes
from protocol.compression import check_meta as check_theta_meta
from protocol.expectation import Expectation
from protocol.frame import CHECKSUM_HEX_LENGTH, HEADER_FIELDS, MAGIC, PREFIX, PREFIX_LENGTH
from protocol.keys import ParsedKey
from protocol.messages import (
    COMPRESSIONS,
    KIND_KEYFRAMES,
    KIND_STATUS,
    KIND_THETA,
    KINDS,
    MAX_ROUND,
    SCHEMA_VERSION,
    WIRE_DTYPES,
    CodedTheta,
    Header,
    ModelSpec,
    Rejected,
    is_int,
    is_number,
    similarity_problem,
)
from protocol.untrusted import describe



@dataclass
class ParsedFrame:
    """A frame whose header passed every check; the payload is still unread."""

    header: Header
    header_map: dict[str, Any]
    arrays: ArrayTable
    meta: dict[str, Any]
    payload: memoryview
    coded: CodedTheta | None = None  # a compressed snapshot's coding, its arrays still unread
    spec: ModelSpec | None = None  # the receiver's model spec (snapshots)


def parse_frame(data: Any, expect: Expectation, kind: str | None, key: ParsedKey | None) -> ParsedFrame:
    """Validate everything but the payload (cheap; no large allocation). Raises Rejected."""
    view, header_length = _split_prefix(data, expect)
    h = _header_map(view, header_length, expect)
    schema = _check_schema_and_fields(h)
    msg_kind = _check_kind(h, kind)
    _check_identity(h, expect, key)
    _check_signature(h, msg_kind, expect)
    _check_encoding(h, msg_kind)
    _check_lengths(h, msg_kind, len(view) - PREFIX_LENGTH - header_length, expect)
    checksum = h["checksum"]
    if not isinstance(checksum, str) or len(checksum) != CHECKSUM_HEX_LENGTH:
        raise Rejected("bad_header", "checksum is not a 16-character hex string")
    coded = check_theta_meta(h["meta"]) if msg_kind == KIND_THETA else None
    arrays = check_array_table(h["arrays"], msg_kind, h["wire_dtype"], expect, coded)
    _check_raw_length(h["raw_length"], arrays, msg_kind)
    meta = h["meta"] if msg_kind == KIND_THETA else _check_meta(h["meta"], msg_kind)
    header = Header(
        schema=schema, kind=msg_kind, swarm=h["swarm"], sender=h["sender"], round=h["round"], epoch=h["epoch"],
        signature=h["signature"], wire_dtype=h["wire_dtype"], compression=h["compression"],
        raw_length=h["raw_length"], payload_length=h["payload_length"], checksum=checksum,
    )
    return ParsedFrame(header, h, arrays, meta, view[PREFIX_LENGTH + header_length :], coded, expect.spec)


def _split_prefix(data: Any, expect: Expectation) -> tuple[memoryview, int]:
    """The frame as bytes and its header length, once magic and prefix are sound."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise Rejected("garbage", f"expected bytes, got {type(data).__name__}")
    try:
        view = memoryview(data).cast("B")
    except (TypeError, ValueError):  # a strided or released memoryview
        raise Rejected("garbage", "not a contiguous byte buffer") from None
    n = len(view)
    if n > expect.max_wire_bytes:
        raise Rejected("too_large", f"{n} bytes on the wire > cap {expect.max_wire_bytes}")
    if n < len(MAGIC):
        if MAGIC.startswith(bytes(view)):
            raise Rejected("bad_length", f"only {n} bytes")
        raise Rejected("bad_magic", "not a dinerf frame")
    if bytes(view[: len(MAGIC)]) != MAGIC:
        raise Rejected("bad_magic", f"starts with {bytes(view[:4])!r}")
    if n < PREFIX_LENGTH:
        raise Rejected("bad_length", f"only {n} bytes")
    _, header_length = PREFIX.unpack_from(view, 0)
    if header_length > expect.max_header_bytes:
        raise Rejected("too_large", f"header of {header_length} bytes > cap {expect.max_header_bytes}")
    if PREFIX_LENGTH + header_length > n:
        raise Rejected("bad_length", f"header of {header_length} bytes does not fit in {n} bytes")
    return view, header_length


def _header_map(view: memoryview, header_length: int, expect: Expectation) -> dict[str, Any]:
    """The header unpacked under msgpack's own limits: strings short, no bin or ext at all."""
    try:
        h = msgpack.unpackb(
            view[PREFIX_LENGTH : PREFIX_LENGTH + header_length],
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_str_len=4096,
            max_bin_len=0,
            max_ext_len=0,
            max_array_len=max(16, expect.max_tensors),
            max_map_len=64,
        )
    except Exception as exc:
        raise Rejected("garbage", f"header is not valid msgpack: {type(exc).__name__}") from None
    if not isinstance(h, dict):
        raise Rejected("garbage", "header is not a map")
    return h


def _check_schema_and_fields(h: dict[str, Any]) -> int:
    """Schema first (another version may legitimately have other fields), then the field set."""
    schema = h.get("schema")
    if not is_int(schema):
        raise Rejected("bad_header", "schema version missing or not an integer")
    if schema != SCHEMA_VERSION:
        raise Rejected("bad_schema", f"schema {schema}, we speak {SCHEMA_VERSION}")
    if set(h) != set(HEADER_FIELDS):
        missing = sorted(set(HEADER_FIELDS) - set(h))
        extra = sorted(describe(k) for k in set(h) - set(HEADER_FIELDS))[:4]
        raise Rejected("bad_header", f"missing {missing} unexpected {extra}")
    return schema


def _check_kind(h: dict[str, Any], kind: str | None) -> str:
    msg_kind = h["kind"]
    if msg_kind not in KINDS:
        raise Rejected("bad_kind", f"unknown kind {describe(msg_kind)}")
    if kind is not None and msg_kind != kind:
        raise Rejected("bad_kind", f"got {msg_kind}, expected {kind}")
    return msg_kind


def _check_identity(h: dict[str, Any], expect: Expectation, key: ParsedKey | None) -> None:
    """Swarm, sender, round and epoch, against our swarm, our peers and the key they came on."""
    swarm = h["swarm"]
    if not isinstance(swarm, str):
        raise Rejected("bad_header", "swarm is not a string")
    if swarm != expect.swarm:
        raise Rejected("wrong_swarm", f"swarm {swarm[:64]!r}, we are {expect.swarm!r}")

    sender = h["sender"]
    if not is_int(sender) or not 0 <= sender <= MAX_ROUND:
        raise Rejected("unknown_sender", f"sender {describe(sender)} is not a robot id")
    if expect.allowed_senders is not None and sender not in expect.allowed_senders:
        raise Rejected("unknown_sender", f"sender {sender} not in {sorted(expect.allowed_senders)}")
    if key is not None and key.robot_id != sender:
        raise Rejected("sender_mismatch", f"header says sender {sender}, key says {key.robot_id}")

    for name in ("round", "epoch"):
        v = h[name]
        if not is_int(v) or not 0 <= v <= MAX_ROUND:
            raise Rejected("bad_round", f"{name} {describe(v)} is not an integer in [0, {MAX_ROUND}]")
    if key is not None and key.round is not None and key.round != h["round"]:
        raise Rejected("bad_round", f"header says round {h['round']}, key says {key.round}")


def _check_signature(h: dict[str, Any], msg_kind: str, expect: Expectation) -> None:
    """Snapshots carry our model's signature; other kinds carry none."""
    signature = h["signature"]
    if not isinstance(signature, str):
        raise Rejected("bad_header", "signature is not a string")
    if msg_kind == KIND_THETA:
        if expect.spec is None:
            raise Rejected("bad_signature", "no model spec configured to accept snapshots")
        if signature != expect.signature:
            raise Rejected("bad_signature", f"signature {signature[:32]!r}, ours {expect.signature!r}")
    elif signature != "":
        raise Rejected("bad_signature", f"{msg_kind} messages carry no model signature")


def _check_encoding(h: dict[str, Any], msg_kind: str) -> None:
    wire_dtype, compression = h["wire_dtype"], h["compression"]
    if wire_dtype not in WIRE_DTYPES or compression not in COMPRESSIONS:
        raise Rejected("bad_encoding", f"dtype {describe(wire_dtype)} compression {describe(compression)}")
    if msg_kind != KIND_THETA and wire_dtype != "float32":
        raise Rejected("bad_encoding", f"{msg_kind} messages are not quantised")


def _check_lengths(h: dict[str, Any], msg_kind: str, actual_payload: int, expect: Expectation) -> None:
    """The payload is as long as declared, and the declared decompressed size is under the kind's cap."""
    raw_length, payload_length = h["raw_length"], h["payload_length"]
    if not is_int(raw_length) or not is_int(payload_length) or raw_length < 0 or payload_length < 0:
        raise Rejected("bad_header", "lengths must be non-negative integers")
    if payload_length != actual_payload:
        raise Rejected("bad_length", f"header says {payload_length} payload bytes, got {actual_payload}")
    cap = expect.max_raw_bytes(msg_kind)
    if raw_length > cap:
        raise Rejected("too_large", f"{msg_kind} declares {raw_length} bytes > cap {cap}")
    if h["compression"] == "none" and raw_length != payload_length:
        raise Rejected("bad_length", "uncompressed payload with raw_length != payload_length")


def _check_raw_length(raw_length: int, arrays: ArrayTable, msg_kind: str) -> None:
    """The declared decompressed size is what the array table needs (a status body has no table)."""
    if msg_kind == KIND_STATUS:
        return
    expected_raw = table_bytes(arrays)
    if raw_length != expected_raw:
        raise Rejected("bad_length", f"arrays need {expected_raw} bytes, header declares {raw_length}")


def _check_meta(meta: Any, msg_kind: str) -> dict[str, Any]:
    """Keyframes carry image_bytes and optionally a field box; other kinds carry no meta."""
    if not isinstance(meta, dict):
        raise Rejected("bad_header", "meta is not a map")
    if msg_kind == KIND_KEYFRAMES:
        if set(meta) - {"box_from_shared"} != {"image_bytes"} or not is_int(meta["image_bytes"]) or meta["image_bytes"] < 0:
            raise Rejected("bad_field", "keyframes meta must be {image_bytes: non-negative int[, box_from_shared]}")
        if "box_from_shared" in meta:
            box = meta["box_from_shared"]
            if not isinstance(box, list) or len(box) != 16 or not all(is_number(x) for x in box):
                raise Rejected("bad_field", "box_from_shared must be 16 numbers (a 4x4 matrix, row-major)")
            problem = similarity_problem(np.array(box, dtype=np.float64).reshape(4, 4))
            if problem:
                raise Rejected("bad_field", f"box_from_shared: {problem}")
    elif meta:
        raise Rejected("bad_field", f"{msg_kind} messages carry no meta")
    return meta
