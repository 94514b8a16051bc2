"""Wire format: encode messages to bytes, and decode received bytes with strict validation.

A frame is a magic, a msgpack header and a (zstd) payload with a checksum (layout in
:mod:`protocol.frame`). The payload of a ``theta`` or ``keyframes`` message is the arrays listed
in the header's array table (:mod:`protocol.array_table`); the payload of a ``status`` message
is a msgpack map.

API::

    encode(msg, *, wire_dtype="float32", compression="zstd", level=3, spec=None) -> bytes
    decode(data, expect, *, kind=None, key=None) -> ThetaSnapshot | Status | KeyframeSummary
    read_header(data, expect, *, kind=None, key=None) -> Header   # cheap checks only

``decode`` checks everything it can from the few header bytes *before* any large allocation
(:mod:`protocol.header`): sizes against the caps of :class:`Expectation`, schema, kind, swarm,
sender, round, signature, encoding, tensor names/dtypes/shapes against the model spec, and that
the declared sizes add up. Only then does it verify the checksum, decompress (refusing any zstd
frame that declares or produces more than the header says, so a decompression bomb never
allocates) and check that all values are finite (:mod:`protocol.payload`). Every failure raises
:class:`~protocol.messages.Rejected` with a reason code; no other exception escapes ``decode``
for any input bytes.

``float32`` on the wire round-trips bit-identically; ``float16`` halves the bytes and is lossy
(relative error ~5e-4, values beyond +-65504 are refused at encode time).

Pure Python + numpy + msgpack + zstandard: no zenoh, no torch.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import msgpack
import numpy as np
import zstandard

from protocol.array_table import ARRAY_DTYPES, pack_arrays
from protocol.compression import coded_arrays, coded_meta
from protocol.expectation import MiB, Expectation
from protocol.frame import (
    HEADER_FIELDS,
    MAGIC,
    PREFIX_LENGTH,
    ZERO_CHECKSUM,
    frame_bytes,
    frame_checksum,
    pack_frame,
)
from protocol.header import parse_frame
from protocol.keys import ParsedKey, validate_swarm
from protocol.messages import (
    COMPRESSIONS,
    KEYFRAME_CAMERA_DIM,
    KIND_KEYFRAMES,
    KIND_STATUS,
    KIND_THETA,
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
    similarity_problem,
    status_body,
)
from protocol.payload import decode_payload

__all__ = [
    "HEADER_FIELDS", "MAGIC", "PREFIX_LENGTH", "MiB", "Expectation", "frame_checksum", "pack_frame",
    "encode", "decode", "read_header", "UNEXPECTED",
]


# =========================================================================== encode


def _check_header_numbers(msg: Message) -> None:
    validate_swarm(msg.swarm)
    for name in ("sender", "round", "epoch"):
        v = getattr(msg, name)
        if not is_int(v) or not 0 <= v <= MAX_ROUND:
            raise ValueError(f"{type(msg).__name__}.{name} must be an integer in [0, {MAX_ROUND}], got {v!r}")


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
        "checksum": ZERO_CHECKSUM,
        "arrays": arrays,
        "meta": meta,
    }
    header["checksum"] = frame_checksum(header, payload)
    return frame_bytes(header, payload)


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
    if msg.coded is not None:
        return _encode_coded_theta(msg, compression, level, spec)
    if spec is not None:
        spec.check(msg.tensors)
        if spec.signature() != msg.signature:
            raise ValueError("ThetaSnapshot.signature differs from the given spec")
    dt = ARRAY_DTYPES[wire_dtype]
    arrays = []
    for name, t in msg.tensors.items():
        a = np.asarray(t)
        if a.dtype.kind != "f":
            raise ValueError(f"tensor {name}: expected floating point values, got {a.dtype}")
        arrays.append((str(name), a, dt))
    raw, table = pack_arrays(arrays)
    # Check what actually goes out: float16 overflow turns large values into inf.
    sent = np.frombuffer(raw, dtype=dt)
    if sent.size and not np.isfinite(sent).all():
        with np.errstate(over="ignore"):
            bad = [n for n, a, _ in arrays if not np.isfinite(a.astype(dt)).all()]
        raise ValueError(f"non-finite values (NaN/inf, or float16 overflow) in tensors {bad}")
    return _seal(KIND_THETA, msg, msg.signature, wire_dtype, compression, level, raw, table, {})


def _encode_coded_theta(msg: ThetaSnapshot, compression: str, level: int, spec: ModelSpec | None) -> bytes:
    """A compressed snapshot (:mod:`protocol.compression`): its arrays as laid out for the spec."""
    if spec is None or spec.signature() != msg.signature:
        raise ValueError("a compressed snapshot needs the model spec it was made for")
    arrays = [(name, np.asarray(a), ARRAY_DTYPES[dtype]) for name, a, dtype in coded_arrays(msg.coded, spec)]
    if any(dt.kind == "f" and a.size and not np.isfinite(a).all() for _, a, dt in arrays):
        raise ValueError("non-finite int8 scales in a compressed snapshot")
    raw, table = pack_arrays(arrays)
    return _seal(KIND_THETA, msg, msg.signature, "float32", compression, level, raw, table, coded_meta(msg.coded))


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
        ("descriptors", d, ARRAY_DTYPES["uint8" if d.dtype == np.uint8 else "float32"]),
        ("points", p, ARRAY_DTYPES["float32"]),
        ("keyframe_index", k, ARRAY_DTYPES["int32"]),
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
        arrays += [("keypoints", uv, ARRAY_DTYPES["float32"]), ("keyframe_cameras", cams, ARRAY_DTYPES["float32"])]
    meta: dict[str, Any] = {"image_bytes": msg.image_bytes}
    if msg.box_from_shared is not None:
        problem = similarity_problem(msg.box_from_shared)
        if problem:
            raise ValueError(f"box_from_shared: {problem}")
        meta["box_from_shared"] = [float(x) for x in np.asarray(msg.box_from_shared, dtype=np.float64).flatten()]
    raw, table = pack_arrays(arrays)
    return _seal(KIND_KEYFRAMES, msg, "", "float32", compression, level, raw, table, meta)


# =========================================================================== decode

#: Start of the detail of a refusal that came from a bug in a check, not from the check itself.
UNEXPECTED = "unexpected"


@contextmanager
def _only_rejected() -> Iterator[None]:
    """Turn any other exception into Rejected: a bug in a check must still never crash the receiver."""
    try:
        yield
    except Rejected:
        raise
    except Exception as exc:
        raise Rejected("garbage", f"{UNEXPECTED} {type(exc).__name__} in a check") from None


def read_header(data: bytes | bytearray | memoryview, expect: Expectation, *, kind: str | None = None,
                key: ParsedKey | None = None) -> Header:
    """Validate everything but the payload (cheap; no large allocation). Raises only Rejected.

    Useful in a Zenoh callback to route raw bytes by (sender, round) and leave the full
    :func:`decode` to another thread.
    """
    with _only_rejected():
        return parse_frame(data, expect, kind, key).header


def decode(data: bytes | bytearray | memoryview, expect: Expectation, *, kind: str | None = None,
           key: ParsedKey | None = None) -> Message:
    """Decode and validate a received frame. Raises only :class:`Rejected`.

    ``kind`` ("theta", "status", "keyframes") refuses any other kind with ``bad_kind``; ``key``
    (the parsed key the bytes arrived on) must agree with the header's sender and round.
    """
    with _only_rejected():
        return decode_payload(parse_frame(data, expect, kind, key))
