"""Frames an attacker would write, one per finding of the review: each ends as Rejected with its reason.

Both entry points are tried: ``read_header`` (called in a Zenoh callback, so an escaping exception
would kill the callback) and ``decode``, which must give the real reason, not the catch-all.
"""

from __future__ import annotations

import time
import tracemalloc
import warnings

import msgpack
import numpy as np
import pytest
import zstandard

from protocol import codec
from protocol.expectation import MiB
from protocol.messages import Rejected
from protocol.untrusted import describe
from tests.protocol.helpers import (Packed, deep_list, expectation, frame_of, keyframe_summary,
                                    keyframe_summary_with_cameras, pack_map, rle_zstd_frame, split_frame,
                                    status_message, valid_frame)


def _reason(data: bytes, entry=codec.decode, **kw) -> Rejected:
    with pytest.raises(Rejected) as exc:
        entry(data, expectation(**kw))
    return exc.value


def _with_header(**changes) -> bytes:
    header, payload = split_frame(valid_frame())
    return codec.pack_frame(dict(header, **changes), payload)


@pytest.mark.parametrize("entry", [codec.read_header, codec.decode])
@pytest.mark.parametrize("dtype", [["float32"], {"float32": 1}, [], None, 3])
def test_array_entry_with_an_unhashable_or_odd_dtype_is_bad_shape(entry, dtype):
    header, _ = split_frame(valid_frame())
    table = [list(row) for row in header["arrays"]]
    table[0][1] = dtype
    exc = _reason(_with_header(arrays=table), entry)
    assert exc.reason == "bad_shape" and "malformed array entry" in exc.detail, exc


@pytest.mark.parametrize("entry", [codec.read_header, codec.decode])
@pytest.mark.parametrize("field,reason", [
    ("kind", "bad_kind"), ("swarm", "bad_header"), ("sender", "unknown_sender"), ("round", "bad_round"),
    ("epoch", "bad_round"), ("signature", "bad_header"), ("wire_dtype", "bad_encoding"),
    ("compression", "bad_encoding"), ("raw_length", "bad_header"), ("checksum", "bad_header"),
    ("arrays", "bad_shape"), ("meta", "bad_header")])
def test_deeply_nested_header_value_is_refused_for_its_fields_reason(entry, field, reason):
    header, payload = split_frame(valid_frame())
    deep = deep_list(1000) if field != "arrays" else Packed(b"\x91" + deep_list(999))  # an entry 1000 deep
    packed = pack_map(dict(header, **{field: deep}))
    assert len(msgpack.unpackb(packed)) == len(header)  # msgpack itself accepts it
    data = frame_of(packed, payload)
    exc = _reason(data, entry)
    assert exc.reason == reason and not exc.detail.startswith(codec.UNEXPECTED) and len(exc.detail) < 300, exc


def test_refusal_details_are_bounded_for_huge_values():
    long_names = [["x" * 4000] * 200, "float32", [1]]  # str() of it is 800 kB before any [:80]
    for changes, reason in [(dict(arrays=[long_names]), "bad_shape"), (dict(kind="k" * 4000), "bad_kind"),
                            (dict(sender=["y" * 4000] * 100), "unknown_sender"),
                            (dict(wire_dtype="z" * 4000, compression=["w" * 4000] * 100), "bad_encoding")]:
        exc = _reason(_with_header(**changes), codec.read_header)
        assert exc.reason == reason and len(exc.detail) < 400, (reason, exc.detail)
    header, payload = split_frame(codec.encode(keyframe_summary()))
    names = [["n" * 4000, dtype, shape] for _, dtype, shape in header["arrays"]]
    exc = _reason(codec.pack_frame(dict(header, arrays=names), payload), codec.read_header)
    assert exc.reason == "bad_shape" and len(exc.detail) < 300, len(exc.detail)
    header, payload = split_frame(codec.encode(status_message(), compression="none"))
    body = dict(msgpack.unpackb(payload), **{f"{i:04d}" + "e" * 1000: 0 for i in range(60)})
    raw = msgpack.packb(body)
    exc = _reason(codec.pack_frame(dict(header, raw_length=len(raw), payload_length=len(raw)), raw))
    assert exc.reason == "bad_field" and len(exc.detail) < 300, len(exc.detail)


def test_describe_never_recurses_and_stays_short():
    deep: list = [0]
    for _ in range(100_000):
        deep = [deep]
    for value in (deep, "s" * 10**6, [["t" * 10**5] * 10] * 1000, {"k": deep}, 2**64, b"\x00" * 10**6, 1.5, None):
        assert len(describe(value)) < 200


@pytest.mark.parametrize("field", ["phase", "alignment"])  # alignment: an enum, whose own error reprs the value
def test_deeply_nested_status_field_is_bad_field(field):
    msg = codec.encode(status_message())
    header, payload = split_frame(msg)
    body = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(payload))
    raw = pack_map(dict(body, **{field: deep_list(1000)}))
    frame = codec.pack_frame(dict(header, compression="none", raw_length=len(raw), payload_length=len(raw)), raw)
    exc = _reason(frame, codec.decode)
    assert exc.reason == "bad_field" and field in exc.detail, exc


def _refused_quickly_in_little_memory(data: bytes, **kw) -> Rejected:
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        exc = _reason(data, **kw)
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert elapsed < 0.5 and peak < 8 * MiB, (exc, elapsed, peak)
    return exc


@pytest.mark.parametrize("declare_size", [True, False])
def test_tiny_keyframe_frame_declaring_hundreds_of_mib_is_too_large_before_allocating(declare_size):
    header, _ = split_frame(codec.encode(keyframe_summary()))
    points, dim = 200_000, 616  # within the point and descriptor-dimension caps
    table = [["descriptors", "float32", [points, dim]], ["points", "float32", [points, 3]],
             ["keyframe_index", "int32", [points]]]
    raw_length = points * (dim * 4 + 12 + 4)  # 473 MiB, under the generic 512 MiB cap
    bomb = rle_zstd_frame(-(-raw_length // 2**17) * 2**17, declare_size)
    data = codec.pack_frame(dict(header, arrays=table, raw_length=raw_length, payload_length=len(bomb)), bomb)
    assert len(data) < 20_000
    exc = _refused_quickly_in_little_memory(data)
    assert exc.reason == "too_large" and "keyframes" in exc.detail, exc


def test_keyframe_and_status_caps_are_the_receivers_to_set():
    summary = codec.encode(keyframe_summary_with_cameras())
    assert codec.decode(summary, expectation()).kind == "keyframes"
    raw_length = split_frame(summary)[0]["raw_length"]
    assert _reason(summary, max_keyframe_bytes=raw_length - 1).reason == "too_large"
    assert codec.decode(summary, expectation(max_keyframe_bytes=raw_length)).kind == "keyframes"
    status = codec.encode(status_message())
    raw_length = split_frame(status)[0]["raw_length"]
    assert _reason(status, max_status_bytes=raw_length - 1).reason == "too_large"
    assert codec.Expectation("s").max_raw_bytes("keyframes") <= 16 * MiB  # a few MB, not 512 MiB
    with pytest.raises(ValueError, match="max_keyframe_bytes"):
        codec.Expectation("s", max_keyframe_bytes=0)


def test_status_bomb_is_too_large_before_decompressing():
    header, _ = split_frame(codec.encode(status_message()))
    bomb = rle_zstd_frame(2**30, False)
    data = codec.pack_frame(dict(header, raw_length=2**20, payload_length=len(bomb)), bomb)
    assert _refused_quickly_in_little_memory(data).reason == "too_large"


@pytest.mark.parametrize("entry", [codec.read_header, codec.decode])
def test_byte_buffers_that_cannot_be_read_as_bytes_are_garbage(entry):
    strided = memoryview(valid_frame() * 2)[::2]  # not contiguous: cannot be cast to bytes
    released = memoryview(bytearray(valid_frame()))
    released.release()
    for data in (strided, released):
        exc = _reason(data, entry)
        assert exc.reason == "garbage" and not exc.detail.startswith(codec.UNEXPECTED), exc


def test_field_box_with_huge_entries_is_bad_field_without_numpy_warnings():
    header, payload = split_frame(codec.encode(keyframe_summary_with_cameras()))
    off_diagonal = np.diag([0.5, 0.5, 0.5, 1.0])
    off_diagonal[0, 1] = 1e200  # the scale is fine (0.5), the rotation check overflows
    for box in [np.diag([d] * 3 + [1.0]) for d in (1e308, 1e200, 1e-300)] + [off_diagonal]:
        box = box.flatten().tolist()
        data = codec.pack_frame(dict(header, meta={"image_bytes": 1, "box_from_shared": box}), payload)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an overflow warning per hostile frame would flood the log
            exc = _reason(data, codec.read_header)
        assert exc.reason == "bad_field" and ("scale" in exc.detail or "rotation" in exc.detail), exc


def test_a_bug_in_a_check_is_still_rejected_from_both_entry_points(monkeypatch):
    import protocol.header

    def broken(*args):
        raise KeyError(list(range(10**6)))  # its str() alone would be megabytes

    monkeypatch.setattr(protocol.header, "_check_kind", broken)
    for entry in (codec.read_header, codec.decode):
        exc = _reason(valid_frame(), entry)
        assert exc.reason == "garbage" and exc.detail.startswith(codec.UNEXPECTED) and len(exc.detail) < 100, exc
