"""Shared test material: a small model, valid messages, and forged malformed frames.

Used both by the unit tests and by the rogue peer process (tests/protocol/peers.py), so every
malformed kind is defined once, with the reason a receiver must give for it.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

import msgpack
import numpy as np
import zstandard

from protocol import codec
from protocol.keys import Keys
from protocol.messages import Alignment, KeyframeSummary, ModelSpec, Status, ThetaSnapshot

SWARM = "testswarm"
SENDER = 1
ROUND = 5
ALLOWED = frozenset({0, 1, 2})


def small_tensors(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "grid.table": rng.standard_normal((64, 2)).astype(np.float32),
        "mlp.0.weight": rng.standard_normal((8, 4)).astype(np.float32),
        "mlp.0.bias": rng.standard_normal((8,)).astype(np.float32),
    }


def small_spec() -> ModelSpec:
    return ModelSpec.from_tensors(small_tensors(), {"levels": 4, "width": 8})


def expectation(**kw: Any) -> codec.Expectation:
    kw.setdefault("allowed_senders", ALLOWED)
    return codec.Expectation(SWARM, small_spec(), **kw)


def snapshot(sender: int = SENDER, round: int = ROUND, seed: int = 0, swarm: str = SWARM) -> ThetaSnapshot:
    return ThetaSnapshot(swarm, sender, round, 0, small_spec().signature(), small_tensors(seed))


def valid_frame(**kw: Any) -> bytes:
    return codec.encode(snapshot(**kw))


def status_message(**kw: Any) -> Status:
    """A valid Status (any field can be overridden)."""
    fields = dict(swarm=SWARM, sender=2, round=7, epoch=3, reference=0, phase="train", loss=0.25, psnr=None,
                  pose=[0.0, 0.1, -0.2, 0.3, 1.0, 2.0, -3.0], neighbours_heard=[1], bytes_in=1000, bytes_out=2000,
                  rejected={"wrong_swarm": 2}, alignment=Alignment.IDENTITY, alignment_detail="", wall_time=12.5, seconds_compute=3.0,
                  seconds_wait=0.5)
    fields.update(kw)
    return Status(**fields)


def keyframe_summary(descriptor_dtype=np.uint8, points: int = 50) -> KeyframeSummary:
    """A valid keyframe summary without keypoints or cameras."""
    rng = np.random.default_rng(3)
    if descriptor_dtype == np.uint8:
        desc = rng.integers(0, 256, (points, 32), dtype=np.uint8)
    else:
        desc = rng.standard_normal((points, 128)).astype(np.float32)
    return KeyframeSummary(SWARM, 1, 0, 0, desc, rng.standard_normal((points, 3)).astype(np.float32),
                           rng.integers(0, 5, points).astype(np.int32), image_bytes=123456)


def keyframe_summary_with_cameras(points: int = 50, keyframes: int = 5) -> KeyframeSummary:
    """A valid keyframe summary with keypoints and keyframe cameras (positive focal lengths)."""
    msg = keyframe_summary(points=points)
    rng = np.random.default_rng(4)
    msg.keypoints = rng.uniform(0, 100, (points, 2)).astype(np.float32)
    cams = rng.standard_normal((keyframes, 16)).astype(np.float32)
    cams[:, 12:14] = 90.0  # focal lengths
    msg.keyframe_cameras = cams
    return msg


def split_frame(data: bytes) -> tuple[dict[str, Any], bytes]:
    """(header map, payload) of a frame, without validation."""
    (header_length,) = struct.unpack_from("<I", data, 4)
    header = msgpack.unpackb(data[8 : 8 + header_length], raw=False)
    return header, data[8 + header_length :]


class Packed(bytes):
    """A value already packed as msgpack: lets a forged map hold what msgpack.packb would not write."""


def pack_map(fields: dict) -> bytes:
    """A msgpack map of ``fields``, in order; :class:`Packed` values, at any depth, go in as they are."""
    return _container_head(len(fields), 0x80, b"\xde", b"\xdf") + b"".join(
        _pack(k) + _pack(v) for k, v in fields.items())


def _pack(value: Any) -> bytes:
    if isinstance(value, Packed):
        return bytes(value)
    if isinstance(value, dict):
        return pack_map(value)
    if isinstance(value, list) and any(isinstance(v, (Packed, list, dict)) for v in value):
        return _container_head(len(value), 0x90, b"\xdc", b"\xdd") + b"".join(_pack(v) for v in value)
    return msgpack.packb(value, use_bin_type=True)


def _container_head(n: int, fix: int, head16: bytes, head32: bytes) -> bytes:
    """msgpack's length prefix of an array or map: fixarray/fixmap, then 16- and 32-bit forms."""
    if n < 16:
        return bytes([fix | n])
    return head16 + struct.pack(">H", n) if n < 2**16 else head32 + struct.pack(">I", n)


def deep_list(depth: int) -> Packed:
    """``[[[...[0]...]]]``, ``depth`` lists deep: msgpack unpacks up to 1024 levels."""
    return Packed(b"\x91" * depth + b"\x00")


def frame_of(packed_header: bytes, payload: bytes) -> bytes:
    """Magic, length prefix, an already packed header and the payload."""
    return codec.MAGIC + struct.pack("<I", len(packed_header)) + packed_header + payload


def reframe(data: bytes, *, raw: bytes | None = None, payload: bytes | None = None, fix_checksum: bool = True,
            **changes: Any) -> bytes:
    """Rewrite a valid frame: new raw (re-compressed) or wire payload, changed header fields."""
    header, old_payload = split_frame(data)
    if raw is not None:
        payload = zstandard.ZstdCompressor().compress(raw)
        header["raw_length"] = len(raw)
    if payload is not None:
        header["payload_length"] = len(payload)
    else:
        payload = old_payload
    header.update(changes)
    return codec.pack_frame(header, payload, fix_checksum=fix_checksum)


def rle_zstd_frame(total: int, declare_size: bool) -> bytes:
    """A genuine zstd frame of a few KB that expands to ``total`` zero bytes (RLE blocks).

    With ``declare_size`` the frame header states the content size; without, the size is only
    discovered by decompressing (the dangerous kind of bomb).
    """
    block = 128 * 1024  # max block size for a 128 KiB window
    assert total % block == 0
    out = bytearray(struct.pack("<I", 0xFD2FB528))
    if declare_size:
        out += bytes([0xC0, 0x38]) + struct.pack("<Q", total)  # 8-byte content size, window 2**17
    else:
        out += bytes([0x00, 0x38])  # no content size, window 2**17
    n = total // block
    for i in range(n):
        last = 1 if i == n - 1 else 0
        out += (last | (1 << 1) | (block << 3)).to_bytes(3, "little") + b"\x00"  # RLE block of 0x00
    return bytes(out)


def raw_of(tensors: dict[str, np.ndarray]) -> bytes:
    return b"".join(np.ascontiguousarray(t, dtype="<f4").tobytes() for t in tensors.values())


def malformed_cases() -> list[tuple[str, str, bytes, int]]:
    """(name, expected reason, frame, robot id of the key it is published on).

    Every frame claims round ROUND; all are published on theta/<id>/ROUND.
    """
    good = valid_frame()
    spec = small_spec()
    nan = small_tensors()
    nan["mlp.0.bias"][3] = np.nan
    inf = small_tensors()
    inf["grid.table"][10, 1] = -np.inf
    other_spec = ModelSpec(spec.params, {"levels": 5, "width": 8})
    wrong_shapes = {"grid.table": np.zeros((32, 4), np.float32), "mlp.0.weight": np.zeros((8, 4), np.float32),
                    "mlp.0.bias": np.zeros((8,), np.float32)}
    header, payload = split_frame(good)
    flipped = bytearray(good)
    flipped[-5] ^= 0x01
    rng = np.random.default_rng(7)
    cases = [
        ("wrong swarm", "wrong_swarm", valid_frame(swarm="otherswarm"), SENDER),
        ("wrong signature", "bad_signature",
         codec.encode(ThetaSnapshot(SWARM, SENDER, ROUND, 0, other_spec.signature(), small_tensors())), SENDER),
        ("wrong shape", "bad_shape",
         codec.encode(ThetaSnapshot(SWARM, SENDER, ROUND, 0, spec.signature(), wrong_shapes)), SENDER),
        ("truncated", "bad_length", good[:-7], SENDER),
        ("padded", "bad_length", good + b"\x00", SENDER),
        ("bad checksum", "bad_checksum", bytes(flipped), SENDER),
        ("NaN", "non_finite", reframe(good, raw=raw_of(nan)), SENDER),
        ("inf", "non_finite", reframe(good, raw=raw_of(inf)), SENDER),
        ("random garbage", "bad_magic", rng.bytes(300), SENDER),
        ("header not msgpack", "garbage", b"DNRF" + struct.pack("<I", 4) + b"\xc1\xc1\xc1\xc1", SENDER),
        ("bomb, declared size", "decompression_bomb",
         reframe(good, payload=rle_zstd_frame(2**31, True)), SENDER),
        ("bomb, undeclared size", "decompression_bomb",
         reframe(good, payload=rle_zstd_frame(2**30 + 2**17, False)), SENDER),
        ("declares too much", "too_large", reframe(good, raw_length=2**40), SENDER),
        ("unknown sender", "unknown_sender", valid_frame(sender=9), 9),
        ("sender differs from key", "sender_mismatch", good, 0),
        ("future schema", "bad_schema", reframe(good, schema=99), SENDER),
        ("negative round", "bad_round", reframe(good, round=-1), SENDER),
        ("round differs from key", "bad_round", valid_frame(round=ROUND + 1), SENDER),
        ("unknown dtype", "bad_encoding", reframe(good, wire_dtype="int8"), SENDER),
        ("unknown compression", "bad_encoding", reframe(good, compression="lz4"), SENDER),
        ("unknown kind", "bad_kind", reframe(good, kind="weights"), SENDER),
        ("missing field", "bad_header",
         codec.pack_frame({k: v for k, v in header.items() if k != "meta"}, payload), SENDER),
    ]
    return cases


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def keys() -> Keys:
    return Keys(SWARM)
