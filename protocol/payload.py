"""Reading a frame's payload once its header passed: checksum, bounded decompression, body.

The checksum is verified before decompressing; decompression refuses any zstd frame that
declares or produces more than the header says, so a decompression bomb never allocates. Then
the body becomes a message: a status map checked field by field, or arrays checked for NaN/inf
and, for keyframes, for indices and focal lengths. Pure Python + numpy + msgpack + zstandard.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import zstandard

from protocol.array_table import unpack_arrays
from protocol.compression import check_coded_values
from protocol.frame import frame_checksum
from protocol.header import ParsedFrame
from protocol.messages import (
    KIND_STATUS,
    KIND_THETA,
    KeyframeSummary,
    Message,
    Rejected,
    Status,
    ThetaSnapshot,
    check_status_body,
)

_MAX_WINDOW = 1 << 27  # zstd window cap (128 MiB), zstd's own default limit


def decode_payload(parsed: ParsedFrame) -> Message:
    """The message of a frame whose header passed :func:`protocol.header.parse_frame`."""
    h = parsed.header
    if frame_checksum(parsed.header_map, parsed.payload) != h.checksum:
        raise Rejected("bad_checksum", "header+payload checksum differs")
    raw = _decompress(parsed)
    if h.kind == KIND_STATUS:
        return _status(raw, parsed)
    arrays = unpack_arrays(raw, parsed.arrays)
    if h.kind == KIND_THETA and parsed.coded is not None:
        assert parsed.spec is not None  # a snapshot's table was checked against it
        return ThetaSnapshot(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch, signature=h.signature,
                             tensors={}, header=h, coded=check_coded_values(arrays, parsed.coded, parsed.spec))
    if h.kind == KIND_THETA:
        return ThetaSnapshot(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch,
                             signature=h.signature, tensors=arrays, header=h)
    return _keyframes(arrays, parsed)


def _decompress(parsed: ParsedFrame) -> bytes | memoryview:
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


def _status(raw: bytes | memoryview, parsed: ParsedFrame) -> Status:
    h = parsed.header
    try:
        body = msgpack.unpackb(raw, raw=False, strict_map_key=True, max_str_len=1024, max_bin_len=0,
                               max_ext_len=0, max_array_len=4096, max_map_len=256)
    except Exception as exc:
        raise Rejected("bad_field", f"status body is not valid msgpack: {type(exc).__name__}") from None
    fields = check_status_body(body)
    return Status(swarm=h.swarm, sender=h.sender, round=h.round, epoch=h.epoch, header=h, **fields)


def _keyframes(arrays: dict[str, np.ndarray], parsed: ParsedFrame) -> KeyframeSummary:
    """A keyframe summary whose indices point at its cameras and whose focal lengths are positive."""
    h = parsed.header
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
