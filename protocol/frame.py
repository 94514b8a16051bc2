"""The frame's byte layout: magic, length prefix, header fields and the checksum over them.

Frame layout (all integers little-endian)::

    b"DNRF"                 4-byte magic
    uint32 header_length
    header                  msgpack map, see HEADER_FIELDS
    payload                 header["payload_length"] bytes, zstd-compressed or raw

The checksum is blake2b with an 8-byte digest over the packed header (with its checksum field
zeroed) followed by the wire payload, so a corrupted header field is caught too (integrity, not
authenticity: use Zenoh TLS for that). Our encoder packs headers canonically; a header packed any
other way fails the checksum.

Both directions use this module: :mod:`protocol.codec` to write frames, :mod:`protocol.header`
to read them. Pure Python + msgpack.
"""

from __future__ import annotations

import hashlib
import struct
from typing import Any, Mapping

import msgpack

MAGIC = b"DNRF"
PREFIX = struct.Struct("<4sI")
PREFIX_LENGTH = PREFIX.size  # 8

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

CHECKSUM_HEX_LENGTH = 16
ZERO_CHECKSUM = "0" * CHECKSUM_HEX_LENGTH


def frame_checksum(header: Mapping[str, Any], payload: bytes | bytearray | memoryview) -> str:
    """blake2b-64 (hex) of the canonically packed header, checksum zeroed, then the payload."""
    digest = hashlib.blake2b(digest_size=8)
    digest.update(msgpack.packb({**header, "checksum": ZERO_CHECKSUM}, use_bin_type=True))
    digest.update(payload)
    return digest.hexdigest()


def frame_bytes(header: Mapping[str, Any], payload: bytes | bytearray) -> bytes:
    """Magic, header length, packed header and payload, as they go on the wire."""
    packed = msgpack.packb(header, use_bin_type=True)
    return b"".join((PREFIX.pack(MAGIC, len(packed)), packed, payload))


def pack_frame(header: Mapping[str, Any], payload: bytes, *, fix_checksum: bool = True) -> bytes:
    """Frame an arbitrary header and payload, unchecked. For tests and fault injection only."""
    header = dict(header)
    if fix_checksum:
        header["checksum"] = frame_checksum(header, payload)
    return frame_bytes(header, payload)
