"""Wire format: encode messages to bytes, and decode received bytes with strict validation.

Frame layout (all integers little-endian)::

    b"DNRF"                 4-byte magic
    uint32 header_length
    header                  msgpack map, see HEADER_FIELDS
    payload                 header["payload_length"] bytes, zstd-compressed or raw

The decompressed payload of a ``theta`` or ``keyframes`` message is the concatenation, in header
order, of the raw little-endian C-order buffers listed in ``header["arrays"]`` as
``[name, dtype, shape]``; the payload of a ``status`` message is a msgpack map. The checksum is
blake2b with an 8-byte digest over the packed header (with its checksum field zeroed) followed by
the wire payload, so a corrupted header field is caught too (integrity, not authenticity: use
Zenoh TLS for that). Our encoder packs headers canonically; a header packed any other way fails
the checksum.

API::

    encode(msg, *, wire_dtype="float32", compression="zstd", level=3, spec=None) -> bytes
    decode(data, expect, *, kind=None, key=None) -> ThetaSnapshot | Status | KeyframeSummary
    read_header(data, expect, *, kind=None, key=None) -> Header   # cheap checks only

``decode`` checks everything it can from the few header bytes *before* any large allocation:
sizes against the caps of :class:`Expectation`, schema, kind, swarm, sender, round, signature,
encoding, tensor names/dtypes/shapes against the model spec, and that the declared sizes add up.
Only then does it verify the checksum, decompress (refusing any zstd frame that declares or
produces more than the header says, so a decompression bomb never allocates) and check that all
values are finite. Every failure raises :class:`~protocol.messages.Rejected` with a reason code;
no other exception escapes ``decode`` for any input bytes.

``float32`` on the wire round-trips bit-identically; ``float16`` halves the bytes and is lossy
(relative error ~5e-4, values beyond +-65504 are refused at encode time).

Pure Python + numpy + msgpack + zstandard: no zenoh, no torch.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass, field
from typing import Any, Mapping

import msgpack
import numpy as np
import zstandard

from protocol.keys import ParsedKey, validate_swarm
from protocol.messages import (
    COMPRESSIONS,
    KEYFRAME_ARRAYS,
    KEYFRAME_CAMERA_DIM,
    KIND_KEYFRAMES,
    KIND_STATUS,
    KIND_THETA,
    KINDS,
    MAX_ROUND,
    SCHEMA_VERSION,
    WIRE_DTYPES,
    Header,
    KeyframeSummary,
    Message,
    ModelSpec,
    Rejected,
    Status,
    ThetaSnapshot,
    check_status_body,
    is_int,
    is_number,
    similarity_problem,
    status_body,
)

MAGIC = b"DNRF"
_PREFIX = struct.Struct("<4sI")
PREFIX_LENGTH = _PREFIX.size  # 8

HEADER_FIELDS = (
    "schema",
    "kind",
    "swarm",
    "sender",
    "round",
    "epoch",
    "signature",
    "wire_dtype",
    "compression",
    "raw_length",
    "payload_length",
    "checksum",
    "arrays",
    "meta",
)

MiB = 1024 * 1024
#: Array dtypes that may appear on the wire, as little-endian numpy dtypes.
_ARRAY_DTYPES = {
    "float32": np.dtype("<f4"),
    "float16": np.dtype("<f2"),
    "uint8": np.dtype("u1"),
    "int32": np.dtype("<i4"),
}
_MAX_STATUS_BYTES = 64 * 1024
_MAX_WINDOW = 1 << 27  # zstd window cap (128 MiB), zstd's own default limit
_CHECKSUM_HEX_LENGTH = 16


@dataclass(frozen=True)
class Expectation:
    """What a receiver accepts: its swarm, model, peers, and hard size caps.

    ``allowed_senders=None`` accepts any id (e.g. ``dinerf-agent status``); a robot passes the
    ids of its swarm. ``spec=None`` refuses every snapshot (``bad_signature``).
    """

    swarm: str
    spec: ModelSpec | None = None
    allowed_senders: frozenset[int] | None = None
    max_wire_bytes: int = 512 * MiB
    max_decompressed_bytes: int = 512 * MiB
    max_tensors: int = 4096
    max_header_bytes: int = 1 * MiB
    max_keyframe_points: int = 200_000
    max_keyframes: int = 4096
    max_descriptor_dim: int = 1024
    signature: str = field(init=False, default="")

    def __post_init__(self) -> None:
        validate_swarm(self.swarm)
        if self.allowed_senders is not None:
            object.__setattr__(self, "allowed_senders", frozenset(self.allowed_senders))
        if self.spec is not None:
            object.__setattr__(self, "signature", self.spec.signature())
            if len(self.spec.params) > self.max_tensors:
                raise ValueError("model spec has more tensors than max_tensors")
        for name in ("max_wire_bytes", "max_decompressed_bytes", "max_tensors", "max_header_bytes"):
            if getattr(self, name) <= 0:
                raise ValueError(f"Expectation.{name} must be positive")


_ZERO_CHECKSUM = "0" * _CHECKSUM_HEX_LENGTH


def frame_checksum(header: Mapping[str, Any], payload: bytes | bytearray | memoryview) -> str:
    """blake2b-64 (hex) of the canonically packed header, checksum zeroed, then the payload."""
    digest = hashlib.blake2b(digest_size=8)
    digest.update(msgpack.packb({**header, "checksum": _ZERO_CHECKSUM}, use_bin_type=True))
    digest.update(payload)
    return digest.hexdigest()


# =========================================================================== encode


def _check_header_numbers(msg: Message) -> None:
    validate_swarm(msg.swarm)
    for name in ("sender", "round", "epoch"):
        v = getattr(msg, name)
        if not is_int(v) or not 0 <= v <= MAX_ROUND:
            raise ValueError(f"{type(msg).__name__}.{name} must be an integer in [0, {MAX_ROUND}], got {v!r}")


def _frame(header: dict[str, Any], payload: bytes | bytearray) -> bytes:
    packed = msgpack.packb(header, use_bin_type=True)
    return b"".join((_PREFIX.pack(MAGIC, len(packed)), packed, payload))


def pack_frame(header: Mapping[str, Any], payload: bytes, *, fix_checksum: bool = True) -> bytes:
    """Frame an arbitrary header and payload, unchecked. For tests and fault injection only."""
    header = dict(header)
    if fix_checksum:
        header["checksum"] = frame_checksum(header, payload)
    return _frame(header, payload)


def _seal(kind: str, msg: Message, signature: str, wire_dtype: str, compression: str, level: int,
          raw: bytes | bytearray, arrays: list, meta: dict) -> bytes:
    if compression == "zstd":
        payload = zstandard.ZstdCompressor(level=level, write_content_size=True).compress(raw)
    elif compression == "none":
        payload = bytes(raw) if isinstance(raw, bytearray) else raw
    else:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
    header = {
        "schema": SCHEMA_VERSION,
        "kind": kind,
        "swarm": msg.swarm,
        "sender": msg.sender,
        "round": msg.round,
        "epoch": msg.epoch,
        "signature": signature,
        "wire_dtype": wire_dtype,
        "compression": compression,
        "raw_length": len(raw),
        "payload_length": len(payload),
        "checksum": _ZERO_CHECKSUM,
        "arrays": arrays,
        "meta": meta,
    }
    header["checksum"] = frame_checksum(header, payload)
    return _frame(header, payload)


def _pack_arrays(arrays: list[tuple[str, np.ndarray, np.dtype]]) -> tuple[bytearray, list]:
    """Concatenate arrays (converted to the given wire dtype) into one buffer with one copy."""
    total = sum(a.size * dt.itemsize for _, a, dt in arrays)
    raw = bytearray(total)
    table = []
    offset = 0
    for name, a, dt in arrays:
        n = a.size * dt.itemsize
        if n:
            dest = np.frombuffer(raw, dtype=dt, count=a.size, offset=offset).reshape(a.shape)
            with np.errstate(over="ignore"):  # float16 overflow becomes inf, refused just below
                np.copyto(dest, a, casting="unsafe")
        wire_name = next(k for k, v in _ARRAY_DTYPES.items() if v == dt)
        table.append([name, wire_name, [int(d) for d in a.shape]])
        offset += n
    return raw, table


def encode(msg: Message, *, wire_dtype: str = "float32", compression: str = "zstd", level: int = 3,
           spec: ModelSpec | None = None) -> bytes:
    """Serialise a message. Raises ValueError for a message we must not send (NaN, overflow ...).

    ``wire_dtype`` applies to snapshots only ("float16" is lossy); ``spec``, if given, checks a
    snapshot's layout and signature before sending.
    """
    _check_header_numbers(msg)
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
    if isinstance(msg, ThetaSnapshot):
        return _encode_theta(msg, wire_dtype, compression, level, spec)
    if isinstance(msg, Status):
        raw = msgpack.packb(status_body(msg), use_bin_type=True)
        try:
            check_status_body(msgpack.unpackb(raw, raw=False))
        except Rejected as exc:
            raise ValueError(f"refusing to send an invalid Status: {exc}") from None
        return _seal(KIND_STATUS, msg, "", "float32", compression, level, raw, [], {})
    if isinstance(msg, KeyframeSummary):
        return _encode_keyframes(msg, compression, level)
    raise TypeError(f"cannot encode {type(msg).__name__}")


def _encode_theta(msg: ThetaSnapshot, wire_dtype: str, compression: str, level: int,
                  spec: ModelSpec | None) -> bytes:
    if wire_dtype not in WIRE_DTYPES:
        raise ValueError(f"wire_dtype must be one of {WIRE_DTYPES}, got {wire_dtype!r}")
    if not isinstance(msg.signature, str) or not msg.signature:
        raise ValueError("ThetaSnapshot.signature must be the model spec's signature")
    if spec is not None:
        spec.check(msg.tensors)
        if spec.signature() != msg.signature:
            raise ValueError("ThetaSnapshot.signature differs from the given spec")
    dt = _ARRAY_DTYPES[wire_dtype]
    arrays = []
    for name, t in msg.tensors.items():
        a = np.asarray(t)
        if a.dtype.kind != "f":
            raise ValueError(f"tensor {name}: expected floating point values, got {a.dtype}")
        arrays.append((str(name), a, dt))
    raw, table = _pack_arrays(arrays)
    # Check what actually goes out: float16 overflow turns large values into inf.
    sent = np.frombuffer(raw, dtype=dt)
    if sent.size and not np.isfinite(sent).all():
        with np.errstate(over="ignore"):
            bad = [n for n, a, _ in arrays if not np.isfinite(a.astype(dt)).all()]
        raise ValueError(f"non-finite values (NaN/inf, or float16 overflow) in tensors {bad}")
    return _seal(KIND_THETA, msg, msg.signature, wire_dtype, compression, level, raw, table, {})


def _encode_keyframes(msg: KeyframeSummary, compression: str, level: int) -> bytes:
    d = np.asarray(msg.descriptors)
    p = np.asarray(msg.points)
    k = np.asarray(msg.keyframe_index)
    if d.ndim != 2 or d.dtype not in (np.uint8, np.float32):
        raise ValueError("descriptors must be a [P, D] uint8 or float32 array")
    if p.shape != (d.shape[0], 3):
        raise ValueError(f"points must be [P, 3] with P = {d.shape[0]}, got {p.shape}")
    if k.shape != (d.shape[0],) or k.dtype.kind not in "iu" or (k.size and (k.min() < 0 or k.max() > MAX_ROUND)):
        raise ValueError("keyframe_index must be a [P] array of integers in [0, 2**31)")
    if not np.isfinite(p).all() or (d.dtype == np.float32 and not np.isfinite(d).all()):
        raise ValueError("non-finite values in the keyframe summary")
    if not is_int(msg.image_bytes) or msg.image_bytes < 0:
        raise ValueError("image_bytes must be a non-negative int")
    arrays = [
        ("descriptors", d, _ARRAY_DTYPES["uint8" if d.dtype == np.uint8 else "float32"]),
        ("points", p, _ARRAY_DTYPES["float32"]),
        ("keyframe_index", k, _ARRAY_DTYPES["int32"]),
    ]
    if (msg.keypoints is None) != (msg.keyframe_cameras is None):
        raise ValueError("keypoints and keyframe_cameras go together (or neither)")
    if msg.keypoints is not None:
        uv, cams = np.asarray(msg.keypoints), np.asarray(msg.keyframe_cameras)
        if uv.shape != (d.shape[0], 2) or cams.ndim != 2 or cams.shape[1] != KEYFRAME_CAMERA_DIM:
            raise ValueError(f"keypoints must be [P, 2] and keyframe_cameras [K, {KEYFRAME_CAMERA_DIM}]")
        if not (np.isfinite(uv).all() and np.isfinite(cams).all()):
            raise ValueError("non-finite values in the keyframe summary")
        if k.size and k.max() >= cams.shape[0]:
            raise ValueError("keyframe_index beyond the keyframe cameras")
        arrays += [("keypoints", uv, _ARRAY_DTYPES["float32"]), ("keyframe_cameras", cams, _ARRAY_DTYPES["float32"])]
    meta: dict[str, Any] = {"image_bytes": msg.image_bytes}
    if msg.box_from_shared is not None:
        problem = similarity_problem(msg.box_from_shared)
        if problem:
            raise ValueError(f"box_from_shared: {problem}")
        meta["box_from_shared"] = [float(x) for x in np.asarray(msg.box_from_shared, dtype=np.float64).flatten()]
    raw, table = _pack_arrays(arrays)
    return _seal(KIND_KEYFRAMES, msg, "", "float32", compression, level, raw, table, meta)


# =========================================================================== decode


@dataclass
class _Parsed:
    header: Header
    header_map: dict[str, Any]
    arrays: list[tuple[str, np.dtype, tuple[int, ...]]]
    meta: dict[str, Any]
    payload: memoryview


def read_header(data: bytes | bytearray | memoryview, expect: Expectation, *, kind: str | None = None,
                key: ParsedKey | None = None) -> Header:
    """Validate everything but the payload (cheap; no large allocation). Raises Rejected.

    Useful in a Zenoh callback to route raw bytes by (sender, round) and leave the full
    :func:`decode` to another thread.
    """
    return _parse(data, expect, kind, key).header


def decode(data: bytes | bytearray | memoryview, expect: Expectation, *, kind: str | None = None,
           key: ParsedKey | None = None) -> Message:
    """Decode and validate a received frame. Raises only :class:`Rejected`.

    ``kind`` ("theta", "status", "keyframes") refuses any other kind with ``bad_kind``; ``key``
    (the parsed key the bytes arrived on) must agree with the header's sender and round.
    """
    try:
        parsed = _parse(data, expect, kind, key)
        return _decode_body(parsed, expect)
    except Rejected:
        raise
    except Exception as exc:  # a bug in a check must still never crash the receiver
        raise Rejected("garbage", f"unexpected {type(exc).__name__}: {exc}") from None


def _parse(data: Any, expect: Expectation, kind: str | None, key: ParsedKey | None) -> _Parsed:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise Rejected("garbage", f"expected bytes, got {type(data).__name__}")
    view = memoryview(data).cast("B")
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
    _, header_length = _PREFIX.unpack_from(view, 0)
    if header_length > expect.max_header_bytes:
        raise Rejected("too_large", f"header of {header_length} bytes > cap {expect.max_header_bytes}")
    if PREFIX_LENGTH + header_length > n:
        raise Rejected("bad_length", f"header of {header_length} bytes does not fit in {n} bytes")
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

    # schema first: another version may legitimately have other fields
    schema = h.get("schema")
    if not is_int(schema):
        raise Rejected("bad_header", "schema version missing or not an integer")
    if schema != SCHEMA_VERSION:
        raise Rejected("bad_schema", f"schema {schema}, we speak {SCHEMA_VERSION}")
    if set(h) != set(HEADER_FIELDS):
        missing = sorted(set(HEADER_FIELDS) - set(h))
        extra = sorted(str(k)[:32] for k in set(h) - set(HEADER_FIELDS))
        raise Rejected("bad_header", f"missing {missing} unexpected {extra}")

    msg_kind = h["kind"]
    if msg_kind not in KINDS:
        raise Rejected("bad_kind", f"unknown kind {str(msg_kind)[:32]!r}")
    if kind is not None and msg_kind != kind:
        raise Rejected("bad_kind", f"got {msg_kind}, expected {kind}")

    swarm = h["swarm"]
    if not isinstance(swarm, str):
        raise Rejected("bad_header", "swarm is not a string")
    if swarm != expect.swarm:
        raise Rejected("wrong_swarm", f"swarm {swarm[:64]!r}, we are {expect.swarm!r}")

    sender = h["sender"]
    if not is_int(sender) or not 0 <= sender <= MAX_ROUND:
        raise Rejected("unknown_sender", f"sender {str(sender)[:32]!r} is not a robot id")
    if expect.allowed_senders is not None and sender not in expect.allowed_senders:
        raise Rejected("unknown_sender", f"sender {sender} not in {sorted(expect.allowed_senders)}")
    if key is not None and key.robot_id != sender:
        raise Rejected("sender_mismatch", f"header says sender {sender}, key says {key.robot_id}")

    for name in ("round", "epoch"):
        v = h[name]
        if not is_int(v) or not 0 <= v <= MAX_ROUND:
            raise Rejected("bad_round", f"{name} {str(v)[:32]!r} is not an integer in [0, {MAX_ROUND}]")
    if key is not None and key.round is not None and key.round != h["round"]:
        raise Rejected("bad_round", f"header says round {h['round']}, key says {key.round}")

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

    wire_dtype, compression = h["wire_dtype"], h["compression"]
    if wire_dtype not in WIRE_DTYPES or compression not in COMPRESSIONS:
        raise Rejected("bad_encoding", f"dtype {str(wire_dtype)[:32]!r} compression {str(compression)[:32]!r}")
    if msg_kind != KIND_THETA and wire_dtype != "float32":
        raise Rejected("bad_encoding", f"{msg_kind} messages are not quantised")

    raw_length, payload_length = h["raw_length"], h["payload_length"]
    if not is_int(raw_length) or not is_int(payload_length) or raw_length < 0 or payload_length < 0:
        raise Rejected("bad_header", "lengths must be non-negative integers")
    actual_payload = n - PREFIX_LENGTH - header_length
    if payload_length != actual_payload:
        raise Rejected("bad_length", f"header says {payload_length} payload bytes, got {actual_payload}")
    if raw_length > expect.max_decompressed_bytes:
        raise Rejected("too_large", f"declares {raw_length} bytes > cap {expect.max_decompressed_bytes}")
    if compression == "none" and raw_length != payload_length:
        raise Rejected("bad_length", "uncompressed payload with raw_length != payload_length")

    checksum = h["checksum"]
    if not isinstance(checksum, str) or len(checksum) != _CHECKSUM_HEX_LENGTH:
        raise Rejected("bad_header", "checksum is not a 16-character hex string")

    arrays = _check_array_table(h["arrays"], msg_kind, wire_dtype, expect)
    expected_raw = sum(dt.itemsize * math.prod(shape) for _, dt, shape in arrays)
    if msg_kind == KIND_STATUS:
        if raw_length > _MAX_STATUS_BYTES:
            raise Rejected("too_large", f"status body of {raw_length} bytes")
    elif raw_length != expected_raw:
        raise Rejected("bad_length", f"arrays need {expected_raw} bytes, header declares {raw_length}")

    meta = h["meta"]
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

    header = Header(
        schema=schema, kind=msg_kind, swarm=swarm, sender=sender, round=h["round"], epoch=h["epoch"],
        signature=signature, wire_dtype=wire_dtype, compression=compression, raw_length=raw_length,
        payload_length=payload_length, checksum=checksum,
    )
    return _Parsed(header, h, arrays, meta, view[PREFIX_LENGTH + header_length :])


def _check_array_table(table: Any, msg_kind: str, wire_dtype: str,
                       expect: Expectation) -> list[tuple[str, np.dtype, tuple[int, ...]]]:
    if not isinstance(table, list):
        raise Rejected("bad_header", "arrays is not a list")
    if len(table) > expect.max_tensors:
        raise Rejected("too_large", f"{len(table)} arrays > cap {expect.max_tensors}")
    entries = []
    for entry in table:
        if (not isinstance(entry, list) or len(entry) != 3 or not isinstance(entry[0], str)
                or entry[1] not in _ARRAY_DTYPES or not isinstance(entry[2], list) or len(entry[2]) > 8
                or not all(is_int(d) and 0 <= d <= MAX_ROUND for d in entry[2])):
            raise Rejected("bad_shape", f"malformed array entry {str(entry)[:80]}")
        entries.append((entry[0], entry[1], tuple(entry[2])))

    if msg_kind == KIND_STATUS:
        if entries:
            raise Rejected("bad_shape", "status messages carry no arrays")
        return []

    if msg_kind == KIND_THETA:
        spec = expect.spec
        assert spec is not None  # checked with the signature
        if len(entries) != len(spec.params):
            raise Rejected("bad_shape", f"{len(entries)} tensors, the spec has {len(spec.params)}")
        for (name, dtype, shape), p in zip(entries, spec.params):
            if name != p.name or dtype != wire_dtype or shape != p.shape:
                raise Rejected("bad_shape", f"tensor {name[:64]!r} {dtype} {list(shape)[:8]}, "
                                            f"spec wants {p.name!r} {wire_dtype} {list(p.shape)}")
        return [(name, _ARRAY_DTYPES[dtype], shape) for name, dtype, shape in entries]

    # keyframes
    names = [e[0] for e in entries]
    if names not in (list(KEYFRAME_ARRAYS[:3]), list(KEYFRAME_ARRAYS)):
        raise Rejected("bad_shape", f"keyframe arrays {names[:6]}, want {', '.join(KEYFRAME_ARRAYS[:3])}"
                                    f" [, {', '.join(KEYFRAME_ARRAYS[3:])}]")
    (_, d_dtype, d_shape), (_, p_dtype, p_shape), (_, k_dtype, k_shape) = entries[:3]
    if d_dtype not in ("uint8", "float32") or p_dtype != "float32" or k_dtype != "int32":
        raise Rejected("bad_shape", "keyframe dtypes must be uint8|float32, float32, int32")
    if len(d_shape) != 2 or not 1 <= d_shape[1] <= expect.max_descriptor_dim:
        raise Rejected("bad_shape", f"descriptors shape {list(d_shape)}")
    count = d_shape[0]
    if p_shape != (count, 3) or k_shape != (count,):
        raise Rejected("bad_shape", f"points {list(p_shape)} / keyframe_index {list(k_shape)} vs P={count}")
    if count > expect.max_keyframe_points:
        raise Rejected("too_large", f"{count} keyframe points > cap {expect.max_keyframe_points}")
    if len(entries) == 5:
        (_, uv_dtype, uv_shape), (_, c_dtype, c_shape) = entries[3:]
        if uv_dtype != "float32" or c_dtype != "float32":
            raise Rejected("bad_shape", "keypoints and keyframe_cameras must be float32")
        if uv_shape != (count, 2) or len(c_shape) != 2 or c_shape[1] != KEYFRAME_CAMERA_DIM:
            raise Rejected("bad_shape", f"keypoints {list(uv_shape)} / keyframe_cameras {list(c_shape)[:4]} vs P={count}")
        if c_shape[0] > expect.max_keyframes:
            raise Rejected("too_large", f"{c_shape[0]} keyframes > cap {expect.max_keyframes}")
    return [(name, _ARRAY_DTYPES[dtype], shape) for name, dtype, shape in entries]


def _decompress(parsed: _Parsed) -> bytes | memoryview:
    h = parsed.header
    payload = parsed.payload
    if h.compression == "none":
        return payload
    try:
        frame = zstandard.get_frame_parameters(payload)
    except zstandard.ZstdError as exc:
        raise Rejected("bad_encoding", f"not a zstd frame: {exc}") from None
    if frame.window_size > _MAX_WINDOW:
        raise Rejected("decompression_bomb", f"zstd window of {frame.window_size} bytes")
    dctx = zstandard.ZstdDecompressor(max_window_size=_MAX_WINDOW)
    declared = frame.content_size
    if declared == zstandard.CONTENTSIZE_UNKNOWN:
        # Probe with a bounded read: one byte more than declared means the frame lies.
        try:
            with dctx.stream_reader(payload, read_across_frames=False) as reader:
                probe = reader.read(h.raw_length + 1)
        except zstandard.ZstdError as exc:
            raise Rejected("bad_encoding", f"corrupt zstd frame: {exc}") from None
        if len(probe) > h.raw_length:
            raise Rejected("decompression_bomb", f"zstd frame expands beyond the declared {h.raw_length} bytes")
        del probe
    elif declared > h.raw_length:
        raise Rejected("decompression_bomb", f"zstd frame declares {declared} bytes, header {h.raw_length}")
    elif declared != h.raw_length:
        raise Rejected("bad_length", f"zstd frame declares {declared} bytes, header {h.raw_length}")
    try:
        raw = dctx.decompress(payload, max_output_size=h.raw_length, allow_extra_data=False)
    except zstandard.ZstdError as exc:
        raise Rejected("bad_encoding", f"corrupt zstd frame: {exc}") from None
    if len(raw) != h.raw_length:
        raise Rejected("bad_length", f"decompressed {len(raw)} bytes, header says {h.raw_length}")
    return raw


def _decode_body(parsed: _Parsed, expect: Expectation) -> Message:
    h = parsed.header
    if frame_checksum(parsed.header_map, parsed.payload) != h.checksum:
        raise Rejected("bad_checksum", "header+payload checksum differs")
    raw = _decompress(parsed)

    if h.kind == KIND_STATUS:
        try:
            body = msgpack.unpackb(raw, raw=False, strict_map_key=True, max_str_len=1024, max_bin_len=0,
                                   max_ext_len=0, max_array_len=4096, max_map_len=256)
        except Exception as exc:
            raise Rejected("bad_field", f"status body is not valid msgpack: {type(exc).__name__}") from None
        fields = check_status_body(body)
        return Status(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch, header=h, **fields)

    arrays: dict[str, np.ndarray] = {}
    offset = 0
    for name, dt, shape in parsed.arrays:
        count = math.prod(shape)
        a = np.frombuffer(raw, dtype=dt, count=count, offset=offset).reshape(shape)
        offset += count * dt.itemsize
        if dt.kind == "f" and a.size and not np.isfinite(a).all():
            raise Rejected("non_finite", f"NaN or inf in {name[:64]!r}")
        # own, writable, native-endian copies; float32 bits are preserved exactly
        arrays[name] = a.astype(dt.newbyteorder("=") if dt.kind != "f" else np.float32)

    if h.kind == KIND_THETA:
        return ThetaSnapshot(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch,
                             signature=h.signature, tensors=arrays, header=h)
    index = arrays["keyframe_index"]
    if index.size and index.min() < 0:
        raise Rejected("bad_field", "negative keyframe index")
    cams = arrays.get("keyframe_cameras")
    if cams is not None:
        if index.size and index.max() >= len(cams):
            raise Rejected("bad_field", f"keyframe index {int(index.max())} beyond the {len(cams)} keyframe cameras")
        if len(cams) and not (cams[:, 12:14] > 0).all():
            raise Rejected("bad_field", "keyframe focal lengths must be positive")
    return KeyframeSummary(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch,
                           descriptors=arrays["descriptors"], points=arrays["points"],
                           keyframe_index=index, image_bytes=parsed.meta["image_bytes"],
                           keypoints=arrays.get("keypoints"), keyframe_cameras=cams, header=h,
                           box_from_shared=_meta_box(parsed.meta))


def _meta_box(meta: dict[str, Any]) -> np.ndarray | None:
    box = meta.get("box_from_shared")
    return None if box is None else np.array(box, dtype=np.float64).reshape(4, 4)
